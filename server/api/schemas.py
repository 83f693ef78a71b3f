"""Request and response bodies of the REST API."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from functools import cache
from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from eventocc.occ.marker import MAX_CELLS, MIN_CELLS
from eventocc.occ.profiles import MAX_REFRESH_HZ, MIN_REFRESH_HZ, PROFILE_NAMES
from eventocc.occ.stream import StreamEncoder

NOMINAL_REFRESH_HZ = 60.0
MESSAGE_ID_PATTERN = r"^[0-9a-f]{12}$"
MAX_FRAME_INDEX = 2**31 - 1
MAX_COUNTER = 2**53 - 1
"""The largest count a page's JavaScript numbers hold exactly."""

ProfileName = StrEnum("ProfileName", {name: name for name in PROFILE_NAMES})


@cache
def link_refusal(profile: str, cells: int) -> str | None:
    """Why the link format cannot send any message with this profile and cell count, or None.

    A one-byte message asks the encoder every check that does not depend on the message
    (payload room for the header and parity, whole bytes per ``paper`` frame)."""
    try:
        StreamEncoder(b"\0", profile=profile, cells=cells)
    except ValueError as error:
        return str(error)
    return None


class MessageText(BaseModel):
    """JSON upload body: the message as text, stored UTF-8 encoded."""

    text: str


class MessagePublic(BaseModel):
    id: str
    name: str
    size: int = Field(description="Bytes.")
    sha256: str
    profile: str
    cells: int = Field(description="Payload cells across (N); the marker shows N x N data cells.")
    created: datetime
    frames_per_loop: int = Field(
        description="Display refreshes before the stream repeats: finite for every profile "
        "(a fountain-coded stream sends a bounded number of repair symbols, then loops)."
    )
    bits_per_frame: int = Field(description="Payload cells of one data frame.")
    bit_rate_60hz: float = Field(
        description="Raw cell bits per second on a 60 Hz display (before framing and FEC), "
        "to 0.1 bit/s: the same for every message of a profile and cell count."
    )


class MessagesPublic(BaseModel):
    messages: list[MessagePublic]


class ProfilesPublic(BaseModel):
    profiles: list[str]
    default_profile: str
    default_cells: int
    min_cells: int
    max_cells: int


class TransmitterStatus(BaseModel):
    """What a transmitter page reports about its own playback, about once a second.

    Every receiver daemon that follows the page rebuilds itself for the profile, cell count
    and refresh rate given here, so each must be one the link can run at."""

    model_config = ConfigDict(allow_inf_nan=False)

    message_id: str | None = Field(None, pattern=MESSAGE_ID_PATTERN)
    profile: ProfileName | None = None
    cells: int | None = Field(None, ge=MIN_CELLS, le=MAX_CELLS)
    cell_px: int | None = Field(None, ge=1, le=4096, description="Screen pixels per cell.")
    playing: bool = False
    frame_index: int = Field(0, ge=0, le=MAX_FRAME_INDEX, description="Next frame to draw.")
    refresh_hz: float | None = Field(
        None,
        ge=MIN_REFRESH_HZ,
        le=MAX_REFRESH_HZ,
        description="Median requestAnimationFrame rate.",
    )
    missed_refreshes: int = Field(
        0, ge=0, le=MAX_COUNTER, description="rAF intervals over 1.5x the median."
    )
    stalls: int = Field(
        0, ge=0, le=MAX_COUNTER, description="Refreshes held because the frame had not arrived."
    )
    user_agent: str | None = Field(None, max_length=512)

    @model_validator(mode="after")
    def _link_can_run(self) -> Self:
        if self.profile is not None and self.cells is not None:
            refusal = link_refusal(self.profile.value, self.cells)
            if refusal:
                raise ValueError(
                    f"no link runs with {self.profile.value} and {self.cells} cells: {refusal}"
                )
        return self


class TransmitterStatusPublic(TransmitterStatus):
    received: datetime = Field(description="Server time (UTC) the status arrived.")
