"""A time-bounded buffer of recent events with their undistorted coordinates, kept as chunks so
that appending and trimming never copy the whole window."""

from __future__ import annotations

from collections import deque

import numpy as np

from receiver.events import EVENT_DTYPE

BUFFER_DTYPE = np.dtype([*EVENT_DTYPE.descr, ("xu", np.float32), ("yu", np.float32)])


class EventBuffer:
    def __init__(self, undistort_table: np.ndarray, keep_us: int) -> None:
        self._table = undistort_table
        self.keep_us = keep_us
        self._chunks: deque[np.ndarray] = deque()

    def append(self, events: np.ndarray) -> np.ndarray:
        """Store ``events``; returns them with ``xu``/``yu`` (ideal pixel coordinates)."""
        out = np.empty(len(events), BUFFER_DTYPE)
        for name in EVENT_DTYPE.names:
            out[name] = events[name]
        ideal = self._table[events["y"], events["x"]]
        out["xu"], out["yu"] = ideal[:, 0], ideal[:, 1]
        if len(out):
            self._chunks.append(out)
            newest = int(out["t"][-1])
            while self._chunks and int(self._chunks[0]["t"][-1]) < newest - self.keep_us:
                self._chunks.popleft()
        return out

    @property
    def span(self) -> tuple[int, int] | None:
        if not self._chunks:
            return None
        return int(self._chunks[0]["t"][0]), int(self._chunks[-1]["t"][-1])

    def between(self, t0: int, t1: int) -> np.ndarray:
        """Events with ``t0 <= t < t1`` (chunks are sorted up to sensor jitter)."""
        parts = []
        for chunk in self._chunks:
            if chunk["t"][-1] < t0 or chunk["t"][0] >= t1:
                continue
            ts = chunk["t"]
            parts.append(chunk[np.searchsorted(ts, t0) : np.searchsorted(ts, t1)])
        return np.concatenate(parts) if parts else np.empty(0, BUFFER_DTYPE)

    def clear(self) -> None:
        self._chunks.clear()
