"""A transmitter page's playback status: ``POST /api/transmitter/status`` or ``/ws/transmitter``,
read back at ``GET /api/transmitter/status``; and its mode: ``PUT /api/transmitter/mode``
(``fixed``, or ``auto``: the server chooses what the page sends), read at ``GET``.

Both ways in take the same path (``LiveState.set_transmitter``): the latest status is kept in
memory, not stored (it is only news), and passed on to the dashboards at once. A status
report is answered with the mode and, in auto, the settings to send: that answer is how the
page follows the server's choice.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter, HTTPException, status
from fastapi.websockets import WebSocket, WebSocketDisconnect
from pydantic import ValidationError

from eventocc.server.api.deps import LiveDep
from eventocc.server.api.schemas import (
    LinkModePublic,
    LinkModeRequest,
    TransmitterStatus,
    TransmitterStatusPublic,
    TransmitterStatusReply,
)
from eventocc.server.api.sockets import MalformedFrame, receive_text, refuse

router = APIRouter(prefix="/transmitter", tags=["transmitter"])
sockets = APIRouter(tags=["transmitter"])


def stamped(report: TransmitterStatus) -> TransmitterStatusPublic:
    return TransmitterStatusPublic(**report.model_dump(), received=datetime.now(UTC))


@router.post("/status")
def update_transmitter_status(report: TransmitterStatus, live: LiveDep) -> TransmitterStatusReply:
    latest = stamped(report)
    live.set_transmitter(latest)
    return TransmitterStatusReply(**latest.model_dump(), link=live.link_public())


@router.put(
    "/mode",
    responses={
        404: {"description": "The receiver to pin is not connected."},
        422: {"description": "Not a mode, or not a receiver id: nothing changed."},
    },
)
def set_transmitter_mode(request: LinkModeRequest, live: LiveDep) -> LinkModePublic:
    """``auto``: start at N = 16 ``robust`` and let the receivers' measurements move it;
    ``fixed``: the page sends what its user set. Either way the page hears of it in the
    answer to its next status report."""
    if request.pin is not None and request.mode != "auto":
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, "only auto mode follows a pinned receiver"
        )
    if request.pin is not None and request.pin not in live.receivers:
        connected = ", ".join(sorted(live.receivers)) or "none"
        raise HTTPException(
            status.HTTP_404_NOT_FOUND,
            f"no receiver {request.pin} is connected to pin (connected: {connected})",
        )
    live.set_link_mode(request.mode, request.pin)
    return LinkModePublic(**live.link_public())


@router.get("/mode")
def read_transmitter_mode(live: LiveDep) -> LinkModePublic:
    return LinkModePublic(**live.link_public())


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
