"""The live side of the server: receivers report in, dashboards watch, transmitters check in.

- ``/ws/receiver``: a receiver daemon. It opens with a ``Hello`` carrying the server's token
  (when one is set), then sends numbered reports
  ``{"seq": n | null, "report": {...}}``. Durable reports (numbered) are stored, then
  acknowledged with ``{"type": "ack", "seq": n}``; a replayed number is acknowledged and skipped.
- ``/ws/dashboard``: read-only fan-out of every update (see ``eventocc.server.hub``).
- ``/ws/transmitter``: a transmitter page's playback status; the same state as
  ``POST /api/transmitter/status`` (``app.state.transmitter_status``).
- REST: receptions (list, one, their bytes), a receiver's kept trajectory, ``/healthz`` and
  ``/metrics`` (Prometheus text format).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
import time
from collections import deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Path, Query, Request, status
from fastapi.responses import PlainTextResponse, Response
from fastapi.websockets import WebSocket, WebSocketDisconnect
from pydantic import BaseModel, TypeAdapter, ValidationError
from starlette.requests import HTTPConnection

from eventocc.occ.report import FrameStats, Hello, MessageReport, PoseReport, ProgressReport, Report
from eventocc.server.api.schemas import TransmitterStatus, TransmitterStatusPublic
from eventocc.server.hub import Hub
from eventocc.server.receptions import Reception, ReceptionStore
from eventocc.server.store import MessageStore

log = logging.getLogger(__name__)

CLOSE_UNAUTHORIZED = 4401
"""No token, or a wrong one."""
CLOSE_BAD_HANDSHAKE = 4400
"""The first message was not a valid ``Hello``, or did not come in time."""
CLOSE_BAD_FRAME = 1007
"""A message that is not a JSON envelope ``{"seq": ..., "report": ...}``."""
CLOSE_STALLED = 1013
"""A dashboard that fell too far behind (it may reconnect)."""
MAX_REASON = 120
"""A close reason must fit in a control frame (123 bytes)."""
HELLO_TIMEOUT_S = 5.0
GOODPUT_WINDOW_S = 60.0
TRANSMITTER_POLL_S = 0.5
"""How often a status POSTed over REST is passed on to the dashboards."""

report_adapter: TypeAdapter[Report] = TypeAdapter(Report)


@dataclass
class LiveState:
    """Everything the live routes share, built in the router's lifespan."""

    hub: Hub
    receptions: ReceptionStore
    messages: MessageStore
    receivers: dict[str, Hello] = field(default_factory=dict)
    """Receivers connected right now, by id."""
    frames_decoded: int = 0
    reports_rejected: int = 0
    stream_seen: dict[tuple[str, int], float] = field(default_factory=dict)
    """(receiver, stream id) -> monotonic time of its first progress report: goodput's start."""
    recent_receptions: deque[tuple[float, int]] = field(default_factory=deque)
    """(monotonic time, bits) of the receptions in the last ``GOODPUT_WINDOW_S``."""

    def goodput_bps(self) -> float:
        """Verified message bits per second over the last ``GOODPUT_WINDOW_S``, all receivers."""
        recent = self.recent_receptions
        while recent and recent[0][0] < time.monotonic() - GOODPUT_WINDOW_S:
            recent.popleft()
        return sum(bits for _, bits in recent) / GOODPUT_WINDOW_S


@asynccontextmanager
async def live_lifespan(app: FastAPI) -> AsyncIterator[None]:
    store = app.state.store
    live = app.state.live = LiveState(Hub(), ReceptionStore(store.path), store)
    watcher = asyncio.create_task(_pass_on_transmitter_status(app, live.hub))
    try:
        yield
    finally:
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watcher
        live.receptions.close()


router = APIRouter(tags=["live"], lifespan=live_lifespan)


def get_live(connection: HTTPConnection) -> LiveState:
    return connection.app.state.live


LiveDep = Annotated[LiveState, Depends(get_live)]


# --- receivers ----------------------------------------------------------------------------------


def token_is_valid(connection: HTTPConnection, hello: Hello) -> bool:
    token = connection.app.state.settings.token
    if token is None:
        return True
    given = (hello.token or "").encode()
    return secrets.compare_digest(given, token.get_secret_value().encode())


async def refuse(websocket: WebSocket, code: int, reason: str) -> None:
    log.warning("refused %s from %s: %s", websocket.url.path, websocket.client, reason)
    await websocket.close(code=code, reason=reason)


async def receive_hello(websocket: WebSocket) -> Hello | None:
    try:
        text = await asyncio.wait_for(websocket.receive_text(), HELLO_TIMEOUT_S)
        return Hello.model_validate_json(text)
    except (TimeoutError, ValidationError, KeyError) as error:
        reason = f"expected a Hello report first: {error}"
        await refuse(websocket, CLOSE_BAD_HANDSHAKE, reason[:MAX_REASON])
        return None


@router.websocket("/ws/receiver")
async def receiver_socket(websocket: WebSocket, live: LiveDep) -> None:
    await websocket.accept()
    hello = await receive_hello(websocket)
    if hello is None:
        return
    if not token_is_valid(websocket, hello):
        await refuse(websocket, CLOSE_UNAUTHORIZED, "missing or wrong token")
        return
    receiver = hello.receiver_id
    last_seq = await asyncio.to_thread(live.receptions.register, receiver)
    await websocket.send_json({"type": "welcome", "last_seq": last_seq})
    live.receivers[receiver] = hello
    announce_receivers(live)
    log.info("receiver %s connected; stored up to its report %d", receiver, last_seq)
    try:
        while True:
            seq, report = await receive_report(websocket, live)
            if report is not None and (seq is None or seq > last_seq):
                await handle_report(live, receiver, seq, report)
            if seq is not None:
                last_seq = max(last_seq, seq)
                await websocket.send_json({"type": "ack", "seq": seq})
    except WebSocketDisconnect:
        pass
    except MalformedFrame as error:
        await refuse(websocket, CLOSE_BAD_FRAME, str(error))
    finally:
        live.receivers.pop(receiver, None)
        live.hub.forget(f"{receiver}:")
        announce_receivers(live)
        log.info("receiver %s disconnected", receiver)


class MalformedFrame(ValueError):
    pass


async def receive_report(websocket: WebSocket, live: LiveState) -> tuple[int | None, Report | None]:
    """One envelope: its number and its report, or None for a report that fails the schema
    (logged, counted and acknowledged anyway, so a bad report cannot jam the receiver's spool)."""
    text = await websocket.receive_text()
    try:
        envelope = json.loads(text)
        seq, body = envelope["seq"], envelope["report"]
        if seq is not None and (not isinstance(seq, int) or seq < 1):
            raise ValueError(f"seq must be a positive integer or null, got {seq!r}")
    except (ValueError, KeyError, TypeError) as error:
        reason = f'expected {{"seq": n, "report": {{...}}}}: {error}'
        raise MalformedFrame(reason[:MAX_REASON]) from None
    try:
        return seq, report_adapter.validate_python(body)
    except ValidationError as error:
        live.reports_rejected += 1
        log.warning("rejected report %s: %s", seq, error)
        return seq, None


async def handle_report(live: LiveState, receiver: str, seq: int | None, report: Report) -> None:
    if isinstance(report, MessageReport):
        live.hub.publish(await store_reception(live, receiver, seq, report))
        return
    if isinstance(report, PoseReport) and seq is not None:
        row = (report.t_us, *report.position, *report.quaternion_xyzw)
        await asyncio.to_thread(live.receptions.add_poses, receiver, seq, [row])
    elif seq is not None:
        await asyncio.to_thread(live.receptions.mark_stored, receiver, seq)
    if isinstance(report, FrameStats) and report.bits_read:
        live.frames_decoded += 1
    topic = f"{receiver}:{report.type}"
    if isinstance(report, ProgressReport):
        live.stream_seen.setdefault((receiver, report.stream_id), time.monotonic())
        topic += f":{report.stream_id}"
    live.hub.publish({"receiver": receiver, **report.model_dump(mode="json")}, topic=topic)


async def store_reception(
    live: LiveState, receiver: str, seq: int | None, report: MessageReport
) -> dict[str, Any]:
    if seq is None:
        raise MalformedFrame("a finished message must be numbered (seq) so it can be acknowledged")
    started = live.stream_seen.pop((receiver, report.stream_id), None)
    goodput = report.size * 8 / (time.monotonic() - started) if started is not None else None
    live.recent_receptions.append((time.monotonic(), report.size * 8))
    uploaded = await asyncio.to_thread(upload_with_digest, live.messages, report.sha256)
    reception = await asyncio.to_thread(
        live.receptions.add,
        receiver=receiver,
        seq=seq,
        name=report.name,
        data=report.data,
        claimed_sha256=report.sha256,
        goodput_bps=goodput,
        message_id=uploaded,
        verified=report.verified,
    )
    live.hub.forget(f"{receiver}:progress:{report.stream_id}")
    log.info(
        "received %r (%d bytes) from %s: %s",
        reception.name,
        reception.size,
        receiver,
        ("verified against the sender's sha256" if report.verified else "unchecked")
        + ("" if uploaded else "; no upload has these bytes"),
    )
    return {"type": "reception", **ReceptionPublic.of(reception).model_dump(mode="json")}


def upload_with_digest(messages: MessageStore, sha256: str) -> str | None:
    """The id of an uploaded message with these bytes, if any (reads the store: off the loop)."""
    return next((m.id for m in messages.messages() if m.sha256 == sha256), None)


def announce_receivers(live: LiveState) -> None:
    live.hub.publish(
        {
            "type": "receivers",
            "receivers": [
                h.model_dump(mode="json", exclude={"token"}) for h in live.receivers.values()
            ],
        },
        topic="receivers",
    )


# --- dashboards and transmitters ------------------------------------------------------------------


@router.websocket("/ws/dashboard")
async def dashboard_socket(websocket: WebSocket, live: LiveDep) -> None:
    await websocket.accept()
    viewer = live.hub.subscribe(f"{websocket.client}")
    tasks = {
        asyncio.create_task(live.hub.serve(viewer, websocket.send_text)),
        asyncio.create_task(_until_closed(websocket)),
        asyncio.create_task(viewer.wait_evicted()),
    }
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        live.hub.unsubscribe(viewer)
    if viewer.evicted:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(websocket.close(CLOSE_STALLED, "too slow, reconnect"), 1.0)


async def _until_closed(websocket: WebSocket) -> None:
    with contextlib.suppress(WebSocketDisconnect):
        while True:
            await websocket.receive_text()  # viewers send nothing we need; this notices them go


@router.websocket("/ws/transmitter")
async def transmitter_socket(websocket: WebSocket, live: LiveDep) -> None:
    await websocket.accept()
    try:
        while True:
            text = await websocket.receive_text()
            try:
                report = TransmitterStatus.model_validate_json(text)
            except ValidationError as error:
                await websocket.send_json({"type": "error", "detail": error.errors()[:3]})
                continue
            latest = TransmitterStatusPublic(**report.model_dump(), received=datetime.now(UTC))
            websocket.app.state.transmitter_status = latest
            live.hub.publish(transmitter_update(latest), topic="transmitter")
    except WebSocketDisconnect:
        pass


def transmitter_update(latest: TransmitterStatusPublic) -> dict[str, Any]:
    return {"type": "transmitter", **latest.model_dump(mode="json")}


async def _pass_on_transmitter_status(app: FastAPI, hub: Hub) -> None:
    """The REST status route only stores the latest status; tell the dashboards when it changes."""
    seen = None
    while True:
        latest = app.state.transmitter_status
        if latest is not None and latest is not seen:
            seen = latest
            hub.publish(transmitter_update(latest), topic="transmitter")
        await asyncio.sleep(TRANSMITTER_POLL_S)


# --- REST -----------------------------------------------------------------------------------------

RECEPTION_ID_PATTERN = r"^[0-9a-f]{12}$"


class ReceptionPublic(BaseModel):
    id: str
    receiver: str
    name: str
    sha256: str
    size: int
    goodput_bps: float | None
    message_id: str | None
    received: datetime
    verified: bool | None
    """The bytes hash to the sha256 their sender sent in-band; False: unchecked (``paper``);
    None: stored before this was recorded."""
    url: str

    @classmethod
    def of(cls, reception: Reception) -> ReceptionPublic:
        fields = {k: getattr(reception, k) for k in cls.model_fields if k != "url"}
        return cls(**fields, url=f"/api/receptions/{reception.id}/content")


class ReceptionsPublic(BaseModel):
    receptions: list[ReceptionPublic]


def get_reception(
    live: LiveDep,
    reception_id: Annotated[str, Path(pattern=RECEPTION_ID_PATTERN, description="Reception id.")],
) -> Reception:
    reception = live.receptions.get(reception_id)
    if reception is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no reception with id {reception_id!r}")
    return reception


ReceptionDep = Annotated[Reception, Depends(get_reception)]


@router.get("/api/receptions")
def read_receptions(
    live: LiveDep, limit: Annotated[int, Query(ge=1, le=1000)] = 100
) -> ReceptionsPublic:
    receptions = live.receptions.receptions(limit)
    return ReceptionsPublic(receptions=[ReceptionPublic.of(r) for r in receptions])


@router.get("/api/receptions/{reception_id}")
def read_reception(reception: ReceptionDep) -> ReceptionPublic:
    return ReceptionPublic.of(reception)


@router.get("/api/receptions/{reception_id}/content", response_class=Response)
def download_reception(reception: ReceptionDep, live: LiveDep) -> Response:
    return Response(
        live.receptions.content(reception),
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{reception.name or reception.id}"'},
    )


@router.get("/api/receivers/{receiver_id}/trajectory", response_class=PlainTextResponse)
def read_trajectory(receiver_id: str, live: LiveDep) -> str:
    """The receiver's kept poses as a TUM file (``t tx ty tz qx qy qz qw``, t in seconds)."""
    lines = [
        f"{t_us // 1_000_000}.{t_us % 1_000_000:06d} " + " ".join(f"{v:.9f}" for v in row)
        for t_us, *row in live.receptions.poses(receiver_id)
    ]
    return "# t tx ty tz qx qy qz qw (T_world_cam, marker frame, metres)\n" + "".join(
        f"{line}\n" for line in lines
    )


@router.get("/healthz")
def health(live: LiveDep) -> dict[str, Any]:
    live.receptions.totals()  # raises (500) if the database is unreachable
    return {"status": "ok", "receivers": len(live.receivers), "dashboards": live.hub.viewer_count}


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(live: LiveDep, request: Request) -> str:
    received, received_bytes = live.receptions.totals()
    samples = [
        (
            "eventocc_receivers_connected",
            "gauge",
            "Receiver daemons connected now.",
            len(live.receivers),
        ),
        (
            "eventocc_dashboard_clients",
            "gauge",
            "Dashboard viewers connected now.",
            live.hub.viewer_count,
        ),
        (
            "eventocc_frames_decoded_total",
            "counter",
            "Data frames receivers decoded.",
            live.frames_decoded,
        ),
        (
            "eventocc_goodput_bits_per_second",
            "gauge",
            "Bits of verified messages received per second over the last minute.",
            live.goodput_bps(),
        ),
        ("eventocc_receptions_total", "counter", "Verified messages received.", received),
        (
            "eventocc_received_bytes_total",
            "counter",
            "Bytes of verified messages received.",
            received_bytes,
        ),
        (
            "eventocc_reports_rejected_total",
            "counter",
            "Receiver reports failing the schema.",
            live.reports_rejected,
        ),
        (
            "eventocc_dashboard_updates_dropped_total",
            "counter",
            "Updates slow dashboards lost (decimated).",
            live.hub.dropped,
        ),
        (
            "eventocc_dashboard_evictions_total",
            "counter",
            "Stalled dashboards dropped.",
            live.hub.evicted,
        ),
    ]
    return "".join(
        f"# HELP {name} {help_}\n# TYPE {name} {kind}\n{name} {value}\n"
        for name, kind, help_, value in samples
    )
