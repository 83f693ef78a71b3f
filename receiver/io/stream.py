"""What every reader and writer shares: the stream object and the sanity checks on events."""

from __future__ import annotations

import operator
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numba
import numpy as np

from eventocc.receiver.events import EVENT_DTYPE
from eventocc.receiver.io.errors import EventFileError

# Real sensors reorder events by ~10 us; a step back this large means a corrupt file.
MAX_TIME_REVERSAL_US = 1_000_000
# Files are read in blocks of this many bytes, so memory stays bounded for any file size.
BLOCK_BYTES = 16 << 20

COORD_LIMIT = 1 << 16
"""Event coordinates are uint16: no sensor is larger a side."""
MAX_INFLATION = 100.0
"""Event columns compress 4-6 times (npz and DSEC-layout HDF5 of a real EVT 3.0 recording or of
synthetic events): a file whose columns decode to more than this many times its size is a
decompression bomb or corrupt, and is refused before it is inflated."""
INFLATION_FLOOR_BYTES = 16 << 20
"""What any file may decode to whatever its size (a test's file of one repeated event)."""
INFLATION_ENV = "EVENTOCC_MAX_INFLATION"
"""Overrides ``MAX_INFLATION``, for a real file that compresses better than event data does."""

# (events, bytes of the source consumed so far): what a reader's generator yields.
Progressed = tuple[np.ndarray, int]


def sensor_size(
    path: Path, width: object, height: object, *, limit: int = COORD_LIMIT, where: str
) -> tuple[int, int] | tuple[None, None]:
    """The sensor size a file states, checked: two whole numbers 1..``limit``; (None, None)
    when it states none. A damaged header's size would otherwise reach the compiled checks
    (a 20-digit height overflowed them)."""
    if width is None or height is None:
        return None, None
    try:
        w, h = operator.index(width), operator.index(height)
    except TypeError:
        raise EventFileError(
            path, f"sensor size {width!r} x {height!r} is not two whole numbers", where=where
        ) from None
    if not (0 < w <= limit and 0 < h <= limit):
        raise EventFileError(
            path, f"sensor size {w}x{h} is not 1..{limit} pixels a side", where=where
        )
    return w, h


def max_inflation() -> float:
    """``MAX_INFLATION``, or the environment's ``EVENTOCC_MAX_INFLATION``."""
    value = os.environ.get(INFLATION_ENV)
    if value is None:
        return MAX_INFLATION
    try:
        limit = float(value)
    except ValueError:
        limit = float("nan")
    if not limit > 0:
        raise ValueError(f"{INFLATION_ENV} must be a positive number, got {value!r}")
    return limit


def check_inflation(path: Path, decoded: int, stored: int, *, where: str) -> None:
    """Refuse a file whose columns would decode to more than ``max_inflation()`` times the
    ``stored`` bytes (or ``INFLATION_FLOOR_BYTES``): the readers' bound on memory and time."""
    limit = max_inflation()
    if decoded <= max(INFLATION_FLOOR_BYTES, limit * stored):
        return
    raise EventFileError(
        path,
        f"its columns decode to {decoded:,} bytes, {decoded / max(stored, 1):,.0f} times its "
        f"{stored:,}; event data inflates at most {limit:g} times (or to "
        f"{INFLATION_FLOOR_BYTES >> 20} MiB), so this is a decompression bomb or corrupt. If "
        f"the file is real, allow it with {INFLATION_ENV}={decoded / max(stored, 1) * 1.1:.0f}",
        where=where,
    )


class EventStream:
    """An iterator of event chunks from one file, with the metadata known before reading.

    ``width``/``height`` are ``None`` when the file does not say (events are then only checked
    against the format's own coordinate range). ``position`` and ``size`` count bytes of the
    source and drive progress bars.
    """

    def __init__(
        self,
        chunks: Iterable[Progressed],
        *,
        path: Path,
        format: str,
        width: int | None,
        height: int | None,
        size: int,
    ) -> None:
        self.path = path
        self.format = format
        self.width = width
        self.height = height
        self.size = size
        self.position = 0
        self._source = iter(chunks)
        self._chunks: Iterator[np.ndarray] = self._track(self._source)

    def _track(self, chunks: Iterator[Progressed]) -> Iterator[np.ndarray]:
        for events, position in chunks:
            self.position = position
            yield events

    def map_chunks(self, transform) -> EventStream:
        """Apply ``transform(chunks) -> chunks`` (rechunking, error policy) in place."""
        self._chunks = transform(self._chunks)
        return self

    def __iter__(self) -> EventStream:
        return self

    def __next__(self) -> np.ndarray:
        return next(self._chunks)

    def close(self) -> None:
        """Release the file now rather than when the stream is garbage-collected."""
        for gen in (self._chunks, self._source):
            close = getattr(gen, "close", None)
            if close is not None:
                close()

    def __enter__(self) -> EventStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        size = f"{self.width}x{self.height}" if self.width else "unknown size"
        return f"EventStream({str(self.path)!r}, format={self.format!r}, {size})"


class EventChecker:
    """Finds the first implausible event in consecutive chunks of one stream.

    Implausible: a coordinate outside the sensor, a negative time, or a time more than
    ``MAX_TIME_REVERSAL_US`` before the latest time seen so far.
    """

    def __init__(
        self, width: int | None, height: int | None, coord_limit: int = COORD_LIMIT
    ) -> None:
        self.width = width or coord_limit
        self.height = height or coord_limit
        self.t_max = np.iinfo(np.int64).min

    def first_problem(self, events: np.ndarray) -> tuple[int, str] | None:
        """Index and description of the first bad event, or ``None``; remembers the good ones."""
        if not len(events):
            return None
        i, latest = _first_bad(events, self.width, self.height, self.t_max, MAX_TIME_REVERSAL_US)
        if i < 0:
            self.t_max = latest
            return None
        ev = events[i]
        if ev["x"] >= self.width or ev["y"] >= self.height:
            return i, (
                f"event at x={ev['x']}, y={ev['y']} is outside the "
                f"{self.width}x{self.height} sensor"
            )
        if ev["t"] < 0:
            return i, f"negative timestamp {ev['t']} us"
        return i, (
            f"time goes back from {latest} to {ev['t']} us, more than "
            f"{MAX_TIME_REVERSAL_US} us: not a real sensor's reordering"
        )


@numba.njit(cache=True, nogil=True)
def _first_bad(events, width, height, t_max, max_reversal):
    """(index of the first event outside the sensor, before time 0 or ``max_reversal`` before
    the latest time so far, or -1; the latest time before it). One pass: numpy's version took
    five, a quarter of a DAT file's reading time."""
    for i in range(events.shape[0]):
        e = events[i]
        if e.x >= width or e.y >= height or e.t < 0 or e.t + max_reversal < t_max:
            return i, t_max
        t_max = max(t_max, e.t)
    return -1, t_max


def as_event_chunks(chunks: np.ndarray | Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    """Accept one event array or an iterable of them, as ``EVENT_DTYPE`` arrays."""
    if isinstance(chunks, np.ndarray):
        chunks = [chunks]
    for chunk in chunks:
        if chunk.dtype != EVENT_DTYPE:
            if chunk.dtype.names is None or not {"t", "x", "y", "p"} <= set(chunk.dtype.names):
                raise ValueError(
                    f"events must be a structured array with fields t, x, y, p, got {chunk.dtype}"
                )
            converted = np.empty(len(chunk), EVENT_DTYPE)
            for name in ("t", "x", "y"):
                converted[name] = chunk[name]
            converted["p"] = np.where(chunk["p"] > 0, 1, -1)
            chunk = converted
        yield chunk


def check_writable(events: np.ndarray, *, format: str, width: int, height: int, max_t: int) -> None:
    """Raise ``ValueError`` if ``events`` cannot be stored in ``format`` as they are."""
    if not len(events):
        return
    t = events["t"]
    if t.min() < 0:
        raise ValueError(
            f"{format} cannot store negative timestamps (got {t.min()} us); "
            "shift the events to start at t >= 0"
        )
    if t.max() > max_t:
        raise ValueError(
            f"{format} stores timestamps up to {max_t} us, got {t.max()} us; "
            "shift the events closer to t = 0"
        )
    if events["x"].max() >= width or events["y"].max() >= height:
        raise ValueError(
            f"events reach x={events['x'].max()}, y={events['y'].max()}, outside the "
            f"{width}x{height} sensor given for {format}"
        )


def sorted_by_time(events: np.ndarray) -> np.ndarray:
    """The events in time order (stable, so a sorted chunk comes back unchanged)."""
    t = events["t"]
    if len(t) < 2 or bool(np.all(t[1:] >= t[:-1])):
        return events
    return events[np.argsort(t, kind="stable")]


def read_blocks(f: BinaryIO, word_bytes: int, block_bytes: int) -> Iterator[bytes]:
    """Consecutive blocks of ``f`` from its current position, each a whole number of words
    except possibly the last (which callers report as truncation)."""
    block_bytes -= block_bytes % word_bytes
    while block := f.read(block_bytes):
        yield block
