"""One compiled pass over every event while the marker is tracked.

Neither consumer needs every event. The decoder reads each pixel once per frame (the union of
its events, as the paper ORs its samples), so it needs only *when each pixel's latest burst of
each polarity began*: a per-pixel time surface. The tracker needs only the events near the
ring's projected edges. Both come out of one pass over the raw chunk, which costs a few memory
accesses per event; everything after it works per pixel or on the few selected events.

A burst is a run of same-polarity events with no gap longer than ``gap_us``: a cell switching
fires its pixels several times within the display's response, and the same pixel cannot switch
the same way again for two refreshes (or a data frame and a blank one).

The tracker's selection is a mask of coarse tiles (``TILE`` px) of the raw sensor that lie within
reach of an edge: cheap enough to rebuild whenever the pose moves the edges by a pixel, and
generous, since the tracker applies its exact gates to what it gets.
"""

from __future__ import annotations

import numba
import numpy as np

from receiver.pipeline.buffer import EventColumns

TILE = 4
"""Side of the tracker-mask tiles in pixels, a power of two (tile = pixel >> _SHIFT)."""
_SHIFT = TILE.bit_length() - 1
_NEVER = -(1 << 30)
_REBASE_US = 1 << 29
"""Surface times are int32 microseconds since an epoch (half the cache footprint of int64: the
surface is read at random for every event); the epoch moves on before they could overflow."""


@numba.njit(cache=True, nogil=True)
def _triage(t, x, y, p, surface, epoch, gap_us, tiles, table):
    """Update ``surface[y, x, polarity] = (burst start, last event)`` (ON only when the surface
    has one polarity); return the events on the marked ``tiles`` as columns (t, x, y, p, xu,
    yu)."""
    n = t.shape[0]
    ct, cx, cy = np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint16)
    cp, xu, yu = np.empty(n, np.int8), np.empty(n, np.float32), np.empty(n, np.float32)
    polarities = surface.shape[2]
    k = 0
    for i in range(t.shape[0]):
        xi, yi = x[i], y[i]
        d = 0 if p[i] > 0 else 1
        if d < polarities:
            ti = np.int32(t[i] - epoch)
            s = surface[yi, xi, d]
            if ti - s[1] > gap_us:
                s[0] = ti
            s[1] = ti
        if tiles[yi >> _SHIFT, xi >> _SHIFT]:
            ct[k], cx[k], cy[k], cp[k] = t[i], xi, yi, p[i]
            xu[k], yu[k] = table[yi, xi, 0], table[yi, xi, 1]
            k += 1
    return ct[:k], cx[:k], cy[:k], cp[:k], xu[:k], yu[:k]


@numba.njit(cache=True, nogil=True)
def _bursts_between(surface, epoch, t0, t1, x0, x1, y0, y1, table):
    """(t, x, y, p, xu, yu) of the bursts that began in ``[t0, t1)`` (since ``epoch``) on the
    pixels of the box."""
    polarities = surface.shape[2]
    n = 0
    for yy in range(y0, y1):
        for xx in range(x0, x1):
            for d in range(polarities):
                if t0 <= surface[yy, xx, d, 0] < t1:
                    n += 1
    t = np.empty(n, np.int64)
    x, y = np.empty(n, np.uint16), np.empty(n, np.uint16)
    xu, yu = np.empty(n, np.float32), np.empty(n, np.float32)
    p = np.empty(n, np.int8)
    k = 0
    for yy in range(y0, y1):
        for xx in range(x0, x1):
            for d in range(polarities):
                ts = surface[yy, xx, d, 0]
                if t0 <= ts < t1:
                    t[k], x[k], y[k] = ts + epoch, xx, yy
                    xu[k], yu[k] = table[yy, xx, 0], table[yy, xx, 1]
                    p[k] = 1 - 2 * d
                    k += 1
    return t, x, y, p, xu, yu


@numba.njit(cache=True, nogil=True)
def _mark_tiles(tiles, table, a, b, reach, tx0, tx1, ty0, ty1):
    """Mark the tiles of the box whose centre (in ideal pixels) lies within ``reach`` of an edge."""
    tiles[:] = False
    half = TILE // 2
    height, width = table.shape[0], table.shape[1]
    for ty in range(ty0, ty1):
        for tx in range(tx0, tx1):
            cy, cx = min(ty * TILE + half, height - 1), min(tx * TILE + half, width - 1)
            px, py = table[cy, cx, 0], table[cy, cx, 1]
            for e in range(a.shape[0]):
                dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
                L2 = dx * dx + dy * dy
                w = ((px - a[e, 0]) * dx + (py - a[e, 1]) * dy) / L2 if L2 > 0 else 0.0
                w = min(max(w, 0.0), 1.0)
                ex, ey = a[e, 0] + w * dx - px, a[e, 1] + w * dy - py
                if ex * ex + ey * ey <= reach * reach:
                    tiles[ty, tx] = True
                    break


class EventTriage:
    """Per-pixel burst surfaces for the decoder and the near-edge events for the tracker."""

    def __init__(
        self, undistort_table: np.ndarray, gap_us: float, both_polarities: bool, epoch_us: int = 0
    ) -> None:
        self._table = np.ascontiguousarray(undistort_table, np.float32)
        height, width = self._table.shape[:2]
        self.surface = np.full((height, width, 2 if both_polarities else 1, 2), _NEVER, np.int32)
        self.epoch_us = epoch_us
        self.gap_us = int(gap_us)
        self._tiles = np.zeros((-(-height // TILE), -(-width // TILE)), np.bool_)
        self._edges: np.ndarray | None = None

    def reset(self, epoch_us: int) -> None:
        """Forget every burst and the tracked edges (a new lock)."""
        self.surface.fill(_NEVER)
        self.epoch_us = epoch_us
        self._tiles[:] = False
        self._edges = None

    def __call__(self, events: np.ndarray) -> EventColumns:
        """Integrate ``events`` (structured) into the surfaces; the near-edge ones as columns."""
        if len(events) and int(events["t"][-1]) - self.epoch_us > _REBASE_US:
            shift = int(events["t"][0]) - self.epoch_us - (1 << 20)
            self.surface[:] = np.maximum(self.surface.astype(np.int64) - shift, _NEVER)
            self.epoch_us += shift
        return EventColumns(
            *_triage(
                events["t"],
                events["x"],
                events["y"],
                events["p"],
                self.surface,
                self.epoch_us,
                self.gap_us,
                self._tiles,
                self._table,
            )
        )

    def track_near(self, a: np.ndarray, b: np.ndarray, reach_px: float) -> None:
        """Select the events within about ``reach_px`` of the segments ``a[i] -> b[i]`` (ideal
        pixels) from now on. Cheap when the edges have not moved by a pixel."""
        edges = np.concatenate([a, b], axis=1)
        if self._edges is not None and np.abs(edges - self._edges).max() < 1.0:
            return
        self._edges = edges
        reach = reach_px + TILE * 0.75  # a tile centre stands for pixels up to ~0.7 tile away
        # The box is in raw pixels and the edges in ideal ones: two tiles cover the distortion.
        lo = np.floor((np.minimum(a, b).min(axis=0) - reach) / TILE).astype(int) - 2
        hi = np.ceil((np.maximum(a, b).max(axis=0) + reach) / TILE).astype(int) + 3
        ty, tx = self._tiles.shape
        _mark_tiles(
            self._tiles,
            self._table,
            a,
            b,
            reach,
            max(lo[0], 0),
            min(hi[0], tx),
            max(lo[1], 0),
            min(hi[1], ty),
        )

    def bursts(self, t0: int, t1: int, box: tuple[int, int, int, int]) -> EventColumns:
        """The pixel bursts that began in ``[t0, t1)`` inside ``box`` = (x0, x1, y0, y1): one
        entry per pixel and polarity, with the burst's start as its time."""
        e = self.epoch_us
        lo, hi = max(t0 - e, _NEVER + 1), min(t1 - e, (1 << 31) - 1)
        return EventColumns(*_bursts_between(self.surface, e, lo, hi, *box, self._table))
