"""Request and response bodies of the REST API."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from functools import cache
from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from eventocc.occ.link_policy import AUTO_PROFILES, HOLDS
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
    packed: bool = Field(
        False,
        description="Frames of fixed-size fountain symbols (auto mode): the message's symbols "
        "are the same at every density, so a receiver keeps its progress across changes.",
    )
    symbol_start: int = Field(
        0,
        ge=0,
        le=MAX_COUNTER,
        description="Packed: the fountain stream position of this segment's first symbol.",
    )
    hold: int = Field(
        1, ge=1, le=max(HOLDS), description="Display refreshes each frame is held for."
    )

    @model_validator(mode="after")
    def _link_can_run(self) -> Self:
        if self.packed and self.profile is not None and self.profile.value not in AUTO_PROFILES:
            raise ValueError(f"packed frames are sent with {' or '.join(AUTO_PROFILES)} only")
        if self.profile is not None and self.cells is not None:
            refusal = link_refusal(self.profile.value, self.cells)
            if refusal:
                raise ValueError(
                    f"no link runs with {self.profile.value} and {self.cells} cells: {refusal}"
                )
        return self


class TransmitterStatusPublic(TransmitterStatus):
    received: datetime = Field(description="Server time (UTC) the status arrived.")


RECEIVER_ID_PATTERN = r"^[0-9a-f]{16}$"


class LinkModeRequest(BaseModel):
    """``PUT /api/transmitter/mode``: who chooses what the transmitter sends."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["fixed", "auto"] = Field(
        description="fixed: the page sends what its user set; auto: the server chooses from "
        "the receivers' reports and the page follows."
    )
    pin: str | None = Field(
        None,
        pattern=RECEIVER_ID_PATTERN,
        description="auto: follow this receiver (its public id) rather than the weakest "
        "verified one.",
    )


class LinkChoicePublic(BaseModel):
    profile: str
    cells: int
    hold: int = Field(description="Display refreshes each frame is held for.")
    frame_hz: float


class GoodputPoint(BaseModel):
    t: float = Field(description="Server time (s, monotonic) of the second's start.")
    bps: int = Field(description="Verified payload bits of the served receiver that second.")
    settings: str


class LinkModePublic(BaseModel):
    mode: str
    pinned: str | None
    served: str | None = Field(description="The receiver whose measurements set the choice.")
    choice: LinkChoicePublic | None = Field(description="What the page sends (auto only).")
    reason: str = Field(description="Why: what moved it, or the margin that holds it.")
    since_s: float = Field(description="Seconds since the choice last changed.")
    history: list[GoodputPoint]


class TransmitterStatusReply(TransmitterStatusPublic):
    """What a page's status report is answered with: its status, and what to send."""

    link: LinkModePublic
