"""The JSON the receiver sends the server over its websocket, one report per message.

The receiver opens with a ``Hello``; after it every message is one ``Report``, told apart by its
``type`` field. Parse with ``parse_report(text)``; write with ``report.model_dump_json()``.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
from enum import StrEnum
from typing import Annotated, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from eventocc.occ.stream import ReceivedMessage

PROTOCOL_VERSION = 1

INT64_MAX = 2**63 - 1
"""Integers are 64-bit signed, as the server stores them (SQLite) and event times are."""

MAX_WAITING = 300
"""Characters of a health report's ``waiting``: a reason, not a log."""
Unit = Annotated[float, Field(ge=0.0, le=1.0)]
Count = Annotated[int, Field(ge=0, le=INT64_MAX)]
Micros = Annotated[int, Field(ge=-INT64_MAX - 1, le=INT64_MAX)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TrackingState(StrEnum):
    """The receiver pipeline's state (the paper's idle / scanning / receiving, plus lost)."""

    IDLE = "idle"
    SCANNING = "scanning"
    TRACKING = "tracking"
    LOST = "lost"


class Hello(_Model):
    type: Literal["hello"] = "hello"
    receiver_id: str = Field(min_length=1, max_length=128)
    """The receiver's own secret name (the daemon draws 16 random hex digits once per output
    folder): presenting it again is what makes a reconnecting receiver the same one, so the
    server never shows it; it shows ``public_id``."""
    token: str | None = None
    version: int = PROTOCOL_VERSION

    @property
    def public_id(self) -> str:
        return public_receiver_id(self.receiver_id)


def public_receiver_id(receiver_id: str) -> str:
    """The name the server shows for the receiver that says ``receiver_id`` in its Hello: a
    digest, so that seeing it does not let anyone speak as that receiver."""
    return hashlib.sha256(f"eventocc receiver {receiver_id}".encode()).hexdigest()[:16]


class PoseReport(_Model):
    """``T_world_cam``: the camera's pose in the marker frame (metres)."""

    type: Literal["pose"] = "pose"
    t_us: Micros
    position: tuple[float, float, float]
    quaternion_xyzw: tuple[float, float, float, float]
    state: TrackingState
    verified: bool = False
    """A frame had proven the lock (CRC passed; ``paper``: its 'L' read clearly) when the pose
    came out; False: tentative (a wrong lock can look right to every other check). Receivers
    before this field sent none: their poses count as tentative."""


class FrameStats(_Model):
    type: Literal["frame"] = "frame"
    t_us: Micros
    frame_index: Count
    bits_read: Count
    confidence_mean: Unit
    ber: Unit | None = None
    """Bit error rate before FEC, when the truth is known (simulator)."""
    events_per_s: Annotated[float, Field(ge=0.0)]
    payload_bits: Count = 0
    """Payload bits the frame delivered verified (its CRC passed); 0 for ``paper`` frames,
    which carry no check."""
    # What the transmitter's auto mode chooses from (``eventocc.occ.link_policy``); receivers
    # before these fields sent none.
    profile: str | None = Field(default=None, max_length=16)
    """The link profile the receiver read the frame as."""
    cells: Annotated[int, Field(ge=1, le=256)] | None = None
    """The cell count the receiver read the frame as: a frame of settings the screen has
    since left tells the controller nothing of the new ones."""
    passed: bool | None = None
    """Its Reed-Solomon code and CRC passed (None: ``paper``, no check)."""
    ber_before_fec: Unit | None = None
    """Share of its cells the code corrected, for a frame that passed."""
    px_per_cell: Annotated[float, Field(ge=0.0)] | None = None
    """A cell's side in pixels at the tracked pose."""
    readout_share: Annotated[float, Field(ge=0.0)] | None = None
    """Events per second over what the camera's readout carries (None: not known)."""
    flow_px_per_ms: Annotated[float, Field(ge=0.0)] | None = None
    """The marker centre's image speed, from the tracked poses."""
    realtime_margin: Annotated[float, Field(ge=0.0)] | None = None
    """Event time the receiver processes per second of its own (below 1: falling behind)."""


_SHA256 = r"^[0-9a-f]{64}$"


class MessageReport(_Model):
    """A message received in full; ``data_b64`` is checked against ``size`` and ``sha256`` (the
    receiver's digest of the bytes) on parsing, and against ``sender_sha256`` when there is one.
    """

    type: Literal["message"] = "message"
    stream_id: Count
    name: str
    size: Count
    sha256: str = Field(pattern=_SHA256)
    data_b64: str
    profile: str
    sender_sha256: str | None = Field(default=None, pattern=_SHA256)
    """The digest the sender sent in-band (framed profiles). None: nothing checked the bytes
    (``paper`` sends no checksum; receivers before this field sent none either)."""

    @property
    def verified(self) -> bool:
        """The bytes hash to what the sender sent (the parser refuses a mismatch)."""
        return self.sender_sha256 is not None

    @model_validator(mode="after")
    def _data_matches(self) -> Self:
        try:
            data = base64.b64decode(self.data_b64, validate=True)
        except binascii.Error as exc:
            raise ValueError(f"data_b64 is not valid base64: {exc}") from None
        if len(data) != self.size:
            raise ValueError(f"data_b64 holds {len(data)} bytes but size says {self.size}")
        if hashlib.sha256(data).hexdigest() != self.sha256:
            raise ValueError("data_b64 does not match sha256")
        if self.sender_sha256 not in (None, self.sha256):
            raise ValueError("data_b64 does not match the sender's sha256 (sender_sha256)")
        return self

    @property
    def data(self) -> bytes:
        return base64.b64decode(self.data_b64)

    @classmethod
    def of(cls, message: ReceivedMessage) -> MessageReport:
        return cls(
            stream_id=message.stream_id,
            name=message.name,
            size=len(message.data),
            sha256=message.sha256,
            data_b64=base64.b64encode(message.data).decode(),
            profile=message.profile,
            sender_sha256=message.sender_sha256,
        )


class ProgressReport(_Model):
    type: Literal["progress"] = "progress"
    stream_id: Count
    symbols_held: Count
    symbols_needed: Count
    name: str | None = None
    size: Count | None = None


class CameraReport(_Model):
    """What a live camera says of itself; None where it cannot say."""

    temperature_c: float | None = None
    illuminance: Annotated[float, Field(ge=0.0)] | None = None
    illuminance_unit: Literal["lux", "count"] | None = None
    """``lux`` (Metavision), or ``count``: the EVK4's light sensor's raw reading as
    neuromorphic-drivers returns it (no unit; it changes with the light on the sensor)."""
    max_event_rate: Annotated[float, Field(gt=0.0)] | None = None
    """Events/s the sensor's own limiter lets through (None: no limiter in force)."""
    usb_overflows: Count = 0
    """Times the camera's USB ring overflowed and packets were lost, since it opened."""
    usb_lost_s: Annotated[float, Field(ge=0.0)] = 0.0
    """Event time those overflows lost."""


class HealthReport(_Model):
    type: Literal["health"] = "health"
    cpu_load: Annotated[float, Field(ge=0.0)]
    """Share of one core the receiver used (may exceed 1 with several threads)."""
    events_per_s: Annotated[float, Field(ge=0.0)]
    state: TrackingState
    source_speed: Annotated[float, Field(ge=0.0)] | None = None
    """Seconds of events a live source delivers per second of its own (the virtual camera's
    simulation, a camera's or a real-time recording's events that the receiver kept up with);
    below 1 it skips ahead to stay live."""
    camera: CameraReport | None = None
    """A live camera's own readings and link losses (absent for other sources)."""
    px_per_cell: Annotated[float, Field(ge=0.0)] | None = None
    """A cell's side in pixels as the camera sees it: at the tracked pose, or while not locked
    estimated from the latest blinking region detection found (None: nothing seen yet)."""
    detection_failure: str | None = Field(default=None, max_length=500)
    """Why the latest detection attempt failed, while not locked."""
    waiting: Annotated[str, Field(max_length=MAX_WAITING)] | None = None
    """Why the source gives no events now (the virtual camera: the transmitter page is paused
    or closed); ``state`` is then idle."""


class SurfaceReport(_Model):
    """A thumbnail of the event time surface for the dashboard: ``width * height`` uint8 values,
    row-major, base64 (255 = an event just now, fading to 0)."""

    type: Literal["surface"] = "surface"
    t_us: Micros
    width: Annotated[int, Field(ge=1, le=256)]
    height: Annotated[int, Field(ge=1, le=256)]
    pixels_b64: str

    @model_validator(mode="after")
    def _size_matches(self) -> Self:
        try:
            size = len(base64.b64decode(self.pixels_b64, validate=True))
        except binascii.Error as exc:
            raise ValueError(f"pixels_b64 is not valid base64: {exc}") from None
        if size != self.width * self.height:
            raise ValueError(f"pixels_b64 holds {size} bytes, not {self.width}x{self.height}")
        return self


class CellsReport(_Model):
    """The cells one data frame read, for the dashboard: the ``cells x cells`` bits, row-major,
    packed (``numpy.packbits``) and base64; for a frame whose Reed-Solomon decoding succeeded,
    the cells whose bits it corrected, packed the same way."""

    type: Literal["cells"] = "cells"
    t_us: Micros
    frame_index: Count
    cells: Annotated[int, Field(ge=1, le=256)]
    bits_b64: str
    corrected_b64: str | None = None
    """None: the frame did not decode (too many errors, or ``paper``: no per-frame code)."""

    @model_validator(mode="after")
    def _sizes_match(self) -> Self:
        packed = -(-self.cells * self.cells // 8)
        for name in ("bits_b64", "corrected_b64"):
            text = getattr(self, name)
            if text is None:
                continue
            try:
                size = len(base64.b64decode(text, validate=True))
            except binascii.Error as exc:
                raise ValueError(f"{name} is not valid base64: {exc}") from None
            if size != packed:
                raise ValueError(f"{name} holds {size} bytes, not {packed} ({self.cells}^2 bits)")
        return self


Report = Annotated[
    PoseReport
    | FrameStats
    | MessageReport
    | ProgressReport
    | HealthReport
    | SurfaceReport
    | CellsReport,
    Field(discriminator="type"),
]
_REPORT = TypeAdapter(Report)


def parse_report(text: str | bytes) -> Report:
    """One report from its JSON; raises ``pydantic.ValidationError`` saying what is wrong."""
    return _REPORT.validate_json(text)
