"""A time-bounded buffer of recent raw event chunks, and the column form of events that the
compiled kernels downstream read.

The buffer keeps references to the chunks as they came (no copy: at a million-pixel sensor's
event rates even one copy of every event costs more than the rest of the receiver). Only the
windows somebody asks for become columns, with their undistorted coordinates.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, fields

import numba
import numpy as np

from eventocc.receiver.events import EVENT_DTYPE


@dataclass(frozen=True)
class EventColumns:
    """Time-sorted events as columns; ``xu``/``yu`` are ideal (undistorted) pixel coordinates.

    Indexing by a field name gives the column, by a slice or index array the selected events,
    as with the structured event arrays elsewhere in the receiver."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray
    xu: np.ndarray
    yu: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def __getitem__(self, key: str | slice | np.ndarray) -> np.ndarray | EventColumns:
        if isinstance(key, str):
            return getattr(self, key)
        return EventColumns(*(getattr(self, f.name)[key] for f in fields(self)))

    @classmethod
    def empty(cls) -> EventColumns:
        return cls(
            np.empty(0, np.int64),
            np.empty(0, np.uint16),
            np.empty(0, np.uint16),
            np.empty(0, np.int8),
            np.empty(0, np.float32),
            np.empty(0, np.float32),
        )


@numba.njit(cache=True, nogil=True)
def ideal_coordinates(x, y, table):
    """(xu, yu) of raw pixels (x, y), looked up in the undistortion table."""
    xu, yu = np.empty(x.shape[0], np.float32), np.empty(x.shape[0], np.float32)
    for k in range(x.shape[0]):
        xu[k], yu[k] = table[y[k], x[k], 0], table[y[k], x[k], 1]
    return xu, yu


@numba.njit(cache=True, nogil=True)
def _columns(events, table):
    """Contiguous columns of the records, plus their ideal coordinates."""
    n = events.shape[0]
    ct, cx, cy = np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16)
    cp = np.empty(n, np.int8)
    for k in range(n):
        e = events[k]
        ct[k], cx[k], cy[k], cp[k] = e.t, e.x, e.y, e.p
    xu, yu = ideal_coordinates(cx, cy, table)
    return ct, cx, cy, cp, xu, yu


@numba.njit(cache=True, nogil=True)
def first_at(t: np.ndarray, value: int) -> int:
    """Index of the first ``t >= value`` in sorted ``t``: ``np.searchsorted`` without the
    contiguous copy it makes of a structured array's field."""
    lo, hi = 0, t.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if t[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


def to_columns(events: np.ndarray, undistort_table: np.ndarray) -> EventColumns:
    """Structured events (``EVENT_DTYPE``) as columns with their ideal coordinates."""
    return EventColumns(*_columns(events, undistort_table))


class EventBuffer:
    """Recent chunks, kept until ``forget_before`` says nobody will read them again."""

    def __init__(self) -> None:
        self._chunks: list[np.ndarray] = []
        self._ends: list[int] = []
        """Each chunk's last event time, for bisecting."""

    def append(self, events: np.ndarray) -> None:
        """Keep ``events`` (structured, ``EVENT_DTYPE``, time-sorted, after those kept)."""
        if len(events):
            self._chunks.append(events)
            self._ends.append(int(events["t"][-1]))

    def forget_before(self, t_us: int) -> None:
        """Drop the chunks that end before ``t_us``."""
        k = bisect.bisect_left(self._ends, t_us)
        del self._chunks[:k], self._ends[:k]

    @property
    def span(self) -> tuple[int, int] | None:
        if not self._chunks:
            return None
        return int(self._chunks[0]["t"][0]), self._ends[-1]

    def parts_between(self, t0: int, t1: int) -> list[np.ndarray]:
        """Views of the kept chunks cut to ``t0 <= t < t1``, in time order."""
        parts = []
        for chunk in self._chunks[bisect.bisect_left(self._ends, t0) :]:
            ts = chunk["t"]
            if ts[0] >= t1:
                break
            parts.append(chunk[first_at(ts, t0) : first_at(ts, t1)])
        return parts

    def between(self, t0: int, t1: int) -> np.ndarray:
        """Structured events with ``t0 <= t < t1`` (one array: a copy if they span chunks)."""
        parts = self.parts_between(t0, t1)
        if len(parts) == 1:
            return parts[0]
        return np.concatenate(parts) if parts else np.empty(0, EVENT_DTYPE)
