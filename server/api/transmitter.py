"""A transmitter page's playback status: ``POST /api/transmitter/status`` or ``/ws/transmitter``,
read back at ``GET /api/transmitter/status``.

Both ways in take the same path (``LiveState.set_transmitter``): the latest status is kept in
memory, not stored (it is only news), and passed on to the dashboards at once.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter, HTTPException, status
from fastapi.websockets import WebSocket, WebSocketDisconnect
from pydantic import ValidationError

from eventocc.server.api.deps import LiveDep
from eventocc.server.api.schemas import TransmitterStatus, TransmitterStatusPublic
from eventocc.server.api.sockets import MalformedFrame, receive_text, refuse

router = APIRouter(prefix="/transmitter", tags=["transmitter"])
sockets = APIRouter(tags=["transmitter"])


def stamped(report: TransmitterStatus) -> TransmitterStatusPublic:
    return TransmitterStatusPublic(**report.model_dump(), received=datetime.now(UTC))


@router.post("/status")
def update_transmitter_status(report: TransmitterStatus, live: LiveDep) -> TransmitterStatusPublic:
    latest = stamped(report)
    live.set_transmitter(latest)
    return latest


@router.get("/status", responses={404: {"description": "No transmitter has reported yet."}})
def read_transmitter_status(live: LiveDep) -> TransmitterStatusPublic:
    if live.transmitter is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no transmitter has reported yet")
    return live.transmitter


@sockets.websocket("/transmitter")
async def transmitter_socket(websocket: WebSocket, live: LiveDep) -> None:
    """Each text frame a status; a bad one is answered ``{"type": "error", "detail": [...]}``
    and changes nothing."""
    await websocket.accept()
    try:
        while True:
            text = await receive_text(websocket)
            try:
                report = TransmitterStatus.model_validate_json(text)
            except ValidationError as error:
                problems = error.errors(
                    include_url=False, include_context=False, include_input=False
                )
                await websocket.send_json({"type": "error", "detail": problems[:3]})
                continue
            live.set_transmitter(stamped(report))
    except WebSocketDisconnect:
        pass
    except MalformedFrame as error:
        await refuse(websocket, error.code, f"{error}")
