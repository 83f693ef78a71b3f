"""Data decoding (paper Sec. IV-D): read the cells of one data frame from its pixels' bursts.

Each pixel is read once per frame, as the paper ORs its samples: the pipeline's triage keeps, per
pixel and polarity, when its latest burst of events began and its first since the frame's time
span opened (``triage.EventTriage``), and a frame sees the bursts that began inside its span.
Every such burst is mapped to the locator grid (column, row in cells) by the plane homography of
the pose current at its start (the full camera model through the undistorted coordinates: never
the authors' affine approximation). A cell then reads as the share of its inner pixels that fired
inside the frame's gate: the time the display's scan-out reaches the pixel's row on the marker
(the clock below), plus the pixel response.

A still camera (the grid moved under ``_STILL_CELLS`` in the last few milliseconds) needs one
pose per frame and has each cell's inner pixels counted once, so a cell's share is exact. A
moving one takes a pose every ``DecoderParams.step_us`` and divides by the cell's image area.

Under hand-held motion five things keep the bits:

- the gate narrows to the spread of the locator's own bursts (a few hundred microseconds; ON,
  and for ``fast`` OFF too), because a black cell that a white neighbour's image sweeps over
  fires later, not at the switch;
- the frame is read as soon as that gate has passed, and the triage keeps each pixel's first
  burst of the frame besides its latest, because motion starts new ones within a refresh;
- the clock takes each locator row's densest span of bursts, not their median, because motion
  starts bursts on the white cells across the whole search gate;
- the grid is shifted by the sub-cell offset that shows the locator ring sharpest, because the
  tracked pose can sit a fraction of a cell off;
- ``paper`` and ``robust`` end a pixel's ON burst where its read gate opens, because a display
  still fading from the frame before lets motion turn a pixel onto a lit cell's glow, and it
  fires ON just before its own cell switches on (``EventTriage.cut_plane``).

- ``paper`` / ``robust`` (data frame + blank frame): ON bursts only; a white cell lights up.
- ``fast`` (one differential symbol per refresh): bursts of either polarity; a cell that toggles
  (bit 1) fires ON or OFF in that refresh, an untoggled one fires none. The inner locator is
  shown on even refreshes only, so its white cells toggle every refresh and read as 1. Blur
  makes a dark cell fire with its switching neighbours, each in its own direction, so a cell
  can read as the stronger of its two polarities (``CellReader._levels``). A cell that switched
  in the refresh before can only switch back, so it reads in that polarity, the other counting
  only where it stands out: a display whose fall outlasts the refresh starts some of a fall's
  OFF bursts in the next one.

The inner locator's known white and black cells give the reference densities and a score that
says whether the marker is really there; the payload's own two clusters of densities place the
threshold between them, and a cell's distance from it its confidence (``fast``, and the other
profiles behind a sparse readout, on the linear or the square-root scale of the densities,
whichever separates the clusters more: a capped readout spreads the lit cells' densities).

The frame clock is re-estimated from the ON bursts of the locator's white cells, row by row, at
every frame where the locator rises, so neither a display/receiver clock mismatch nor the
scan-out slope drifts. OFF bursts never feed it: a pixel's luminance falls exponentially, so
its OFF events spread over several milliseconds, while its ON events bunch at the switch.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numba
import numpy as np

from eventocc.receiver.pipeline.buffer import EventColumns
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.detector import ring_cells, turn_readings
from eventocc.receiver.pipeline.pose import plane_homography, project_ideal

_HISTORY = 32
"""Frames in the clock fit: long enough to average jitter, short enough to follow drift."""
_MIN_CLOCK_EVENTS = 20
_CLOCK_BIN_US = 50.0
"""Resolution of the per-row burst times (a few per cent of the shortest refresh period)."""
_PEAK_BINS = 6
"""A row's burst time is the centre of its densest ``_PEAK_BINS`` clock bins (300 us, about
the spread of a still camera's switch)."""
_SPREAD_PERCENT = 5.0
_SWITCH_RUN = 0.1
"""A switch's bursts begin where their smoothed excess last rose above this share of its peak
(``_switch_span``)."""
_GATE_PAD = 0.5
"""The read gate spans the central 90 % of the locator's bursts at the switch, widened by half
that span on each side (plus a clock bin) for the cells' stragglers."""
_ALIGN_STEP = 0.1
_ALIGN_SHIFTS = np.array(
    [(0.0, 0.0)]
    + [
        (du, dv)
        for du in np.arange(-3, 4) * _ALIGN_STEP
        for dv in np.arange(-3, 4) * _ALIGN_STEP
        if du or dv
    ]
)
"""Sub-cell grid offsets tried against the locator ring, the pose's own first: up to 0.3 cell,
a 0.6 ms pose lag at 2 px/ms on 4 px cells."""
_NO_SHIFT = _ALIGN_SHIFTS[:1]
_ALIGN_LOOKBACK_US = 5000
_ALIGN_MIN_MOTION = 0.25
"""The shift search runs only when the grid moved this many cells in the last
``_ALIGN_LOOKBACK_US``: a pose error of a fraction of a millisecond's motion is then a tenth
of a cell or more, the search's step. A still camera skips it (it costs a count per shift)."""
_STILL_CELLS = 0.05
"""Below this grid motion in ``_ALIGN_LOOKBACK_US`` a frame is unwarped with one pose: the
grid then moves a hundredth of a cell within a frame's gate."""
_RECOUNT_CELLS = 0.02
"""The cells' inner pixels are recounted once the grid moved this far since the last count."""
_ALIGN_GAIN = 0.02
"""A shifted grid must raise the ring's contrast by this much to replace the pose's own."""
_SPLIT_ROUNDS = 8
_SPLIT_RANGE = (0.25, 0.75)
"""The payload threshold is fitted to the payload's own densities (two-means, ``_SPLIT_ROUNDS``
rounds) and kept within this share of the way from the black to the white reference: a frame
of nearly one colour has no second cluster to find."""
_ROOT_MARGIN = 1.2
"""A frame is split on the square root of its densities only where that separates the clusters
this much better than the linear scale: a capped readout's unequal polarities give ``fast``
1.1-2.3 times the separation there, while dense cells at 4-5 px per cell give 1.04-1.1 and read
twenty times the bit errors on the root scale."""


_APART_MARGIN = 1.1
"""``fast`` reads its cells' polarities apart (``CellReader._levels``) only where that separates
the toggled and untoggled cells' clusters this much better than their sum: the sum counts every
event, and where a capped readout drops most of a switch's events, a toggled cell's few events
of the other polarity are what lift it over the threshold."""


@dataclass(frozen=True)
class FrameRead:
    index: int
    """Data frames since lock."""
    t_us: int
    """Burst time of the frame's locator rise at the middle row of the marker."""
    bits: np.ndarray
    confidence: np.ndarray
    locator_score: float
    """Michelson contrast of the inner locator's white and black cells: ~1 seen, ~0 absent (0
    too for a frame read before any burst timed the clock)."""
    pixels: int
    """Pixel bursts inside the frame's gates on the cells."""
    turns: np.ndarray = field(default_factory=lambda: np.zeros(4))
    """(4,) the locator ring read with the grid turned by 0..3 quarter turns
    (``detector.turn_readings``), in units of the ring's mean density (the same in every turn):
    a pose a quarter turn off can still show a high ``locator_score`` (the medians of the white
    and black cells), but it reads best at another turn."""


class FrameClock:
    """Burst time of data frame ``m`` at locator row ``r``: ``mid(m) + (r - n/2) * slope``."""

    def __init__(self, first_burst_us: float, frame_us: float, rows: int) -> None:
        self.nominal_us = frame_us
        self.rows = rows
        self._fit = (float(first_burst_us), float(frame_us))  # intercept, period
        self.slope_us = 0.0
        self._seen: deque[tuple[int, float]] = deque(maxlen=_HISTORY)
        self.correction_us = np.inf
        """How far the latest frame's bursts lay from where the clock had them (infinite until
        a second frame was seen): the clock's error, as far as the bursts tell."""

    def mid(self, m: int) -> float:
        return self._fit[0] + m * self._fit[1]

    @property
    def period_us(self) -> float:
        return self._fit[1]

    @property
    def timed(self) -> bool:
        """The clock has seen at least one frame's bursts (and with them the scan-out slope)."""
        return bool(self._seen)

    def observe(self, m: int, mid_us: float, slope_us: float) -> None:
        if self._seen:
            self.correction_us = abs(mid_us - self.mid(m))
        self.slope_us = slope_us if not self._seen else 0.7 * self.slope_us + 0.3 * slope_us
        self._seen.append((m, mid_us))
        if len(self._seen) >= 3:
            ms, ts = np.array(self._seen).T
            period, intercept = np.polyfit(ms, ts, 1)
            if abs(period / self.nominal_us - 1) < 0.02:
                self._fit = (intercept, period)
                return
        self._fit = (mid_us - m * self._fit[1], self._fit[1])


# --- per-event kernels ---------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _grid_coords(t, xu, yu, step_edges, to_grid):
    """Locator-grid (column, row) of each pixel burst through the homography of its time step
    (bursts come in pixel order, not time order)."""
    n = t.shape[0]
    u = np.empty(n, np.float32)
    v = np.empty(n, np.float32)
    last = step_edges.shape[0] - 2
    for i in range(n):
        s = 0
        while s < last and t[i] >= step_edges[s + 1]:
            s += 1
        A = to_grid[s]
        x, y = xu[i], yu[i]
        w = A[2, 0] * x + A[2, 1] * y + A[2, 2]
        if w <= 0:
            u[i] = v[i] = -1.0  # behind the camera
            continue
        u[i] = (A[0, 0] * x + A[0, 1] * y + A[0, 2]) / w
        v[i] = (A[1, 0] * x + A[1, 1] * y + A[1, 2]) / w
    return u, v


@numba.njit(cache=True, nogil=True)
def _locator_bursts(bursts, white, timing, polarity):
    """(row, time after the row's predicted burst) of the ``bursts`` = (t, p, u, v) of sign
    ``polarity`` on the locator's white cells inside the gate of ``timing`` (``_cell_bursts``)."""
    t, p, u, v = bursts
    mid, slope, gate_lo, gate_hi = timing
    n = white.shape[0]
    rows = np.empty(t.shape[0], np.int64)
    dts = np.empty(t.shape[0], np.float64)
    k = 0
    for i in range(t.shape[0]):
        if p[i] * polarity <= 0 or not (0.0 <= u[i] < n and 0.0 <= v[i] < n):
            continue
        r, c = int(v[i]), int(u[i])
        if not white[r, c]:
            continue
        dt = t[i] - (mid + (v[i] - 0.5 - n / 2) * slope)
        if gate_lo <= dt <= gate_hi:
            rows[k], dts[k] = r, dt
            k += 1
    return rows[:k], dts[:k]


@numba.njit(cache=True, nogil=True)
def _row_peaks(rows, dts, n, gate_lo, gate_hi, bin_us, width):
    """Per locator row: (centre of the ``width`` consecutive ``bin_us`` bins that hold the most
    ``dts``, how many they hold). The display's switch starts a row's bursts within a few
    response times, while a moving camera starts more on the white cells whenever their
    images sweep over dark pixels, evenly across the gate: a median would be pulled towards
    the gate's middle, the densest span stays on the switch."""
    bins = int((gate_hi - gate_lo) / bin_us) + 1
    hist = np.zeros((n, bins), np.int32)
    for i in range(rows.shape[0]):
        hist[rows[i], int((dts[i] - gate_lo) / bin_us)] += 1
    peak = np.full(n, np.nan)
    count = np.zeros(n, np.int64)
    for r in range(n):
        run = 0
        for b in range(bins):
            run += hist[r, b] - (hist[r, b - width] if b >= width else 0)
            if run > count[r]:
                count[r] = run
                peak[r] = gate_lo + (b + 1 - width / 2) * bin_us
    return peak, count


def _switch_span(
    dt: np.ndarray, lo: float, hi: float, floored: bool = False
) -> tuple[float, float] | None:
    """The span of the central ``100 - 2 * _SPREAD_PERCENT`` % of the bursts ``dt`` in
    ``[lo, hi]`` that lie above the even background of the bursts that motion starts (the
    median count per ``_CLOCK_BIN_US`` bin); None without such bursts. ``floored``: only those
    from where that excess, smoothed over ``_PEAK_BINS``, last rose above ``_SWITCH_RUN`` of its
    peak before the peak. A moving white cell's edges start OFF bursts all through the refresh
    before it switches off, a floor that the median of the quiet tail after the switch does not
    take off."""
    edges = np.arange(lo, hi + _CLOCK_BIN_US, _CLOCK_BIN_US)
    hist, _ = np.histogram(dt, edges)
    excess = np.maximum(hist - np.median(hist), 0.0)
    if floored:
        smooth = np.convolve(excess, np.ones(_PEAK_BINS) / _PEAK_BINS, mode="same")
        below = np.flatnonzero(smooth[: int(np.argmax(smooth))] < _SWITCH_RUN * smooth.max())
        if len(below):
            excess[: below[-1] + 1] = 0.0
    if not excess.sum():
        return None
    share = np.cumsum(excess) / excess.sum()
    first = np.searchsorted(share, _SPREAD_PERCENT / 100)
    last = np.searchsorted(share, 1 - _SPREAD_PERCENT / 100)
    return float(edges[first]), float(edges[last + 1])


@numba.njit(cache=True, nogil=True, inline="always")
def _inner_cell(u, v, n, margin):
    """(row, column) of the cell whose inner part holds the grid point (u, v), or (-1, -1)."""
    if not (0.0 <= u < n and 0.0 <= v < n):
        return -1, -1
    c, r = int(u), int(v)
    fu, fv = u - c, v - r
    if fu < margin or fu > 1.0 - margin or fv < margin or fv > 1.0 - margin:
        return -1, -1
    return r, c


@numba.njit(cache=True, nogil=True)
def _cell_bursts(bursts, n, timing, on_only, margin, shifts):
    """(shifts, 2, n, n) count of the ON and the OFF ``bursts`` = (t, p, u, v) (time,
    polarity, grid point) inside each cell's inner part and its row's time gate, on the grid
    moved by each of the (du, dv) ``shifts`` (cells). ``timing`` = (mid, slope, gate_lo,
    gate_hi): a burst at grid height ``v`` is predicted at ``mid + (v - 0.5 - n / 2) * slope``
    and read within [gate_lo, gate_hi] of that."""
    t, p, u, v = bursts
    mid, slope, gate_lo, gate_hi = timing
    count = np.zeros((shifts.shape[0], 2, n, n), np.int32)
    for i in range(t.shape[0]):
        if on_only and p[i] <= 0:
            continue
        d = 0 if p[i] > 0 else 1
        for s in range(shifts.shape[0]):
            ui, vi = u[i] + shifts[s, 0], v[i] + shifts[s, 1]
            r, c = _inner_cell(ui, vi, n, margin)
            if r < 0:
                continue
            dt = t[i] - (mid + (vi - 0.5 - n / 2) * slope)
            if gate_lo <= dt <= gate_hi:
                count[s, d, r, c] += 1
    return count


@numba.njit(cache=True, nogil=True)
def _cell_pixels(ideal, to_grid, n, margin):
    """(n, n) count of the pixels whose centres (``ideal``: (rows, columns, 2) ideal
    coordinates) map into each cell's inner part through ``to_grid``."""
    count = np.zeros((n, n), np.int32)
    A = to_grid
    for yy in range(ideal.shape[0]):
        for xx in range(ideal.shape[1]):
            x, y = ideal[yy, xx, 0], ideal[yy, xx, 1]
            w = A[2, 0] * x + A[2, 1] * y + A[2, 2]
            if w <= 0:
                continue
            u = (A[0, 0] * x + A[0, 1] * y + A[0, 2]) / w
            v = (A[1, 0] * x + A[1, 1] * y + A[1, 2]) / w
            r, c = _inner_cell(u, v, n, margin)
            if r >= 0:
                count[r, c] += 1
    return count


def _cell_areas(to_grid: np.ndarray, n: int, margin: float) -> np.ndarray:
    """(n, n) expected number of pixels inside each cell's inner part: the cell's image area
    (Jacobian of the grid -> pixel homography at its centre) times the inner share."""
    G = np.linalg.inv(to_grid)
    c = np.arange(n) + 0.5
    u, v = np.meshgrid(c, c)
    w = G[2, 0] * u + G[2, 1] * v + G[2, 2]
    x = (G[0, 0] * u + G[0, 1] * v + G[0, 2]) / w
    y = (G[1, 0] * u + G[1, 1] * v + G[1, 2]) / w
    # d(x, y)/d(u, v) of a homography: (G[:2, :2] - (x, y) G[2, :2]) / w
    dxu, dxv = (G[0, 0] - x * G[2, 0]) / w, (G[0, 1] - x * G[2, 1]) / w
    dyu, dyv = (G[1, 0] - y * G[2, 0]) / w, (G[1, 1] - y * G[2, 1]) / w
    return np.abs(dxu * dyv - dxv * dyu) * (1 - 2 * margin) ** 2


_OTHER_FLOOR = 90.0
"""Percentile of the densities a ``fast`` cell of known state fires in the polarity it cannot
switch in (late bursts of its last switch, spill), taken as what they reach: above it that
polarity counts too (``CellReader._levels``)."""

_LEAST_SPILL = 0.02
"""A spill per lit neighbour below this share of the lit cells' contrast is left alone: even
with all eight neighbours lit it moves a cell by less than the quarter of the contrast that
separates it from the threshold at the least."""


def _less_spill(density: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """(n, n) cell densities less what lit neighbours spill into them.

    Blur lights a dark cell's pixels from its lit neighbours, and the sensor answers the log of
    the light, so a few per cent of a neighbour's light makes a dark cell fire almost as often
    as a lit one: a dark cell amid lit ones can read lit. The spill per lit 4-neighbour is
    fitted on the frame itself (``density ~ a + b * lit + c * sides + d * corners`` over every
    cell, ``lit`` a first reading, ``sides`` and ``corners`` its lit 4- and diagonal neighbours),
    so it follows the blur and the sensor there are; a spill the fit does not show
    (``_LEAST_SPILL``) leaves the densities as they are."""
    padded = np.pad(lit, 1).astype(np.float64)  # the black ring around the locator: unlit
    sides = padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]
    corners = padded[:-2, :-2] + padded[:-2, 2:] + padded[2:, :-2] + padded[2:, 2:]
    A = np.stack([np.ones(lit.size), lit.ravel(), sides.ravel(), corners.ravel()], axis=1)
    (_, contrast, side, corner), *_ = np.linalg.lstsq(A, density.ravel(), rcond=None)
    least = _LEAST_SPILL * contrast
    return density - (side > least) * side * sides - (corner > least) * corner * corners


def _two_means(x: np.ndarray, dark: float, bright: float) -> float:
    """Threshold midway between the means of the dark and the bright values ``x`` (sorted),
    from Lloyd's iterations started at the ``dark`` and ``bright`` references. The payload's
    own clusters move with the conditions that the locator's few known cells do not show: under
    motion a white cell's border pixels fire late and its share drops to ~0.7, while a still
    cell's pixels all fire."""
    total = np.r_[0.0, np.cumsum(x)]  # sum of the k darkest values at [k]
    for _ in range(_SPLIT_ROUNDS):
        k = int(np.searchsorted(x, 0.5 * (dark + bright), side="right"))  # dark: value <= cut
        if k < len(x):
            bright = (total[-1] - total[k]) / (len(x) - k)
        if k:
            dark = total[k] / k
    return 0.5 * (dark + bright)


def cell_side_px(config: ReceiverConfig, T_cam_world: np.ndarray) -> float:
    """The shortest side of a cell seen from this pose, in pixels (0 if it does not project)."""
    geo = config.geometry
    corners = project_ideal(T_cam_world, config.camera.K, geo.locator_corners(config.marker_size_m))
    if not np.all(np.isfinite(corners)):
        return 0.0
    return float(np.hypot(*(corners - np.roll(corners, 1, axis=0)).T).min() / geo.locator_side)


def read_stride(config: ReceiverConfig, side_px: float, on_per_pixel: float | None = None) -> int:
    """The pixel stride (``EventTriage.reset``) that cells ``side_px`` wide (``cell_side_px``)
    can be read with: the largest leaving ``decoder.read_px_per_cell`` pixels per cell side,
    shrunk in proportion where a lit pixel fires fewer than ``decoder.dense_on_per_pixel`` ON
    events per transition (``on_per_pixel``, ``on_events_per_pixel``): a readout that thins
    the events (a rate controller, a full link) leaves each read pixel less to say."""
    want = config.decoder.read_px_per_cell
    if want is None or not side_px:
        return 1
    thinned = 1.0 if on_per_pixel is None else on_per_pixel / config.decoder.dense_on_per_pixel
    return max(int(side_px / want * min(max(thinned, 0.0), 1.0)), 1)


_DENSITY_SAMPLE = 200_000
"""Events that ``on_events_per_pixel`` reads at most (every k-th): blinks of a megapixel
marker hold tens of millions, and a count of a sample tells the density as well."""


def on_events_per_pixel(parts: list[np.ndarray], corners_px: np.ndarray, blink_hz: float) -> float:
    """ON events per lit pixel per blink inside the locator ``corners_px`` (sensor pixels), from
    the time-ordered ``parts`` of whole blinks (never joined), half the cells taken as lit."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return 0.0
    step = max(1, sum(len(p) for p in parts) // _DENSITY_SAMPLE)
    quad = np.round(corners_px).astype(np.int32)
    x0, y0 = quad.min(axis=0)
    x1, y1 = quad.max(axis=0) + 1
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, quad - [x0, y0], 1)
    count = 0
    for part in parts:
        on = part[::step]
        on = on[on["p"] > 0]
        x, y = on["x"].astype(np.int64) - x0, on["y"].astype(np.int64) - y0
        inside = (x >= 0) & (y >= 0) & (x < mask.shape[1]) & (y < mask.shape[0])
        count += step * np.count_nonzero(mask[y[inside], x[inside]])
    span_us = int(parts[-1]["t"][-1]) - int(parts[0]["t"][0])
    blinks = max(span_us * blink_hz / 1e6, 1.0)
    return count / max(0.5 * np.count_nonzero(mask) * blinks, 1.0)


@dataclass(frozen=True)
class _Split:
    """A frame's payload split into bits, on one scale of its densities."""

    white_ref: float
    black_ref: float
    """Medians of the locator ring's white and black cells."""
    threshold: float
    bits: np.ndarray
    payload: np.ndarray
    """(n - 2, n - 2) the payload's densities on this scale."""
    separation: float
    """The distance between the means of the cells read 1 and read 0 over the sum of their
    standard deviations (0 if either is empty): how clearly this scale splits them."""


def _ring_references(ring: np.ndarray, ring_white: np.ndarray) -> tuple[float, float]:
    """Medians of the locator ring's white and black cells, given the ring's levels."""
    return float(np.median(ring[ring_white])), float(np.median(ring[~ring_white]))


def _split_levels(levels: np.ndarray, ring_cells: np.ndarray, ring_white: np.ndarray) -> _Split:
    """The payload of (n, n) ``levels`` split at the threshold between its own two clusters
    (``_two_means``), kept within ``_SPLIT_RANGE`` of the way from the ring's black cells'
    median to its white cells'."""
    white_ref, black_ref = _ring_references(levels[ring_cells[:, 1], ring_cells[:, 0]], ring_white)
    payload = levels[1:-1, 1:-1]
    contrast = max(white_ref - black_ref, 1e-9)
    lo, hi = (black_ref + share * contrast for share in _SPLIT_RANGE)
    x = np.sort(payload, axis=None)
    threshold = min(max(_two_means(x, black_ref, white_ref), lo), hi)
    k = int(np.searchsorted(x, threshold, side="right"))  # read 0: value <= threshold
    zeros, ones = x[:k], x[k:]
    separation = 0.0
    if len(ones) and len(zeros):
        spread = float(ones.std() + zeros.std())
        separation = float(ones.mean() - zeros.mean()) / max(spread, 1e-9)
    bits = (payload > threshold).astype(np.uint8)
    return _Split(white_ref, black_ref, threshold, bits, payload, separation)


class CellReader:
    """Reads one data frame's cells; keeps the frame clock."""

    def __init__(
        self, config: ReceiverConfig, first_burst_us: float, stride: int = 1, sparse: bool = False
    ) -> None:
        """``stride``: the bursts come from the pixels on every stride-th row and column;
        ``sparse``: a lit pixel fires fewer than ``decoder.dense_on_per_pixel`` ON events per
        transition (``on_events_per_pixel``)."""
        if config.decoder.step_us <= 0:
            raise ValueError(
                f"decoder step_us must be positive microseconds, got {config.decoder.step_us}"
            )
        self.config = config
        self.stride = stride
        self.sparse = sparse
        geo = config.geometry
        self.n = geo.locator_side
        c = geo.cell_size_m(config.marker_size_m)
        lo = 2 * geo.ring * c
        # marker plane (X, Y, 1) in metres -> locator grid (column, row) in cells
        self._plane_to_grid = np.array([[1 / c, 0, -lo / c], [0, 1 / c, -lo / c], [0, 0, 1]])
        cells, white = ring_cells(geo)
        self._ring_cells, self._ring_white = cells, white
        self._white = geo.inner_locator
        # Event times relative to their row's predicted burst. The search gate finds the burst
        # before the clock is sure of it: wide when a blank refresh separates data frames, inside
        # one refresh for ``fast``. The read gate keeps one refresh's switch: ON events bunch
        # within a few response times, OFF events trail longer (``fast`` reads both).
        r = config.refresh_us
        self._search_gate = (-0.8 * r, 1.2 * r) if config.data_every == 2 else (-0.45 * r, 0.5 * r)
        self._read_gate = (-0.3 * r, 0.6 * r) if config.data_every == 2 else (-0.25 * r, 0.5 * r)
        self.clock = FrameClock(first_burst_us, config.frame_us, self.n)
        self._on_only = config.data_every == 2
        self.gate = self._read_gate
        """Burst times (after their row's predicted burst) a cell reads, narrowed to the spread
        of the locator's own bursts of each polarity read (``_narrow_gate``)."""
        self._spans: dict[int, np.ndarray] = {}
        """The fitted spread of the locator's bursts per polarity (1: ON, -1: OFF)."""
        self._switched: tuple[int, np.ndarray] | None = None
        """(m, (n - 2, n - 2) int8): which way ``fast``'s payload cells switched in frame m, 1 on,
        -1 off, 0 not read as toggled (``_note_switches``)."""
        self._moving = False
        """Whether the grid moved in the latest frame read (``_gate_now``)."""
        n = self.n
        self._grid_centre = np.array([[n / 2, n / 2, 1.0]])
        self._grid_corners = np.array([[0, 0, 1.0], [n, 0, 1], [0, n, 1], [n, n, 1]])
        self._pixels: tuple[np.ndarray, np.ndarray] | None = None
        """The grid map and the (n, n) inner pixel counts of a still grid last counted."""
        self._last_box: tuple[object, tuple[int, int, int, int]] = (None, (0, 0, 0, 0))
        """(pose and padding, box) of the latest ``box`` call."""
        self._last_rows: tuple[object, tuple[float, float, float] | None] = (None, None)
        """(pose, plane) of the latest ``_row_plane`` call."""

    def window(self, m: int) -> tuple[int, int]:
        """Time span of the bursts that frame ``m`` reads: the search gate until one frame's
        bursts timed the clock, then the (narrowed) read gate, so that the frame is read before
        motion overwrites its pixels' bursts. One frame that timed the clock is enough: under
        fast motion, waiting for a fit of the period would cost the first frames of a lock."""
        half = abs(self.clock.slope_us) * self.n / 2
        mid = self.clock.mid(m)
        lo, hi = self._gate_now() if self.clock.timed else self._search_gate
        return int(mid - half + lo), int(mid + half + hi) + 1

    @property
    def _gate_fitted(self) -> bool:
        """Whether ``gate`` spans the fitted spread of every polarity read."""
        return len(self._spans) == (1 if self._on_only else 2)

    def _gate_now(self) -> tuple[float, float]:
        """The gate whose bursts frames are read from: the narrowed one, but for ``fast`` only
        while the grid moves; a still ``fast`` grid reads through the narrowed gate only where
        its cells separate better there (``_gates``)."""
        return self.gate if self._on_only or self._moving else self._read_gate

    def _gates(self) -> list[tuple[float, float]]:
        """The gates a frame's cells are counted through, the one whose payload separates its
        two clusters best read (``read``): ``_gate_now``, and for a still ``fast`` grid behind a
        ``sparse`` readout the narrowed gate too. A dense still ``fast`` link read through the
        narrowed gate loses its switches' stragglers. A thinned one's few events per switch
        stand out of the refresh's stray bursts only inside it behind some readouts, while
        behind others its slow switches' late bursts fall outside it (docs/BENCHMARKS.md's
        tuning record has the clips)."""
        gate = self._gate_now()
        if self._gate_fitted and self.sparse and gate != self.gate:
            return [gate, self.gate]
        return [gate]

    def gate_opens(self, m: int, T_cam_world: np.ndarray) -> tuple[float, float, float] | None:
        """(a, b, c): frame ``m``'s read gate opens at ``a + b * x + c * y`` at raw pixel (x, y)
        near the locator seen from ``T_cam_world`` (``EventTriage.cut_plane``), fitted to its
        rows' gate times over a grid of points on it. None for ``fast`` (its OFF bursts count
        too), and until the gate has been narrowed and the clock's latest correction was within
        half the gate's lead on the switch: a gate opening inside a switch would cut the
        switch's own bursts in two (the first frames of a lock, timed on a few bursts, can be
        milliseconds off)."""
        fitted = self._on_only and self._gate_fitted
        if not (fitted and self.clock.correction_us <= -self.gate[0] / 2):
            return None
        rows = self._row_plane(T_cam_world)
        if rows is None:
            return None
        # The gate opens linearly in the grid row, so its plane is the row plane's, rescaled.
        a, b, c = rows
        slope = self.clock.slope_us
        opens = self.clock.mid(m) + (a - 0.5 - self.n / 2) * slope + self.gate[0]
        return opens, b * slope, c * slope

    def _row_plane(self, T_cam_world: np.ndarray) -> tuple[float, float, float] | None:
        """(a, b, c): the grid row at raw pixel (x, y) near the locator is ``a + b * x + c * y``,
        fitted over a grid of points on it; None if the locator is behind the camera. The last
        plane is kept: a still camera's pose stays the same for many frames."""
        key = T_cam_world.tobytes()
        if self._last_rows[0] != key:
            u, v = (g.ravel() for g in np.meshgrid(*[np.linspace(0, self.n, 5)] * 2))
            px = self._grid_to_pixels(np.c_[u, v], (T_cam_world,))
            plane = None
            if px is not None:
                (a, b, c), *_ = np.linalg.lstsq(np.c_[np.ones(len(v)), px], v, rcond=None)
                plane = float(a), float(b), float(c)
            self._last_rows = (key, plane)
        return self._last_rows[1]

    def _grid_to_pixels(self, grid: np.ndarray, poses: tuple[np.ndarray, ...]) -> np.ndarray | None:
        """Raw pixels (len(poses) * k, 2) of the (k, 2) locator ``grid`` points (column, row)
        seen from each pose in turn; None if any lies behind the camera."""
        plane = np.c_[grid, np.ones(len(grid))] @ np.linalg.inv(self._plane_to_grid).T
        points = np.c_[plane[:, :2], np.zeros(len(plane))]
        seen = np.concatenate([points @ T[:3, :3].T + T[:3, 3] for T in poses])
        if np.any(seen[:, 2] <= 0):
            return None
        return self.config.camera.project(seen)

    def _rises(self, m: int) -> bool:
        """Whether the inner locator switches on in frame ``m`` (frame 0 is the detected burst;
        ``fast`` shows the locator on every other refresh)."""
        return self.config.data_every == 2 or m % 2 == 0

    def _to_grid(self, T_cam_world: np.ndarray) -> np.ndarray:
        """The map (3x3, or (n, 3, 3) for n poses) from ideal pixels to the grid."""
        to_pixels = plane_homography(T_cam_world, self.config.camera.K)
        return self._plane_to_grid @ np.linalg.inv(to_pixels)

    @property
    def both_polarities(self) -> bool:
        """``fast`` reads OFF bursts too."""
        return not self._on_only

    def box(self, *poses: np.ndarray, pad_px: int = 4) -> tuple[int, int, int, int]:
        """Raw-pixel box (x0, x1, y0, y1) holding the inner locator at all of these poses (a
        moving camera's over a frame's window: the scan-out spreads a frame's bursts over
        ~10 ms, in which 6 px/ms moves the marker 60 px); its border is sampled densely because
        the lens bends straight sides. The last box is kept: a still camera's pose, and with
        it the box, stays the same for many frames."""
        key = (b"".join(T.tobytes() for T in poses), pad_px)
        if self._last_box[0] != key:
            self._last_box = (key, self._locator_box(poses, pad_px))
        return self._last_box[1]

    def _locator_box(self, poses: tuple[np.ndarray, ...], pad_px: int) -> tuple[int, int, int, int]:
        n, cam = self.n, self.config.camera
        s = np.linspace(0, n, 17)
        zeros, full = np.zeros_like(s), np.full_like(s, n)
        border = np.r_[np.c_[s, zeros], np.c_[s, full], np.c_[zeros, s], np.c_[full, s]]
        px = self._grid_to_pixels(border, poses)
        if px is None:
            return 0, 0, 0, 0
        lo = np.floor(px.min(axis=0)).astype(int) - pad_px
        hi = np.ceil(px.max(axis=0)).astype(int) + pad_px + 1
        return (max(lo[0], 0), min(hi[0], cam.width), max(lo[1], 0), min(hi[1], cam.height))

    def read(
        self, m: int, ev: EventColumns, pose_at: Callable[[np.ndarray], np.ndarray]
    ) -> FrameRead:
        """Frame ``m`` from the pixel bursts ``ev`` (t, p, xu, yu) that began in
        ``window(m)``; ``pose_at(times)``: the tracked poses (n, 4, 4) at those times."""
        t, p = ev["t"], ev["p"]
        t0, t1 = self.window(m)
        motion = self._grid_motion(pose_at, t1)
        still = motion < _STILL_CELLS
        self._moving = not still
        steps = 1  # a still grid needs one pose; a moving one a pose per step
        if not still:
            steps = max(1, int(np.ceil((t1 - t0) / self.config.decoder.step_us)))
        edges = np.linspace(t0, t1, steps + 1)
        # A step's pose is the tracked one at its middle (``pose_at`` interpolates the updates).
        poses = pose_at((edges[1:] + edges[:-1]) / 2)
        to_grid = self._to_grid(poses)
        u, v = _grid_coords(t, ev["xu"], ev["yu"], edges, to_grid)
        if self._rises(m):
            self._retime(m, t, p, u, v)
        elif self.clock.timed:  # ``fast``'s locator switches off
            self._narrow_gate(m, t, p, u, v)
        shifts = _ALIGN_SHIFTS if self._on_only and motion >= _ALIGN_MIN_MOTION else _NO_SHIFT
        mid = steps // 2
        inner = self._inner_pixels(poses[mid], to_grid[mid], still)
        counts = [self._count(t, p, u, v, m, shifts, gate) for gate in self._gates()]
        count = counts[0]
        if len(counts) > 1:  # the payload that separates best (``_gates``); rare: split only then
            count = max(counts, key=lambda c: self._split(c[0].sum(axis=0) / inner).separation)
        best = self._sharpest(count.sum(axis=1) / inner)
        read = self._classify(m, count[best] / inner, int(count[best].sum()))
        if not self.clock.timed:
            # Before any burst fitted the clock the rows' times are guesses without the scan-out
            # slope: a frame whose locator does not rise (``fast``'s first buffered one) reads
            # many cells wrong.
            read = replace(read, locator_score=0.0)
        return read

    def _count(
        self,
        t,
        p,
        u,
        v,
        m: int,
        shifts: np.ndarray = _NO_SHIFT,
        gate: tuple[float, float] | None = None,
    ) -> np.ndarray:
        """(shifts, 2, n, n) cell counts of frame ``m``'s ON and OFF bursts in ``gate`` (by
        default ``_gate_now``) on the grid moved by each shift."""
        mid, slope, margin = self.clock.mid(m), self.clock.slope_us, self.config.decoder.cell_margin
        on_only = self._on_only
        timing = (mid, slope, *(gate or self._gate_now()))
        return _cell_bursts((t, p, u, v), self.n, timing, on_only, margin, shifts)

    def _inner_pixels(self, T_cam_world: np.ndarray, to_grid: np.ndarray, still: bool):
        """(n, n) pixels inside each cell's inner part (at least one), so that a cell reads as
        the share of its pixels that fired.

        A still grid has its pixels counted: at 4-5 px per cell the inner part holds anywhere
        from 4 to 9 pixel centres, which swings an area-normalised density by a factor of two.
        The count is kept until the grid moves by ``_RECOUNT_CELLS``. A moving grid takes the
        cell's image area instead: its pixels sweep across the cell borders and the tracked pose
        is a little off, so which pixel centres fall inside is a guess, and the smooth
        expectation reads better."""
        n, margin, s = self.n, self.config.decoder.cell_margin, self.stride
        if not still:
            return np.maximum(_cell_areas(to_grid, n, margin) / (s * s), 1.0)
        kept = self._pixels
        if kept is not None and self._moved(kept[0], to_grid, self._grid_corners) < _RECOUNT_CELLS:
            return kept[1]
        x0, x1, y0, y1 = self.box(T_cam_world)
        on_grid = slice(-(-y0 // s) * s, y1, s), slice(-(-x0 // s) * s, x1, s)
        ideal = self.config.camera.undistort_table[on_grid]
        pixels = np.maximum(_cell_pixels(ideal, to_grid, n, margin), 1)
        self._pixels = (to_grid, pixels)
        return pixels

    @staticmethod
    def _moved(then: np.ndarray, now: np.ndarray, points: np.ndarray) -> float:
        """Largest distance (cells) that the grid ``points`` (k, 3 homogeneous) moved between
        the grid maps ``then`` and ``now`` (ideal pixels -> grid)."""
        moved = now @ np.linalg.inv(then) @ points.T
        return float(np.max(np.hypot(*(moved[:2] / moved[2] - points.T[:2]))))

    def _grid_motion(self, pose_at: Callable[[np.ndarray], np.ndarray], t_us: float) -> float:
        """How far (cells) the grid's centre moved over the ``_ALIGN_LOOKBACK_US`` before
        ``t_us``."""
        then, now = self._to_grid(pose_at(np.array([t_us - _ALIGN_LOOKBACK_US, t_us])))
        return self._moved(then, now, self._grid_centre)

    def _sharpest(self, density: np.ndarray) -> int:
        """Index of the shifted grid whose (shifts, n, n) ``density`` shows the locator ring
        sharpest. The tracked pose of a moving camera can sit a fraction of a cell off, enough
        to light black cells' inner parts from their white neighbours; the ring's known cells
        pin the grid back."""
        if len(density) == 1:
            return 0
        scores = self._ring_contrast(density)
        scores[0] += _ALIGN_GAIN  # the pose's own grid unless a shift is clearly sharper
        return int(np.argmax(scores))

    def _ring_contrast(self, density: np.ndarray) -> np.ndarray:
        """Michelson contrast of the mean densities of the ring's white and black cells, per
        (..., n, n) density map."""
        cells = self._ring_cells
        ring = density[..., cells[:, 1], cells[:, 0]]
        w, b = ring[..., self._ring_white].mean(-1), ring[..., ~self._ring_white].mean(-1)
        return (w - b) / np.maximum(w + b, 1e-9)

    def _retime(self, m: int, t, p, u, v) -> None:
        """Fit the burst time and scan-out slope of frame ``m`` to its locator's white cells."""
        rows, dts = self._locator_bursts(m, t, p, u, v, self._search_gate, 1)
        if len(rows) < _MIN_CLOCK_EVENTS:
            return
        gate = self._search_gate
        peak, count = _row_peaks(rows, dts, self.n, *gate, _CLOCK_BIN_US, _PEAK_BINS)
        rows = np.flatnonzero(count >= 3)
        if len(rows) >= 3:
            slope, offset = np.polyfit(rows - self.n / 2, peak[rows], 1)
        elif len(rows):
            slope, offset = 0.0, float(np.median(peak[rows]))
        else:
            return
        self.clock.observe(m, self.clock.mid(m) + offset, self.clock.slope_us + slope)
        self._narrow_gate(m, t, p, u, v)

    def _locator_bursts(self, m: int, t, p, u, v, gate: tuple[float, float], polarity: int):
        """(row, time after the row's predicted burst) of frame ``m``'s bursts of sign
        ``polarity`` on the locator's white cells inside ``gate``."""
        mid, slope = self.clock.mid(m), self.clock.slope_us
        return _locator_bursts((t, p, u, v), self._white, (mid, slope, *gate), polarity)

    def _narrow_gate(self, m: int, t, p, u, v) -> None:
        """Fit the read gate to the spread of the locator's white-cell bursts around their
        rows' burst times: ON where the locator switches on, OFF where ``fast``'s switches
        off; ``fast``'s gate spans both once both are fitted. A wider gate lets a moving camera
        read cells swept by their neighbours' images after the switch (0.5 px/ms crosses a
        4 px cell in 8 ms, and ``fast``'s refresh-long gate let such bursts outnumber the
        switch's), while a cell under the display's switch fires within its response time."""
        polarity = 1 if self._rises(m) else -1
        lo, hi = self._read_gate
        dt = self._locator_bursts(m, t, p, u, v, self._read_gate, polarity)[1]
        if len(dt) < _MIN_CLOCK_EVENTS:
            return
        span = _switch_span(dt, lo, hi, floored=polarity < 0)
        if span is None:
            return
        q_lo, q_hi = span
        pad = _GATE_PAD * (q_hi - q_lo) + _CLOCK_BIN_US
        fit = np.array([max(q_lo - pad, lo), min(q_hi + pad, hi)])
        if polarity in self._spans:
            fit = 0.7 * self._spans[polarity] + 0.3 * fit
        self._spans[polarity] = fit
        if self._gate_fitted:
            spans = np.array(list(self._spans.values()))
            self.gate = float(spans[:, 0].min()), float(spans[:, 1].max())

    def _classify(self, m: int, density: np.ndarray, pixels: int) -> FrameRead:
        """Bits from the cells' (2, n, n) ON and OFF burst densities, against the ring's white
        and black cells, once less what the neighbours spill into each cell (``_levels``)."""
        on, off = density
        both = on + off
        # The locator's readings take the densities as they are: the spill's fit assumes the
        # 'L' upright, which they judge.
        cells = self._ring_cells
        ring = both[cells[:, 1], cells[:, 0]]
        white_ref, black_ref = _ring_references(ring, self._ring_white)
        score = (white_ref - black_ref) / max(white_ref + black_ref, 1e-9)
        turns = turn_readings(both, self.config.geometry) / max(float(ring.mean()), 1e-9)
        bits = self._split(both).bits
        shown = self._shown_before(m) if self.both_polarities else None
        for _ in range(2):  # the second pass fits the spill on the bits the first corrected
            levels = self._levels(on, off, bits, shown)
            split, *others = (self._split(level) for level in levels)
            for other in others:
                if other.separation > _APART_MARGIN * split.separation:
                    split = other
            bits = split.bits
        if shown is not None:
            self._note_switches(m, on, off, bits, shown)
        sure = self.config.decoder.sure_contrast * max(split.white_ref - split.black_ref, 1e-9)
        confidence = np.clip(np.abs(split.payload - split.threshold) / sure, 0.0, 1.0)
        return FrameRead(m, int(self.clock.mid(m)), bits, confidence, score, pixels, turns)

    def _levels(
        self, on: np.ndarray, off: np.ndarray, bits: np.ndarray, shown: np.ndarray | None
    ) -> list[np.ndarray]:
        """(n, n) cell levels less what the neighbours spill into them (``_less_spill``),
        given a first reading ``bits``: one map, or for ``fast`` two, the second taken where it
        separates the cells' two clusters clearly better (``_APART_MARGIN``).

        ON-only profiles: the ON densities less the lit neighbours' spill. ``fast``: the two
        polarities added up less the spill of every switching neighbour, then each cell in the
        one polarity it can switch in, less the spill of the neighbours that switched that
        way: ON where it is ``shown`` dark (-1), OFF where lit (1), and where that is not known
        (0) the stronger of the two. A toggling cell fires the one polarity of its own switch,
        while a dark cell fires with each neighbour in that neighbour's direction: between a
        rising and a falling one it fires both, which the sum adds up. A known cell's other
        polarity still counts where it stands out of what the others reach in it
        (``_OTHER_FLOOR``): a cell whose switch the frame before misread, or read the wrong
        way, switches the way it was not expected to, at a whole switch's level."""
        lit = self._lit(bits)
        if not self.both_polarities:
            return [_less_spill(on, lit)]
        rose = lit & (on >= off)
        on_level, off_level = _less_spill(on, rose), _less_spill(off, lit & ~rose)
        known = shown != 0
        own = np.where(shown < 0, on_level, off_level)
        other = np.where(shown < 0, off_level, on_level)
        floor = np.percentile(other[known], _OTHER_FLOOR)  # the ring's cells are always known
        level = np.where(known, np.maximum(own, other - floor), np.maximum(on_level, off_level))
        return [_less_spill(on + off, lit), level]

    def _shown_before(self, m: int) -> np.ndarray:
        """(n, n) int8: what each cell showed before frame ``m`` switched it, as far as the
        reads tell: 1 lit, -1 dark, 0 not known. The ring's cells are known (its black cells
        stay dark, ``fast`` shows its white ones on even refreshes only); a payload cell is
        known where it switched in frame ``m - 1`` (``_note_switches``)."""
        shown = np.zeros((self.n, self.n), np.int8)
        cells = self._ring_cells
        lit = self._ring_white & (not self._rises(m))
        shown[cells[:, 1], cells[:, 0]] = np.where(lit, 1, -1)
        if self._switched is not None and self._switched[0] == m - 1:
            shown[1:-1, 1:-1] = self._switched[1]
        return shown

    def _note_switches(
        self, m: int, on: np.ndarray, off: np.ndarray, bits: np.ndarray, shown: np.ndarray
    ) -> None:
        """Keep which way frame ``m``'s payload cells read as toggled switched: the other way
        from how they were ``shown``, or where that is not known the polarity they fired more of.
        Only for one refresh: a display whose fall outlasts the refresh keeps starting OFF
        bursts in the one after, where a cell that just went dark can only switch on, while a
        switch misread and carried on would cost a second error at the cell's next switch."""
        inner = slice(1, -1), slice(1, -1)
        fired = np.where(on[inner] >= off[inner], 1, -1)
        before = shown[inner]
        after = np.where(before != 0, -before, fired)
        self._switched = (m, np.where(bits > 0, after, 0).astype(np.int8))

    def _split(self, density: np.ndarray) -> _Split:
        """The payload of (n, n) densities split against the ring's white and black cells, on
        the scale, linear or square root, that separates its two clusters more
        (``_Split.separation``): ``fast``'s always, the ON-only profiles' where the readout is
        ``sparse``, and on the linear scale otherwise.

        Where one cluster spreads far wider than the other, a threshold midway between their
        means falls among the wider one's cells. A readout that drops the excess of each
        millisecond does it: a lit cell keeps a varying share of its pixels' few events where a
        dark one has few to lose, and ``fast``'s ON bursts, which bunch at the switch, lose a
        far larger share than its OFF ones, which trail over milliseconds. The square root
        evens such spreads (it is the scale on which a count's noise is the same at any rate);
        where the lit cells all fire and the dark ones spread instead (blur lights a dark cell
        from its switching neighbours), it widens the dark ones' spread, and the linear scale
        separates better. An ON-only frame from a dense readout under motion can still separate
        better on the root scale and read more bits wrong there, so it keeps the linear one."""
        linear = _split_levels(density, self._ring_cells, self._ring_white)
        if not (self.both_polarities or self.sparse):
            return linear
        root = _split_levels(np.sqrt(np.maximum(density, 0.0)), self._ring_cells, self._ring_white)
        return root if root.separation > _ROOT_MARGIN * linear.separation else linear

    def _lit(self, bits: np.ndarray) -> np.ndarray:
        """(n, n) bool: the locator ring as it is drawn around the payload ``bits``."""
        lit = np.zeros((self.n, self.n), bool)
        cells = self._ring_cells
        lit[cells[:, 1], cells[:, 0]] = self._ring_white
        lit[1:-1, 1:-1] = bits > 0
        return lit
