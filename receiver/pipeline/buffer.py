"""A time-bounded buffer of recent events with their undistorted coordinates, kept as chunks so
that appending and trimming never copy the whole window.

Events are stored as contiguous columns rather than one structured array: the compiled
kernels downstream then read each field at full memory speed, and slicing a time window copies
only the columns' bytes.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, fields

import numba
import numpy as np


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
    def concatenate(cls, parts: list[EventColumns]) -> EventColumns:
        if len(parts) == 1:
            return parts[0]
        return cls(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)))

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
def _columns(t, x, y, p, table):
    """One pass over the (strided) fields of a structured chunk: contiguous copies plus the
    ideal coordinates looked up in the undistortion table."""
    n = t.shape[0]
    ct, cx, cy = np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16)
    cp, xu, yu = np.empty(n, np.int8), np.empty(n, np.float32), np.empty(n, np.float32)
    for i in range(n):
        ct[i], cx[i], cy[i], cp[i] = t[i], x[i], y[i], p[i]
        xu[i] = table[y[i], x[i], 0]
        yu[i] = table[y[i], x[i], 1]
    return ct, cx, cy, cp, xu, yu


class EventBuffer:
    def __init__(self, undistort_table: np.ndarray, keep_us: int) -> None:
        self._table = np.ascontiguousarray(undistort_table, np.float32)
        self.keep_us = keep_us
        self._chunks: deque[EventColumns] = deque()

    def append(self, events: np.ndarray) -> EventColumns:
        """Store ``events`` (structured, ``EVENT_DTYPE``); returns them as columns."""
        out = EventColumns(
            *_columns(events["t"], events["x"], events["y"], events["p"], self._table)
        )
        if len(out):
            self._chunks.append(out)
            newest = int(out.t[-1])
            while self._chunks and int(self._chunks[0].t[-1]) < newest - self.keep_us:
                self._chunks.popleft()
        return out

    @property
    def span(self) -> tuple[int, int] | None:
        if not self._chunks:
            return None
        return int(self._chunks[0].t[0]), int(self._chunks[-1].t[-1])

    def between(self, t0: int, t1: int) -> EventColumns:
        """Events with ``t0 <= t < t1`` (chunks are sorted up to sensor jitter)."""
        parts = []
        for chunk in self._chunks:
            ts = chunk.t
            if ts[-1] < t0 or ts[0] >= t1:
                continue
            parts.append(chunk[np.searchsorted(ts, t0) : np.searchsorted(ts, t1)])
        return EventColumns.concatenate(parts) if parts else EventColumns.empty()

    def clear(self) -> None:
        self._chunks.clear()
