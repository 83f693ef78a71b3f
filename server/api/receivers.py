"""Receiver daemons: ``/ws/receiver`` and the trajectory they leave.

A receiver opens with a ``Hello`` carrying its secret id and the server's token (when one is
set), then sends numbered reports ``{"seq": n | null, "report": {...}}``. Durable reports
(numbered) are stored, then acknowledged with ``{"type": "ack", "seq": n}``; a replayed number
is acknowledged and skipped. Each report goes on to the dashboards under the receiver's public
id. One connection speaks for a receiver at a time: a newer one with the same secret id takes
over (the receiver restarted), and the older one is closed.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import secrets
import time
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, status
from fastapi.responses import PlainTextResponse
from fastapi.websockets import WebSocket, WebSocketDisconnect
from pydantic import TypeAdapter, ValidationError
from starlette.requests import HTTPConnection

from eventocc.occ.report import (
    INT64_MAX,
    FrameStats,
    HealthReport,
    Hello,
    MessageReport,
    PoseReport,
    ProgressReport,
    Report,
)
from eventocc.server.api.deps import LiveDep
from eventocc.server.api.receptions import ReceptionPublic
from eventocc.server.api.sockets import MalformedFrame, receive_text, refuse
from eventocc.server.api.state import LiveState, ReceiverSession
from eventocc.server.store import MessageStore

log = logging.getLogger(__name__)

CLOSE_UNAUTHORIZED = 4401
"""No token, or a wrong one."""
CLOSE_BAD_HANDSHAKE = 4400
"""The first message was not a valid ``Hello``, or did not come in time."""
CLOSE_REPLACED = 4409
"""A newer connection of the same receiver took over."""
HELLO_TIMEOUT_S = 5.0

report_adapter: TypeAdapter[Report] = TypeAdapter(Report)

router = APIRouter(prefix="/receivers", tags=["receivers"])
sockets = APIRouter(tags=["receivers"])


def token_is_valid(connection: HTTPConnection, hello: Hello) -> bool:
    token = connection.app.state.settings.token
    if token is None:
        return True
    given = (hello.token or "").encode()
    return secrets.compare_digest(given, token.get_secret_value().encode())


async def receive_hello(websocket: WebSocket) -> Hello | None:
    try:
        text = await asyncio.wait_for(receive_text(websocket), HELLO_TIMEOUT_S)
        return Hello.model_validate_json(text)
    except (TimeoutError, ValidationError, MalformedFrame) as error:
        await refuse(websocket, CLOSE_BAD_HANDSHAKE, f"expected a Hello report first: {error}")
        return None


@sockets.websocket("/receiver")
async def receiver_socket(websocket: WebSocket, live: LiveDep) -> None:
    await websocket.accept()
    try:
        hello = await receive_hello(websocket)
    except WebSocketDisconnect:
        return
    if hello is None:
        return
    if not token_is_valid(websocket, hello):
        await refuse(websocket, CLOSE_UNAUTHORIZED, "missing or wrong token")
        return
    session = live.claim(hello)
    exchange = asyncio.create_task(exchange_reports(websocket, live, session))
    replaced = asyncio.create_task(session.replaced.wait())
    try:
        await asyncio.wait({exchange, replaced}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        exchange.cancel()
        replaced.cancel()
        if live.release(session):
            log.info("receiver %s disconnected", session.receiver)
    error = exchange.exception() if exchange.done() and not exchange.cancelled() else None
    if session.replaced.is_set():
        await refuse(websocket, CLOSE_REPLACED, "a newer connection of this receiver took over")
    elif isinstance(error, MalformedFrame):
        await refuse(websocket, error.code, f"{error}")
    elif error is not None:
        raise error


async def exchange_reports(websocket: WebSocket, live: LiveState, session: ReceiverSession) -> None:
    """Welcome the receiver, then store, acknowledge and pass on its reports until it goes.

    Returns on a disconnect; raises ``MalformedFrame`` for a frame outside the protocol."""
    receiver = session.receiver
    try:
        last_seq = await asyncio.to_thread(live.receptions.register, receiver)
        await websocket.send_json({"type": "welcome", "last_seq": last_seq})
        log.info("receiver %s connected; stored up to its report %d", receiver, last_seq)
        while True:
            seq, report = await receive_report(websocket, live)
            if session.replaced.is_set():  # what the older connection still sends is not stored
                return
            if report is not None and (seq is None or seq > last_seq):
                await handle_report(live, receiver, seq, report)
            if seq is not None:
                last_seq = max(last_seq, seq)
                await websocket.send_json({"type": "ack", "seq": seq})
            # A burst of reports arrives already buffered, so nothing above need wait: give
            # the dashboards' senders their turn after each one, or they fall behind and are
            # evicted as stalled.
            await asyncio.sleep(0)
    except WebSocketDisconnect:
        pass


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is out of range for a number")
    return value


def _not_json(constant: str) -> float:
    raise ValueError(f"{constant} is not JSON: send finite numbers")


def parse_envelope(text: str) -> tuple[int | None, Any]:
    """``{"seq": n | null, "report": {...}}`` -> (seq, report body); ``MalformedFrame`` if
    the text is not such an envelope (strict JSON: no NaN or Infinity)."""
    try:
        envelope = json.loads(text, parse_float=_finite, parse_constant=_not_json)
        seq, body = envelope["seq"], envelope["report"]
        if seq is not None and (type(seq) is not int or not 1 <= seq <= INT64_MAX):
            raise ValueError(f"seq must be an integer 1..2^63-1 or null, got {seq!r}")
    except (ValueError, KeyError, TypeError, RecursionError) as error:
        raise MalformedFrame(f'expected {{"seq": n, "report": {{...}}}}: {error}') from None
    return seq, body


async def receive_report(websocket: WebSocket, live: LiveState) -> tuple[int | None, Report | None]:
    """One envelope: its number and its report, or None for a report that fails the schema
    (logged, counted and acknowledged anyway, so a bad report cannot jam the receiver's spool)."""
    seq, body = parse_envelope(await receive_text(websocket))
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
        await asyncio.to_thread(
            live.receptions.add_poses, receiver, seq, [row], verified=report.verified
        )
    elif seq is not None:
        await asyncio.to_thread(live.receptions.mark_stored, receiver, seq)
    if isinstance(report, FrameStats):
        live.frames_decoded += bool(report.bits_read)
        live.link_frame(receiver, report)
    if isinstance(report, HealthReport):
        live.link.on_health(receiver, report.source_speed)
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
    # The stream id lets the dashboards drop that stream's progress bar (its name may be unknown).
    public = ReceptionPublic.of(reception).model_dump(mode="json")
    return {"type": "reception", "stream_id": report.stream_id, **public}


def upload_with_digest(messages: MessageStore, sha256: str) -> str | None:
    """The id of an uploaded message with these bytes, if any (reads the store: off the loop)."""
    return next((m.id for m in messages.messages() if m.sha256 == sha256), None)


@router.get(
    "/{receiver}/trajectory",
    response_class=PlainTextResponse,
    responses={404: {"description": "No receiver with this public id ever connected."}},
)
def read_trajectory(
    receiver: str,
    live: LiveDep,
    tentative: Annotated[
        bool,
        Query(
            alias="all",
            description="Also the tentative poses: those before a frame proved the "
            "receiver's lock (a wrong lock can look right to every other check).",
        ),
    ] = False,
) -> str:
    """The receiver's kept poses as a TUM file (``t tx ty tz qx qy qz qw``, t in seconds): the
    verified ones, or with ``?all=true`` the tentative ones too."""
    poses = live.receptions.poses(receiver, tentative=tentative)
    if poses is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no receiver {receiver!r} ever connected")
    lines = [
        f"{t_us // 1_000_000}.{t_us % 1_000_000:06d} " + " ".join(f"{v:.9f}" for v in row)
        for t_us, *row in poses
    ]
    return "# t tx ty tz qx qy qz qw (T_world_cam, marker frame, metres)\n" + "".join(
        f"{line}\n" for line in lines
    )
