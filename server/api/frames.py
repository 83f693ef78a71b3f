"""``/api/messages/{id}/frames``: batches of frames, packed bits, for the transmitter page."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Response, status

from eventocc.occ.link_policy import AUTO_PROFILES
from eventocc.server.api.deps import CellsQuery, EncodersDep, MessageDep
from eventocc.server.api.schemas import MAX_COUNTER, MAX_FRAME_INDEX, ProfileName

router = APIRouter(prefix="/messages", tags=["frames"])

MAX_BATCH = 600
"""Frames per request: 10 s at 60 Hz, a few MB at the largest marker."""

FRAMES_FORMAT = """\
Frames `start .. start+count-1`, each the **full marker cell matrix** (every cell, locators and
exterior rings included) of `side x side` cells, row-major, 1 = white, bits packed MSB first.
Each frame is padded with zero bits to whole bytes, so the body is
`count * ceil(side * side / 8)` bytes. Headers: `X-Frame-Side`, `X-Frame-Start`,
`X-Frame-Count`, `X-Frame-Bytes` (bytes per frame), `X-Frame-Symbols` (fountain symbols per data
frame; a packed segment that ends after `k` refreshes is followed by one from `symbol_start +
k * X-Frame-Symbols`).
In numpy: `np.unpackbits(np.frombuffer(body, np.uint8).reshape(count, -1), axis=1)`,
then `[:, :side * side].reshape(count, side, side)`.
"""


def pack_frames(frames: np.ndarray) -> bytes:
    """(count, side, side) bool -> packed bytes as described in ``FRAMES_FORMAT``."""
    return np.packbits(frames.reshape(len(frames), -1), axis=1).tobytes()


@router.get(
    "/{message_id}/frames",
    response_class=Response,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": FRAMES_FORMAT},
        404: {"description": "No such message."},
    },
)
def read_frames(
    message: MessageDep,
    encoders: EncodersDep,
    start: Annotated[int, Query(ge=0, le=MAX_FRAME_INDEX, description="First frame.")] = 0,
    count: Annotated[int, Query(ge=1, le=MAX_BATCH, description="Frames in the batch.")] = 60,
    profile: Annotated[ProfileName | None, Query(description="Defaults to the message's.")] = None,
    cells: CellsQuery = None,
    packed: Annotated[
        bool, Query(description="Fixed-size fountain symbols, as auto mode sends.")
    ] = False,
    symbol_start: Annotated[
        int,
        Query(ge=0, le=MAX_COUNTER, description="Packed: the first symbol's stream position."),
    ] = 0,
) -> Response:
    """Frames as displayed, one per display refresh (blank frames included)."""
    profile_name = profile.value if profile else message.profile
    if packed and profile_name not in AUTO_PROFILES:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"packed frames are sent with {' or '.join(AUTO_PROFILES)} only, not {profile_name}",
        )
    encoder = encoders.get(
        message, profile_name, cells or message.cells, packed, symbol_start if packed else 0
    )
    frames = encoder.frames(start, count)
    side = encoder.geometry.side
    return Response(
        pack_frames(frames),
        media_type="application/octet-stream",
        headers={
            "X-Frame-Side": str(side),
            "X-Frame-Start": str(start),
            "X-Frame-Count": str(count),
            "X-Frame-Bytes": str(-(-side * side // 8)),
            "X-Frame-Symbols": str(encoder.symbols_per_frame),
        },
    )
