"""``/api/messages/{id}/frames``: batches of frames, packed bits, for the transmitter page."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Response

from eventocc.server.api.deps import CellsQuery, EncodersDep, MessageDep
from eventocc.server.api.schemas import MAX_FRAME_INDEX, ProfileName

router = APIRouter(prefix="/messages", tags=["frames"])

MAX_BATCH = 600
"""Frames per request: 10 s at 60 Hz, a few MB at the largest marker."""

FRAMES_FORMAT = """\
Frames `start .. start+count-1`, each the **full marker cell matrix** (every cell, locators and
exterior rings included) of `side x side` cells, row-major, 1 = white, bits packed MSB first.
Each frame is padded with zero bits to whole bytes, so the body is
`count * ceil(side * side / 8)` bytes. Headers: `X-Frame-Side`, `X-Frame-Start`,
`X-Frame-Count`, `X-Frame-Bytes` (bytes per frame).
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
) -> Response:
    """Frames as displayed, one per display refresh (blank frames included)."""
    profile_name = profile.value if profile else message.profile
    encoder = encoders.get(message, profile_name, cells or message.cells)
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
        },
    )
