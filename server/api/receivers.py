"""Receiver daemons: ``/ws/receiver`` and the trajectory they leave.

A receiver opens with a ``Hello`` carrying the server's token (when one is set), then sends
numbered reports ``{"seq": n | null, "report": {...}}``. Durable reports (numbered) are stored,
then acknowledged with ``{"type": "ack", "seq": n}``; a replayed number is acknowledged and
skipped. Each report goes on to the dashboards.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import time
from typing import Any

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse
from fastapi.websockets import WebSocket, WebSocketDisconnect
from pydantic import TypeAdapter, ValidationError
from starlette.requests import HTTPConnection

from eventocc.occ.report import FrameStats, Hello, MessageReport, PoseReport, ProgressReport, Report
from eventocc.server.api.deps import LiveDep
from eventocc.server.api.receptions import ReceptionPublic
from eventocc.server.api.state import LiveState
from eventocc.server.store import MessageStore

log = logging.getLogger(__name__)

CLOSE_UNAUTHORIZED = 4401
"""No token, or a wrong one."""
CLOSE_BAD_HANDSHAKE = 4400
"""The first message was not a valid ``Hello``, or did not come in time."""
CLOSE_BAD_FRAME = 1007
"""A message that is not a JSON envelope ``{"seq": ..., "report": ...}``."""
MAX_REASON = 120
"""A close reason must fit in a control frame (123 bytes)."""
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


@sockets.websocket("/receiver")
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
    live.announce_receivers()
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
        live.announce_receivers()
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


@router.get("/{receiver_id}/trajectory", response_class=PlainTextResponse)
def read_trajectory(receiver_id: str, live: LiveDep) -> str:
    """The receiver's kept poses as a TUM file (``t tx ty tz qx qy qz qw``, t in seconds)."""
    lines = [
        f"{t_us // 1_000_000}.{t_us % 1_000_000:06d} " + " ".join(f"{v:.9f}" for v in row)
        for t_us, *row in live.receptions.poses(receiver_id)
    ]
    return "# t tx ty tz qx qy qz qw (T_world_cam, marker frame, metres)\n" + "".join(
        f"{line}\n" for line in lines
    )
