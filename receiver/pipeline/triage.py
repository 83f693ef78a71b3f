"""One compiled pass over every event while the marker is tracked.

Neither consumer needs every event. The decoder reads each pixel once per frame (the union of
its events, as the paper ORs its samples), so it needs only *when each pixel's bursts of each
polarity began*: a per-pixel time surface of the latest burst's start and of the first one's
since the current frame's window opened (``EventTriage.marks_us``). The tracker needs only the
events near the ring's projected edges. Both come out of one pass over the raw chunk, which
costs a few memory accesses per event; everything after it works per pixel or on the few
selected events.

A frame's scan-out takes most of a refresh, and at 6 px/ms the images of the rows already
switched sweep over the pixels of the rows still to come: a bottom row's pixel often fires for a
neighbour before its own switch, and again after it. So the first burst is kept from two times
on (``marks_us``): the frame window's start, for the rows that switch early, and a later one
for the rest, where cells are large enough (``DecoderParams.late_mark_px_per_cell``).

A burst is a run of same-polarity events with no gap longer than ``gap_us`` (with both
polarities kept, an OFF burst's gaps are unbounded: ``_burst``) and no event of the other
polarity: a cell switching fires its pixels several times within the display's response,
and the same pixel cannot switch the same way again for two refreshes (or a data frame and a
blank one), unless motion sweeps an edge's image over it. At 6 px/ms the scan-out spreads a
frame's bursts over ~10 ms, in which a white cell's pixel is often relit once or twice by its
neighbours' images: the first burst is the display's switch, the latest one is not. With ON
events alone (``paper``, ``robust``) a burst also ends where its pixel's read gate opens
(``EventTriage.cut_plane``): behind a display still fading from the frame before, motion turns a
pixel onto a lit cell's glow in the blank refresh and it fires ON up to a few milliseconds before
its own cell switches on, with no OFF event between.

Cells much larger than the decoder needs (a 1280x720 camera close to an N = 16 marker sees 22 px
per cell and ~140 M events a second) are read from a coarser surface: only the pixels on every
``stride``-th row and column update it, which cuts the pass's random memory traffic by
``stride``² while the tracker still sees every pixel's events.

The tracker's selection is a mask of coarse tiles (``TILE`` px) of the raw sensor that lie within
reach of an edge: cheap enough to rebuild whenever the pose moves the edges by a pixel, and
generous, since the tracker applies its exact gates to what it gets.
"""

from __future__ import annotations

import numba
import numpy as np

from eventocc.receiver.pipeline.buffer import EventColumns, ideal_coordinates
from eventocc.receiver.pipeline.config import TrackerParams

TILE = 4
"""Side of the tracker-mask tiles in pixels, a power of two (tile = pixel >> _SHIFT)."""
_SHIFT = TILE.bit_length() - 1
_NEVER = -(1 << 30)
_REBASE_US = 1 << 29
"""Surface times are int32 microseconds since an epoch (half the cache footprint of int64: the
surface is read at random for every event); the epoch moves on before they could overflow."""


_SLOTS = 4
"""Times per pixel and polarity: the latest burst's start, its last event, and the first
burst's start from each of the two marks on (16 bytes: an entry never straddles a cache line)."""

_RARE_SHARE = 0.05
"""Below this share of events near the edges, the dense pass tests each event's tile with a
branch, which then predicts well (a still camera); above, it counts without one (a moving
camera, or a small sensor that sees the blinking cells near the edges). Either way it picks
the same events."""
_OFF_GRID = -(1 << 30)
_BLOCK = 1024
"""Events whose on-grid ones are gathered, and whose near-edge ones are copied out, at a time
(their records stay in the L1 cache)."""


@numba.njit(cache=True, nogil=True, inline="always")
def _burst(pixels, e, at, epoch, gap_us, mark, mark2, cut):
    """Note event ``e`` in the burst times of its pixel, ``pixels[at]`` (ON only when the
    surface has one polarity): the latest burst's start and last event, and the first burst's
    start from ``mark`` on and from ``mark2`` on. An event of the other polarity ends a burst: a
    moving edge darkens and relights a pixel well within ``gap_us``. On the ON-only surface a
    burst also ends where its pixel's read gate opens, ``cut`` = (a, b, c): at time
    ``a + b * x + c * y`` (``EventTriage.cut_plane``).

    With both polarities (``fast``), a change of polarity starts a burst: each switch of a
    toggling cell reverses its pixels' polarity, while an OFF event long after the last (a
    pixel's slow settling towards black) is no switch. An ON event also starts one after a gap
    of ``gap_us`` (``DecoderParams.fast_on_gap_us``): ON events bunch at a switch, and a dark
    pixel that a lit neighbour's light made fire ON gets no OFF event before its own switch.
    (The two surfaces' cases are written apart, each with its polarity a constant where it can
    be: an index throughout makes the pass slower.)"""
    ti = np.int32(e.t - epoch)
    if pixels.shape[1] == 1:
        if e.p > 0:
            last = pixels[at, 0, 1]
            starts = ti - last > gap_us
            if not starts:
                opens = cut[0] + cut[1] * e.x + cut[2] * e.y
                starts = last < opens <= ti
            _note(pixels, at, 0, ti, starts, mark, mark2)
        else:
            pixels[at, 0, 1] = _NEVER
    elif e.p > 0:
        pixels[at, 1, 1] = _NEVER
        _note(pixels, at, 0, ti, ti - pixels[at, 0, 1] > gap_us, mark, mark2)
    else:
        pixels[at, 0, 1] = _NEVER
        _note(pixels, at, 1, ti, pixels[at, 1, 1] == _NEVER, mark, mark2)


@numba.njit(cache=True, nogil=True, inline="always")
def _note(pixels, at, d, ti, starts, mark, mark2):
    """``_burst`` for an event of polarity index ``d`` at time ``ti``; ``starts``: it begins a
    burst."""
    if starts:
        pixels[at, d, 0] = ti
        if pixels[at, d, 2] < mark:
            pixels[at, d, 2] = ti
        if pixels[at, d, 3] < mark2:
            pixels[at, d, 3] = ti
    pixels[at, d, 1] = ti


@numba.njit(cache=True, nogil=True)
def _pick(events, start, stop, every, tiles, rare, selected, k):
    """Append to ``selected[:k]`` the indices ``start``, ``start + every``, ... before ``stop``
    of the events on marked tiles; return the new count. ``rare``: few are, and a branch
    predicts well; otherwise none."""
    for i in range(start, stop, every):
        e = events[i]
        if rare:
            if tiles[e.y >> _SHIFT, e.x >> _SHIFT]:
                selected[k] = i
                k += 1
        else:
            selected[k] = i
            k += tiles[e.y >> _SHIFT, e.x >> _SHIFT]
    return k


@numba.njit(cache=True, nogil=True)
def _take(events, index, count, t, x, y, p, k):
    """Copy the records at ``index[:count]`` into the columns from ``k`` on; return the new
    count."""
    for q in range(count):
        e = events[index[q]]
        t[k], x[k], y[k], p[k] = e.t, e.x, e.y, e.p
        k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _triage(events, bursts, grid, selection):
    """Update ``pixels[grid_y[y] + grid_x[x], polarity] = (latest burst's start, its last event,
    first burst's start from ``mark`` on, from ``mark2`` on)`` (the surface's pixels in one
    row-major axis) from the pixels on the stride's grid (``grid_*`` negative off it; ``dense``:
    every pixel is on it); return the columns (t, x, y, p) of the events on the marked
    ``tiles``, of every ``every``-th event from index ``first`` on (``first < every``: a call
    continuing another's thinning). ``rare``: few events lie on the marked tiles
    (``_RARE_SHARE``). Three records: ``bursts`` = (pixels, epoch, gap_us, mark, mark2, cut)
    (times since ``epoch``), ``grid`` = (grid_y, grid_x, dense), ``selection`` = (tiles,
    every, first, rare). Plain tuples, not NamedTuples: this runs per chunk, and building and
    typing those costs a few microseconds a call.

    ``events`` is the structured chunk itself: numba reads each record's fields in one go,
    faster than four strided field views. With a stride, whether an event lies on the grid is a
    coin toss that a branch would mispredict ~2 ns at a time: each block's on-grid events are
    first gathered without one. Each block's near-edge records are copied out while they are in
    the L1 cache, rather than after the whole chunk (as the dense pass does, whose picks are
    few)."""
    pixels, epoch, gap_us, mark, mark2, cut = bursts
    grid_y, grid_x, dense = grid
    tiles, every, first, rare = selection
    n = events.shape[0]
    size = -(-n // every)  # pages are touched only as far as written
    t, x, y = np.empty(size, np.int64), np.empty(size, np.uint16), np.empty(size, np.uint16)
    p = np.empty(size, np.int8)
    if dense:  # the bursts in one pass (blocks, and the grid's tables, are slower here)
        width = grid_x.shape[0]
        for i in range(n):
            e = events[i]
            _burst(pixels, e, np.int64(e.y) * width + e.x, epoch, gap_us, mark, mark2, cut)
        picked = np.empty(size, np.int64)
        k = _pick(events, first, n, every, tiles, rare, picked, 0)
        k = _take(events, picked, k, t, x, y, p, 0)
        return t[:k], x[:k], y[:k], p[:k]
    k = 0
    picked = np.empty(_BLOCK, np.int64)
    on_grid, at = np.empty(_BLOCK, np.int64), np.empty(_BLOCK, np.int32)
    for b0 in range(0, n, _BLOCK):
        b1 = min(b0 + _BLOCK, n)
        g = 0
        for i in range(b0, b1):
            e = events[i]
            on_grid[g] = i
            at[g] = grid_y[e.y] + grid_x[e.x]
            g += at[g] >= 0
        for j in range(g):
            _burst(pixels, events[on_grid[j]], at[j], epoch, gap_us, mark, mark2, cut)
        found = _pick(events, b0 + (first - b0) % every, b1, every, tiles, rare, picked, 0)
        k = _take(events, picked, found, t, x, y, p, k)
    return t[:k], x[:k], y[:k], p[:k]


@numba.njit(cache=True, nogil=True, inline="always")
def _new(surface, gy, gx, d, j, ts):
    """Whether slot ``j``'s burst start ``ts`` is not one of the slots read before it (2, 3, 0)."""
    if j == 2:
        return True
    if ts == surface[gy, gx, d, 2]:
        return False
    return j == 3 or ts != surface[gy, gx, d, 3]


@numba.njit(cache=True, nogil=True)
def _bursts_between(surface, epoch, t0, t1, box, table, stride):
    """(t, x, y, p, xu, yu) of the bursts that began in ``[t0, t1)`` (since ``epoch``) on the
    grid's pixels in ``box`` = (x0, x1, y0, y1), in one pass (the outputs are sized for every
    pixel, touched as filled)."""
    x0, x1, y0, y1 = box
    polarities = surface.shape[2]
    gy0, gy1 = -(-y0 // stride), -(-y1 // stride)
    gx0, gx1 = -(-x0 // stride), -(-x1 // stride)
    size = max(gy1 - gy0, 0) * max(gx1 - gx0, 0) * polarities * 3
    t = np.empty(size, np.int64)
    x, y = np.empty(size, np.uint16), np.empty(size, np.uint16)
    xu, yu = np.empty(size, np.float32), np.empty(size, np.float32)
    p = np.empty(size, np.int8)
    k = 0
    for gy in range(gy0, gy1):
        yy = gy * stride
        for gx in range(gx0, gx1):
            xx = gx * stride
            for d in range(polarities):
                for j in (2, 3, 0):  # the first bursts from the marks on, then the latest
                    ts = surface[gy, gx, d, j]
                    if t0 <= ts < t1 and _new(surface, gy, gx, d, j, ts):
                        t[k], x[k], y[k] = ts + epoch, xx, yy
                        xu[k], yu[k] = table[yy, xx, 0], table[yy, xx, 1]
                        p[k] = 1 - 2 * d
                        k += 1
    return t[:k], x[:k], y[:k], p[:k], xu[:k], yu[:k]


@numba.njit(cache=True, nogil=True, inline="always")
def _tile_span(lo, hi, pixels, tiles):
    """The tiles covering pixels ``lo..hi`` (clamped to the sensor, plus a tile, before the
    integer conversion: a pose far off the view projects to huge coordinates)."""
    lo, hi = min(max(lo, -TILE), pixels + TILE), min(max(hi, -TILE), pixels + TILE)
    return range(max(int(np.floor(lo / TILE)), 0), min(int(np.ceil(hi / TILE)) + 1, tiles))


@numba.njit(cache=True, nogil=True)
def _mark_tiles(tiles, table, a, b, reach, margin):
    """Mark the tiles whose centre (in ideal pixels) lies within ``reach`` of an edge. Each
    row of tiles searches only the columns that the edge's stretch within its reach can touch
    (``margin`` tiles wider, for the distortion between raw and ideal pixels): a long slanted
    edge's bounding box holds tens of times the tiles near it."""
    tiles[:] = False
    half = TILE // 2
    height, width = table.shape[0], table.shape[1]
    rows, cols = tiles.shape
    slack = reach + margin * TILE  # raw pixels from an ideal point within reach of the edge
    for e in range(a.shape[0]):
        ax, ay, dx, dy = a[e, 0], a[e, 1], b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
        L2 = dx * dx + dy * dy
        for ty in _tile_span(min(ay, b[e, 1]) - slack, max(ay, b[e, 1]) + slack, height, rows):
            cy = min(ty * TILE + half, height - 1)
            # The part of the edge whose y lies within ``slack`` of the row's centres, and the
            # columns within ``slack`` of it.
            s0, s1 = 0.0, 1.0
            if dy != 0:
                s0, s1 = (cy - slack - ay) / dy, (cy + slack - ay) / dy
                s0, s1 = max(min(s0, s1), 0.0), min(max(s0, s1), 1.0)
            elif abs(cy - ay) > slack:
                continue
            if s0 > s1:
                continue
            x_lo, x_hi = ax + min(s0 * dx, s1 * dx) - slack, ax + max(s0 * dx, s1 * dx) + slack
            for tx in _tile_span(x_lo, x_hi, width, cols):
                if tiles[ty, tx]:
                    continue
                cx = min(tx * TILE + half, width - 1)
                px, py = table[cy, cx, 0], table[cy, cx, 1]
                w = ((px - ax) * dx + (py - ay) * dy) / L2 if L2 > 0 else 0.0
                w = min(max(w, 0.0), 1.0)
                ex, ey = ax + w * dx - px, ay + w * dy - py
                if ex * ex + ey * ey <= reach * reach:
                    tiles[ty, tx] = True


def _grid_index(height: int, width: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Tables of the surface's pixel for each raw row and column on the grid of every
    ``stride``-th (row-major, summed), ``_OFF_GRID`` for the others (so that a sum with either
    stays negative): two lookups cost less than an integer division per event."""
    rows = np.full(height, _OFF_GRID, np.int32)
    cols = np.full(width, _OFF_GRID, np.int32)
    cols[::stride] = np.arange(len(cols[::stride]), dtype=np.int32)
    rows[::stride] = np.arange(len(rows[::stride]), dtype=np.int32) * len(cols[::stride])
    return rows, cols


class EventTriage:
    """Per-pixel burst surfaces for the decoder and the near-edge events for the tracker."""

    def __init__(
        self,
        undistort_table: np.ndarray,
        gap_us: float,
        both_polarities: bool,
        epoch_us: int = 0,
        still_share: float = TrackerParams.still_near_share,
        still_every: int = TrackerParams.still_lookup_every,
    ) -> None:
        """``still_share``, ``still_every``: the thinning of the tile lookups while the camera
        stands still (``TrackerParams.still_near_share``)."""
        self._table = np.ascontiguousarray(undistort_table, np.float32)
        height, width = self._table.shape[:2]
        self._polarities = 2 if both_polarities else 1
        self.surface = np.full((height, width, self._polarities, _SLOTS), _NEVER, np.int32)
        self.stride = 1
        """The surface holds the pixels on every ``stride``-th row and column (``reset``)."""
        self._grid = _grid_index(height, width, 1)
        """The surface's pixel (row-major) of raw pixel (y, x): ``_grid[0][y] + _grid[1][x]``,
        negative off the grid."""
        self._near_share = 1.0
        """Share of the events that lay near the edges in the latest call."""
        self.epoch_us = epoch_us
        self.marks_us = (epoch_us, epoch_us)
        """Each pixel's first burst from each of these times on is kept as well as its latest:
        set them to the start of a frame's window and to a time within it before its events
        arrive, and the frame sees the bursts of the display's switch even where motion has
        started newer ones since (a pixel's latest burst alone keeps only the last time an
        edge's image relit it)."""
        self.gap_us = int(gap_us)
        self.cut_plane: tuple[float, float, float] | None = None
        """ON-only surface: (a, b, c), the time ``a + b * x + c * y`` at which the read gate of
        the frame to come opens at raw pixel (x, y); a burst running into it ends there, so that
        a pixel that the moving camera turned onto a fading cell's light before its own cell
        switched on still shows the switch. None: no cut."""
        self._still = (still_share, still_every)
        self._tiles = np.zeros((-(-height // TILE), -(-width // TILE)), np.bool_)
        self._edges: np.ndarray | None = None
        # The tiles are raw pixels, the edges ideal ones: search this many tiles further.
        shift = max(
            np.nanmax(np.abs(self._table[..., 0] - np.arange(width))),
            np.nanmax(np.abs(self._table[..., 1] - np.arange(height)[:, None])),
        )
        self._warp_tiles = int(np.ceil(shift / TILE)) + 1

    def reset(self, epoch_us: int, stride: int = 1) -> None:
        """Forget every burst and the tracked edges (a new lock); keep the bursts of the pixels
        on every ``stride``-th row and column from now on."""
        if stride < 1:
            raise ValueError(f"triage stride must be a positive integer, got {stride}")
        height, width = self._table.shape[:2]
        shape = (-(-height // stride), -(-width // stride), self._polarities, _SLOTS)
        if self.surface.shape != shape:
            self.surface = np.empty(shape, np.int32)
        self.surface.fill(_NEVER)
        self.stride = stride
        self._grid = _grid_index(height, width, stride)
        self.epoch_us = epoch_us
        self.marks_us = (epoch_us, epoch_us)
        self.cut_plane = None
        self._near_share = 1.0
        self._tiles[:] = False
        self._edges = None

    def __call__(self, *parts: np.ndarray, per_ms: float | None = None) -> EventColumns:
        """Integrate the time-sorted event ``parts`` (structured; consecutive stretches of one
        stream, e.g. the ends of two chunks) into the surfaces; the near-edge ones as columns,
        evenly thinned to at most ``per_ms`` per millisecond of the parts (None: all). The parts
        are read in place, and give what their concatenation would."""
        parts = tuple(p for p in parts if len(p))
        if not parts:
            return EventColumns.empty()
        t_first, t_last = int(parts[0]["t"][0]), int(parts[-1]["t"][-1])
        if t_last - self.epoch_us > _REBASE_US:
            shift = t_first - self.epoch_us - (1 << 20)
            self.surface[:] = np.maximum(self.surface.astype(np.int64) - shift, _NEVER)
            self.epoch_us += shift
        n = sum(len(p) for p in parts)
        most = n if per_ms is None else max(int(per_ms * (t_last - t_first + 1) / 1000), 1)
        # Only every k-th event is looked up in the tiles, k from the share that lay near the
        # edges last time: at 140 M events a second the tracker keeps one near event in ten.
        share, (still_share, still_every) = self._near_share, self._still
        every = max(-int(-n * share // most), still_every if 0 < share < still_share else 1)
        epoch = self.epoch_us
        pixels = self.surface.reshape(-1, *self.surface.shape[2:])
        marks = [min(max(m - epoch, _NEVER), 1 << 30) for m in self.marks_us]
        a, b, c = self.cut_plane or (float(_NEVER + epoch), 0.0, 0.0)
        bursts = (pixels, epoch, self.gap_us, *marks, (float(a - epoch), float(b), float(c)))
        grid = (*self._grid, self.stride == 1)
        rare = self._near_share < _RARE_SHARE
        near, seen = [], 0
        for p in parts:
            near.append(_triage(p, bursts, grid, (self._tiles, every, -seen % every, rare)))
            seen += len(p)
        columns = (
            near[0] if len(near) == 1 else [np.concatenate(c) for c in zip(*near, strict=True)]
        )
        found = len(columns[0])
        self._near_share = found * every / n
        t, x, y, polarity = (c[:: max(-(-found // most), 1)] for c in columns)
        return EventColumns(t, x, y, polarity, *ideal_coordinates(x, y, self._table))

    def track_near(self, a: np.ndarray, b: np.ndarray, reach_px: float) -> None:
        """Select the events within about ``reach_px`` of the segments ``a[i] -> b[i]`` (ideal
        pixels) from now on. Cheap when the edges have not moved by a pixel."""
        edges = np.concatenate([a, b], axis=1)
        if self._edges is not None and np.abs(edges - self._edges).max() < 1.0:
            return
        self._edges = edges
        reach = reach_px + TILE * 0.75  # a tile centre stands for pixels up to ~0.7 tile away
        _mark_tiles(self._tiles, self._table, a, b, reach, self._warp_tiles)

    def bursts(self, t0: int, t1: int, box: tuple[int, int, int, int]) -> EventColumns:
        """The pixel bursts that began in ``[t0, t1)`` inside ``box`` = (x0, x1, y0, y1): up to
        three entries (the first from each of ``marks_us`` on and the latest) per pixel on the
        stride's grid and polarity, with the burst's start as its time."""
        e = self.epoch_us
        lo, hi = max(t0 - e, _NEVER + 1), min(t1 - e, (1 << 31) - 1)
        return EventColumns(
            *_bursts_between(self.surface, e, lo, hi, box, self._table, self.stride)
        )
