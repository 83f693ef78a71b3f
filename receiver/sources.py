"""Where the daemon's events come from, behind one small interface.

A source has a sensor size and yields event chunks in time order. It is named by a URI:

- ``sim:`` the virtual event camera, watching what the server's transmitter plays right now;
- ``file:PATH`` (or just ``PATH``) a recording, replayed at real-time pace or as fast as possible;
- ``nd:`` / ``metavision:[SERIAL]`` / ``dv:`` a live camera through an optional backend
  (neuromorphic-drivers, Metavision's Python API, dv-processing).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

__all__ = [
    "EventSource",
    "LinkSettings",
    "LiveClock",
    "RecordingSource",
    "SourceError",
    "open_source",
    "paced",
]


class SourceError(RuntimeError):
    """A source cannot be opened; the message says what to fix (a path, an extra to install)."""


class EventSource(Protocol):
    """Optional extra, read by the daemon when present: ``speed`` (seconds of events per
    wall-clock second, for a source that can fall behind real time)."""

    width: int
    height: int

    def chunks(self) -> Iterator[np.ndarray]:
        """Event chunks (``receiver.events.EVENT_DTYPE``) in time order, until the source ends."""
        ...


@dataclass(frozen=True)
class LinkSettings:
    """What the receiver pipeline must be told about the screen: its link profile, cells and
    refresh rate."""

    profile: str
    cells: int
    refresh_hz: float = 60.0
    """Whole hertz: a page's measured rate wobbles by a fraction of a hertz, which the receiver
    absorbs (it re-times every frame from its own burst) and must not rebuild for."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "refresh_hz", float(round(self.refresh_hz)))


class LiveClock:
    """Event time on the wall clock, so that events arrive as a live camera delivers them.

    ``start(t_us)`` ties event time ``t_us`` to the wall clock's now (times ``speed``); then
    ``wait(t_us)`` sleeps until ``t_us`` is due and says how late it already was.
    """

    def __init__(
        self,
        *,
        speed: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.speed = speed
        self._clock, self._sleep = clock, sleep
        self._origin: tuple[float, int] | None = None

    @property
    def started(self) -> bool:
        return self._origin is not None

    def start(self, t_us: int) -> None:
        self._origin = (self._clock(), t_us)

    def now_us(self) -> int:
        """The event time due now."""
        wall, t0 = self._require_origin()
        return t0 + round((self._clock() - wall) * self.speed * 1e6)

    def due_s(self, t_us: int) -> float:
        """The wall-clock time at which event time ``t_us`` is due."""
        wall, t0 = self._require_origin()
        return wall + (t_us - t0) / 1e6 / self.speed

    def wait(self, t_us: int) -> float:
        """Sleep until ``t_us`` is due; returns how many seconds late it was (0 if on time)."""
        late = self._clock() - self.due_s(t_us)
        if late < 0:
            self._sleep(-late)
        return max(late, 0.0)

    def _require_origin(self) -> tuple[float, int]:
        if self._origin is None:
            raise RuntimeError("LiveClock.start() must be called first")
        return self._origin


def paced(
    chunks: Iterable[np.ndarray],
    *,
    speed: float = 1.0,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> Iterator[np.ndarray]:
    """Yield each chunk once the wall clock has caught up with its last event (times ``speed``),
    so a recording arrives as a live camera would deliver it."""
    pace = LiveClock(speed=speed, clock=clock, sleep=sleep)
    for chunk in chunks:
        if len(chunk):
            if not pace.started:
                pace.start(int(chunk["t"][0]))
            pace.wait(int(chunk["t"][-1]))
        yield chunk


@dataclass
class RecordingSource:
    """An event file in any format ``receiver.io`` reads."""

    path: Path
    realtime: bool = True

    def __post_init__(self) -> None:
        from receiver.io import read_events  # the readers pull in numba kernels: only when used

        if not self.path.is_file():
            raise SourceError(f"no recording at {self.path}: give an event file's path")
        self._stream = read_events(self.path)
        if self._stream.width is None or self._stream.height is None:
            raise SourceError(f"{self.path} does not state its sensor size; convert it first")
        self.width, self.height = int(self._stream.width), int(self._stream.height)

    def chunks(self) -> Iterator[np.ndarray]:
        return paced(self._stream) if self.realtime else iter(self._stream)


def open_source(uri: str, *, realtime: bool = True, **virtual_camera_options) -> EventSource:
    """The source a URI names (see the module docstring); raises ``SourceError`` if it can't."""
    scheme, sep, rest = uri.partition(":")
    if not sep or len(scheme) == 1:  # a plain path (or a Windows drive letter)
        scheme, rest = "file", uri
    if scheme == "file":
        return RecordingSource(Path(rest), realtime=realtime)
    if scheme == "sim":
        from receiver.virtual_camera import VirtualCamera

        return VirtualCamera(**virtual_camera_options)
    from receiver.live_cameras import LIVE_BACKENDS, open_live_camera

    if scheme in LIVE_BACKENDS:
        return open_live_camera(scheme, rest)
    raise SourceError(
        f"unknown source {uri!r}: use sim:, file:PATH, or a live camera "
        f"({', '.join(f'{name}:' for name in LIVE_BACKENDS)})"
    )
