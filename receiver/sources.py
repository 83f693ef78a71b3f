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

__all__ = ["EventSource", "RecordingSource", "SourceError", "open_source", "paced"]


class SourceError(RuntimeError):
    """A source cannot be opened; the message says what to fix (a path, an extra to install)."""


class EventSource(Protocol):
    width: int
    height: int

    def chunks(self) -> Iterator[np.ndarray]:
        """Event chunks (``receiver.events.EVENT_DTYPE``) in time order, until the source ends."""
        ...


def paced(
    chunks: Iterable[np.ndarray],
    *,
    speed: float = 1.0,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> Iterator[np.ndarray]:
    """Yield each chunk once the wall clock has caught up with its last event (times ``speed``),
    so a recording or a simulation arrives as a live camera would deliver it."""
    if speed <= 0:
        raise ValueError(f"speed must be positive, got {speed}")
    origin: tuple[float, int] | None = None
    for chunk in chunks:
        if len(chunk):
            t_end = int(chunk["t"][-1])
            if origin is None:
                origin = (clock(), int(chunk["t"][0]))
            due = origin[0] + (t_end - origin[1]) / 1e6 / speed
            if (wait := due - clock()) > 0:
                sleep(wait)
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
