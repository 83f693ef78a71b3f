"""``/api/transmitter/status``: the latest playback report of a transmitter page.

Kept in memory on the app (``app.state.transmitter_status``), not stored: it is only news.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter, HTTPException, Request, status

from eventocc.server.api.schemas import TransmitterStatus, TransmitterStatusPublic

router = APIRouter(prefix="/transmitter", tags=["transmitter"])


@router.post("/status")
def update_transmitter_status(
    report: TransmitterStatus, request: Request
) -> TransmitterStatusPublic:
    latest = TransmitterStatusPublic(**report.model_dump(), received=datetime.now(UTC))
    request.app.state.transmitter_status = latest
    return latest


@router.get("/status", responses={404: {"description": "No transmitter has reported yet."}})
def read_transmitter_status(request: Request) -> TransmitterStatusPublic:
    latest = request.app.state.transmitter_status
    if latest is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no transmitter has reported yet")
    return latest
