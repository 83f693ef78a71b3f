"""Where the daemon's events come from, behind one small interface.

A source has a sensor size and yields event chunks in time order. It is named by a URI:

- ``sim:`` the virtual event camera, watching what the server's transmitter plays right now;
- ``file:PATH`` (or just ``PATH``) a recording, replayed at real-time pace or as fast as possible;
- ``nd:`` / ``metavision:[SERIAL]`` / ``dv:`` a live camera through an optional backend
  (neuromorphic-drivers, Metavision's Python API, dv-processing);
- ``nd-replay:PATH`` a recording replayed as a USB camera through the neuromorphic-drivers
  path (``live_replay``).

A live source (a camera, a recording at real-time pace, the virtual camera) never lets its
consumer fall more than ``MAX_LAG_S`` behind: it skips ahead to what it delivers now, and
reports its ``speed``, the seconds of events it delivered per second of the source.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from receiver.live_controls import CameraSettings

__all__ = [
    "MAX_LAG_S",
    "BehindNote",
    "EventSource",
    "LinkSettings",
    "LiveClock",
    "RecordingSource",
    "SourceError",
    "StayLive",
    "open_source",
    "paced",
]

log = logging.getLogger(__name__)

MAX_LAG_S = 1.0
"""Behind a live source by this much, its consumer skips ahead to what the source delivers now."""
KEEPING_UP = 0.95
"""``speed`` at or above which a source counts as keeping up with real time."""
BEHIND_NOTE_S = 30.0
"""While behind, the log says so at most this often."""
FRESH_SHARE = 0.75
"""While dropping, a chunk that took this share of its span to come was not waiting: caught up."""


class SourceError(RuntimeError):
    """A source cannot be opened; the message says what to fix (a path, an extra to install)."""


class EventSource(Protocol):
    """Optional extra, read by the daemon when present: ``speed`` (for a live source, the
    seconds of events it delivered per second of its own; below 1 it skips ahead)."""

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


class BehindNote:
    """Says in the log, at most every ``BEHIND_NOTE_S``, that a live source skips ahead because
    ``who`` cannot keep up, and when it keeps up again."""

    def __init__(self, who: str, because: str) -> None:
        self.behind = False
        self._who, self._because = who, because
        self._skips = 0
        self._next_note = 0.0

    def skipped(self, speed: float) -> None:
        self._skips += 1
        self.behind = True
        if time.monotonic() >= self._next_note:
            self._next_note = time.monotonic() + BEHIND_NOTE_S
            log.warning(
                "%s at %.2fx real time: %s, so it skipped ahead %d time(s) to what comes now",
                self._who,
                speed,
                self._because,
                self._skips,
            )
            self._skips = 0

    def measured(self, speed: float) -> None:
        if self.behind and speed >= KEEPING_UP:
            self.behind = False
            log.info("%s keeps up with real time again", self._who)


class StayLive:
    """Keeps the consumer of a live stream of chunks (a camera's, or a recording's at its pace)
    within ``max_lag_s`` of it: further behind, it drops the chunks waiting until one comes
    fresh, as a camera's driver drops what overflows its buffers. The receiver then sees a gap
    in event time and goes on from there, re-acquiring the marker if it lost it.

    Lateness is wall-clock time against event time, tied at the first chunk, at any chunk
    earlier than the tie predicts, and where dropping ends: at the first chunk that took most
    of its span to come, where queued ones come back to back. (While chunks are kept, how long
    one took to come tells nothing: a reader on a starved core takes most of a span per chunk.)
    Re-tying keeps clock drift from reading as lag: a camera clock 1e-4 slow would add a second
    every three hours; here it costs one chunk when it adds up. ``speed``: the share of the
    source's event time kept over the last ``window_s`` of it (None before)."""

    def __init__(
        self,
        who: str = "receiver",
        *,
        max_lag_s: float = MAX_LAG_S,
        window_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_lag_s, self.window_us = max_lag_s, window_s * 1e6
        self.speed: float | None = None
        self.skips = 0
        """Times the consumer fell ``max_lag_s`` behind and chunks were dropped."""
        self.dropped_events = 0
        self._clock = clock
        self._note = BehindNote(who, "it cannot process the events as fast as they come")

    def __call__(self, chunks: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        tie: tuple[float, int] | None = None  # (wall clock, event time) of a fresh chunk
        last_us: int | None = None
        arrived_us = kept_us = 0
        dropping = False
        source = iter(chunks)
        while True:
            asked = self._clock()
            chunk = next(source, None)
            if chunk is None:
                return
            if not len(chunk):
                yield chunk
                continue
            now, end_us = self._clock(), int(chunk["t"][-1])
            span = end_us - (int(chunk["t"][0]) if last_us is None else last_us)
            arrived_us, last_us = arrived_us + span, end_us
            late_s = 0.0 if tie is None else now - tie[0] - (end_us - tie[1]) / 1e6
            caught_up = dropping and (now - asked) * 1e6 >= FRESH_SHARE * span
            if tie is None or late_s < 0 or caught_up:
                tie, late_s, dropping = (now, end_us), 0.0, False
            if not dropping and late_s > self.max_lag_s:
                dropping = True
                self.skips += 1
                self._note.skipped((end_us - tie[1]) / 1e6 / (now - tie[0]))  # since the tie
            if dropping:
                self.dropped_events += len(chunk)
            else:
                kept_us += span
            if arrived_us >= self.window_us:
                self.speed = kept_us / arrived_us
                self._note.measured(self.speed)
                arrived_us = kept_us = 0
            if not dropping:
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
        self._live = StayLive()

    @property
    def speed(self) -> float | None:
        return self._live.speed if self.realtime else None

    def chunks(self) -> Iterator[np.ndarray]:
        return self._live(paced(self._stream)) if self.realtime else iter(self._stream)


def open_source(
    uri: str,
    *,
    realtime: bool = True,
    live_settings: CameraSettings | None = None,
    **virtual_camera_options,
) -> EventSource:
    """The source a URI names (see the module docstring); raises ``SourceError`` if it can't.
    ``live_settings``: a live camera's ``live_controls.CameraSettings`` (default: its own)."""
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
        return open_live_camera(scheme, rest, live_settings)
    raise SourceError(
        f"unknown source {uri!r}: use sim:, file:PATH, or a live camera "
        f"({', '.join(f'{name}:' for name in LIVE_BACKENDS)})"
    )
