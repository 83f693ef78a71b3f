"""Request and response bodies of the REST API."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum

from pydantic import BaseModel, Field

from eventocc.occ.profiles import PROFILE_NAMES

NOMINAL_REFRESH_HZ = 60.0

ProfileName = StrEnum("ProfileName", {name: name for name in PROFILE_NAMES})


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
    frames_per_loop: int | None = Field(
        description="Display refreshes before the stream repeats; null for an endless "
        "(fountain-coded) stream."
    )
    bits_per_frame: int = Field(description="Payload cells of one data frame.")
    bit_rate_60hz: float = Field(
        description="Raw cell bits per second on a 60 Hz display (before framing and FEC)."
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
    """What a transmitter page reports about its own playback, about once a second."""

    message_id: str | None = None
    profile: str | None = None
    cells: int | None = Field(None, ge=1)
    cell_px: int | None = Field(None, ge=1)
    playing: bool = False
    frame_index: int = Field(0, ge=0, description="Next frame to draw.")
    refresh_hz: float | None = Field(None, gt=0, description="Median requestAnimationFrame rate.")
    missed_refreshes: int = Field(0, ge=0, description="rAF intervals over 1.5x the median.")
    stalls: int = Field(0, ge=0, description="Refreshes held because the frame had not arrived.")
    user_agent: str | None = Field(None, max_length=512)


class TransmitterStatusPublic(TransmitterStatus):
    received: datetime = Field(description="Server time (UTC) the status arrived.")
