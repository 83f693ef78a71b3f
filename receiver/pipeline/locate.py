"""Where the inner locator is, from one motion-compensated burst.

Under hand-held motion the static white ring sweeps across pixels and fires events of both
polarities at any phase, and over a few blink periods the marker moves by several cells. So the
locator is found in a single data-frame burst (the paper's window of +-0.2 period around it):

1. *Flow.* The OFF events inside the ON burst window come from motion alone (the data frame only
   switches cells on), so the image flow is the translation that makes them sharpest (contrast
   maximisation, Gallego et al. 2018). A still camera keeps zero flow.
2. *Blink image.* ON events of the burst, warped to its time, minus those of the two windows half a
   period away (the blank frames, where only motion fires ON): the ring's swept edges cancel.
3. *Blob.* A closing joins the payload and locator cells into one blob and an opening removes the
   thin remains of swept edges; its convex quadrilateral is the locator's outline, to a cell or
   so: blur makes cells light up their dark neighbours, and leftovers of swept edges stick to it.
4. *Square.* The square that best separates the lit locator ring from the dark ring around it
   (``fit_square``) pins the outline to a pixel or two (the square ignores perspective: the
   detector's ring capture adds it).

Everything works in a box of the sensor around the blinking region (``Box``). Contrast
maximisation tries a few hundred flows on a few thousand events in one compiled pass
(``_sharpness``), so that a still camera, which needs none of this, pays almost nothing for the
question.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass

import cv2
import numba
import numpy as np

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.buffer import first_at
from eventocc.receiver.pipeline.config import DetectorParams

MAX_FLOW_PX_PER_MS = 12.0
"""Largest image flow searched: the peaks of a fast sweep on the paper's 1280x720 sensor (its
6 px/ms clips peak at 9-12). A burst faster than the search reaches stays smeared over tens of
pixels, and detection waits for the motion to slow down."""
_FLOW_LEVELS = (
    (1.5, 8, 12.0, 5_000),
    (0.5, 2, 4.0, 5_000),
    (0.25, 1, 2.0, 5_000),
    (0.1, 2, 1.0, 30_000),
    (0.04, 2, 1.0, 30_000),
)
"""Coarse to fine search of the flow: (step px/ms, steps each way, image bin px, events). Each
grid step moves the burst's edge events by less than a bin at the window's edges (0.2 blink
period: 6.7 ms at a 60 Hz refresh); a few thousand events outline the ring well enough for the
coarse levels, and each level's reach covers half the step of the one before."""
_MIN_GAIN = 1.05
"""A flow must sharpen the image by this factor over zero flow, or the camera counts as still."""
_GAIN_BIN_PX = 2.0
"""Bin of that comparison: in 1 px bins a still display's OFF events can line up better at some
flow of 1-2 px/ms than at none, in 2 px bins they do not, while hand-held motion still gains
far more than ``_MIN_GAIN``."""
_SLOW_STEP = 0.05
_SLOW_SAMPLE = 5_000
"""``slow_flow``'s grid step (px/ms) and the OFF events it reads at most (every k-th). A camera
drifting a fraction of a pixel per ms fires few edge events beside the display's OFF tail, whose
times follow the scan-out's rows, and some flow of 1-3 px/ms often lines those up better than
the true one does; a search within a fraction of a pixel per ms is not misled so."""
HALF_WINDOW = 0.2
"""Half-width of a burst window in blink periods (paper Sec. IV-B)."""
_SQUARE_SHIFTS_CELLS = np.arange(-1.5, 1.6, 0.25)
"""Shifts of the square's centre searched first, in cells: the blob's outline is off by up to a
cell and a half (the motion-swept ring edges beside it join the blob), at any cell size."""
_SQUARE_FINEST_PX = 0.25
"""The refinement halves its steps (from an eighth of a cell) down to this."""
_SQUARE_SCALES = np.arange(0.84, 1.07, 0.02)
"""The blob is up to a cell and a half larger than the locator on each side."""
_SQUARE_TURNS = np.radians([-3.0, -1.5, 0.0, 1.5, 3.0])
_QUAD_PASSES = 4
"""Rounds over the four corners at each step of ``_fit_quad`` (fewer if none moves)."""
QUAD_MARGIN = 1.2
"""How much better a free quadrilateral must fit the locator's bands than the square to be
tried first: freeing the corners buys a few per cent of contrast from the burst's noise alone
(a square-on locator: +3-5%, with corners moved up to two cells), where a locator seen 35-45
deg off its normal reads 30-80% more than any square gives it."""


class MarkerNotFound(Exception):
    """Detection failed; the message says which stage and why."""

    cell_px: float | None = None
    """A cell's side in pixels as the blinking region found suggests, if one was found: too
    few pixels per cell is why a marker that blinks plainly cannot be read."""


@dataclass(frozen=True)
class Box:
    """A sensor region: columns ``x0 <= x < x1``, rows ``y0 <= y < y1``."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def shape(self) -> tuple[int, int]:
        return self.y1 - self.y0, self.x1 - self.x0


@dataclass(frozen=True)
class CompensatedBurst:
    image: np.ndarray
    """Boolean image of the box: pixels that brighten with the burst, motion undone."""
    box: Box
    t_us: float
    """The burst's time, to which every event was warped."""
    flow: np.ndarray
    """Image flow (vx, vy) in px/ms; zero for a still camera."""


@numba.njit(cache=True, nogil=True)
def _selected(x, y, p, polarity, x0, y0, x1, y1):
    """Indices of the events of ``polarity`` (0: either) inside the box x0 <= x < x1,
    y0 <= y < y1, in one pass (numpy's masks take a pass and a temporary per condition)."""
    out = np.empty(x.shape[0], np.int64)
    k = 0
    for i in range(x.shape[0]):
        if (polarity == 0 or p[i] == polarity) and x0 <= x[i] < x1 and y0 <= y[i] < y1:
            out[k] = i
            k += 1
    return out[:k]


def events_between(
    parts: list[np.ndarray],
    t0: float,
    t1: float,
    polarity: int | None = None,
    box: Box | None = None,
    most: int | None = None,
) -> np.ndarray:
    """The events of the time-ordered parts in [t0, t1), of one ``polarity`` and inside ``box``
    if given, as one array; with ``most``, only every k-th of them, k chosen so that about
    ``most`` remain. The parts are cut, filtered and thinned before they are joined: the window
    can hold millions."""
    lo, hi = int(np.ceil(t0)), int(np.ceil(t1))
    out = [p[first_at(p["t"], lo) : first_at(p["t"], hi)] for p in parts]
    if polarity is not None or box is not None:
        b = box or Box(0, 0, 1 << 16, 1 << 16)
        out = [p[_selected(p["x"], p["y"], p["p"], polarity or 0, *astuple(b))] for p in out]
    if most is not None:
        k = max(1, sum(len(p) for p in out) // most)
        thinned, skip = [], 0  # skip: where the next part's first k-th event lies
        for p in out:
            thinned.append(p[skip::k])
            skip = (skip - len(p)) % k
        out = thinned
    out = [p for p in out if len(p)]
    return np.concatenate(out) if out else parts[0][:0]


@numba.njit(cache=True, nogil=True)
def _add_warped(events, polarity, t_ref, flow, counts, origin):
    """Add to ``counts`` (the box from ``origin`` = (x0, y0)) the ``events`` = (t, x, y, p) of
    ``polarity``, each moved along the ``flow`` = (vx, vy) px/ms to ``t_ref``, at its nearest
    pixel."""
    t, x, y, p = events
    vx, vy = flow
    x0, y0 = origin
    h, w = counts.shape
    for i in range(t.shape[0]):
        if p[i] != polarity:
            continue
        dt = (t_ref - t[i]) / 1000.0
        u = int(np.floor(x[i] + vx * dt + 0.5)) - x0
        v = int(np.floor(y[i] + vy * dt + 0.5)) - y0
        if 0 <= u < w and 0 <= v < h:
            counts[v, u] += 1.0


def warped_counts(
    parts: list[np.ndarray],
    t0: float,
    t1: float,
    polarity: int,
    t_ref: float,
    flow: np.ndarray,
    box: Box,
) -> np.ndarray:
    """Counts per pixel of ``box`` of the events of ``polarity`` in [t0, t1), each moved along
    ``flow`` (px/ms) to ``t_ref``: one compiled pass over the parts, nothing copied."""
    counts = np.zeros(box.shape, np.float32)
    lo, hi = int(np.ceil(t0)), int(np.ceil(t1))
    for ev in parts:
        ev = ev[first_at(ev["t"], lo) : first_at(ev["t"], hi)]
        events = (ev["t"], ev["x"], ev["y"], ev["p"])
        _add_warped(events, polarity, t_ref, (*flow,), counts, (box.x0, box.y0))
    return counts


@numba.njit(cache=True, nogil=True)
def _sharpness(x, y, dt_ms, flows, bin_px, width, height):
    """Per flow (vx, vy) px/ms: how many pairs of the points (x, y), moved by ``flow * dt_ms``,
    share a bin of ``bin_px`` pixels over ``width`` x ``height`` pixels (the image's sum of
    squares less its sum), at a cost per event rather than per pixel.

    Nearest-bin counts: whatever the points' sub-pixel positions, the chance that two of them
    share a bin falls off linearly with their distance. Bilinear votes would not be fair: they
    overlap most on whole pixels, where zero flow puts every event."""
    w, h = int(np.ceil(width / bin_px)) + 1, int(np.ceil(height / bin_px)) + 1
    counts = np.zeros(w * h, np.int32)
    cell = np.empty(x.shape[0], np.int64)
    out = np.empty(flows.shape[0])
    for k in range(flows.shape[0]):
        vx, vy = flows[k, 0] / bin_px, flows[k, 1] / bin_px
        pairs, n = 0, 0
        for i in range(x.shape[0]):
            u = np.floor(x[i] / bin_px + vx * dt_ms[i] + 0.5)
            v = np.floor(y[i] / bin_px + vy * dt_ms[i] + 0.5)
            if not (0.0 <= u < w and 0.0 <= v < h):
                continue
            j = int(v) * w + int(u)
            pairs += counts[j]
            counts[j] += 1
            cell[n] = j
            n += 1
        for m in range(n):  # clear only what was touched
            counts[cell[m]] = 0
        out[k] = pairs
    return out


def motion_flow(events: np.ndarray, t_ref: float, box: Box) -> np.ndarray:
    """(vx, vy) px/ms that makes ``events`` sharpest when warped to ``t_ref``: a coarse grid
    over +-``MAX_FLOW_PX_PER_MS``, then finer ones around the best (``_FLOW_LEVELS``)."""
    zero = np.zeros(2)
    if len(events) < 100:
        return zero
    x = events["x"].astype(np.float64) - box.x0
    y = events["y"].astype(np.float64) - box.y0
    dt = (t_ref - events["t"]) / 1000.0
    h, w = box.shape
    best = zero
    for step, reach, bin_px, sample in _FLOW_LEVELS:
        k = max(1, len(x) // sample)
        axis = np.arange(-reach, reach + 1) * step
        flows = best + np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
        flows = flows[np.all(np.abs(flows) <= MAX_FLOW_PX_PER_MS + 1e-9, axis=1)]
        best = flows[int(np.argmax(_sharpness(x[::k], y[::k], dt[::k], flows, bin_px, w, h)))]
    gain = _sharpness(x[::k], y[::k], dt[::k], np.stack([best, zero]), _GAIN_BIN_PX, w, h)
    return best if gain[0] > _MIN_GAIN * gain[1] else zero


def latest_burst_us(parts: list[np.ndarray], burst_us: float, period_us: float) -> float:
    """The latest burst (``burst_us`` plus whole periods) whose following half period and burst
    window are in ``parts``."""
    half = HALF_WINDOW * period_us
    t_end = float(parts[-1]["t"][-1])
    return burst_us + np.floor((t_end - period_us / 2 - half - burst_us) / period_us) * period_us


def densest_burst_us(parts: list[np.ndarray], tb: float, period_us: float, box: Box) -> float:
    """The middle of the burst window (``HALF_WINDOW`` periods either side) that holds the most
    ON events of ``box`` within a quarter period of ``tb``: the burst as its own events place
    it. The blink map's phase (``tb`` plus whole periods) averages the window's bursts and the
    ON events that a moving camera's edges fire at every phase; the window it puts around the
    latest burst can miss that burst's start by a millisecond or two."""
    width = 2 * HALF_WINDOW * period_us
    t = events_between(parts, tb - period_us / 4, tb + period_us / 4, polarity=1, box=box)["t"]
    if len(t) < 100:
        return tb
    inside = np.searchsorted(t, t + width) - np.arange(len(t))  # events of the window from t[i]
    return float(t[int(np.argmax(inside))] + width / 2)


def slow_flow(events: np.ndarray, t_ref: float, box: Box, most_px_per_ms: float) -> np.ndarray:
    """The flow of at most ``most_px_per_ms`` that makes ``events`` sharpest when warped to
    ``t_ref``, on a grid of ``_SLOW_STEP``: a second opinion where ``motion_flow`` is misled.
    Pairs are counted in 1 px bins on four grids shifted by half a pixel: events sit on whole
    pixels, and a single grid favours the flows that move them by whole bins."""
    if len(events) < 100:
        return np.zeros(2)
    axis = np.arange(-most_px_per_ms, most_px_per_ms + 1e-9, _SLOW_STEP)
    flows = np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    flows = flows[np.hypot(*flows.T) <= most_px_per_ms + 1e-9]
    k = max(1, len(events) // _SLOW_SAMPLE)
    x = events["x"][::k].astype(np.float64) - box.x0
    y = events["y"][::k].astype(np.float64) - box.y0
    dt = (t_ref - events["t"][::k]) / 1000.0
    h, w = box.shape
    pairs = np.zeros(len(flows))
    for dx, dy in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        pairs += _sharpness(x + dx, y + dy, dt, flows, 1.0, w + 1, h + 1)
    return flows[int(np.argmax(pairs))]


def burst_flow(
    parts: list[np.ndarray],
    tb: float,
    period_us: float,
    box: Box,
    most_px_per_ms: float | None = None,
) -> np.ndarray:
    """Image flow (px/ms) at the burst at ``tb``, from the OFF events of its window in ``box``:
    the data frame only switches cells on, so those come from motion alone. With
    ``most_px_per_ms``, the sharpest flow up to that speed (``slow_flow``)."""
    half = HALF_WINDOW * period_us
    off = events_between(parts, tb - half, tb + half, polarity=-1, box=box)
    if most_px_per_ms is None:
        return motion_flow(off, tb, box)
    return slow_flow(off, tb, box, most_px_per_ms)


def compensated_burst(
    parts: list[np.ndarray],
    tb: float,
    period_us: float,
    box: Box,
    flow: np.ndarray | None = None,
) -> CompensatedBurst:
    """The burst at ``tb`` (``latest_burst_us``, or whole periods before it): pixels of ``box``
    with more ON events in the burst than in either blank frame beside it, all warped to the
    burst time along ``flow`` (measured by ``burst_flow`` when not given). A blank frame before
    the first event counts as empty."""
    half = HALF_WINDOW * period_us
    if flow is None:
        flow = burst_flow(parts, tb, period_us, box)
    blank = period_us / 2  # the blank frames' switches, where only motion fires ON
    on = [
        warped_counts(parts, tb + d - half, tb + d + half, 1, tb, flow, box)
        for d in (0, -blank, blank)
    ]
    return CompensatedBurst(on[0] - np.maximum(on[1], on[2]) >= 1, box, float(tb), flow)


def outline(binary: np.ndarray) -> np.ndarray:
    """(k, 2) (x, y) of the pixels on the outer outlines of a binary image's blobs: the convex
    hull of a blob's pixels is that of its outline, a few per cent of them."""
    contours, _ = cv2.findContours(
        binary.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    return np.concatenate(contours).reshape(-1, 2) if contours else np.empty((0, 2), np.int32)


def locator_blob(image: np.ndarray, cell_px: float) -> np.ndarray:
    """(k, 2) pixels on the outline of the largest blob after joining cells (closing by one
    cell) and removing lines thinner than two cells (opening)."""
    small = np.ones((max(3, round(cell_px) | 1),) * 2, np.uint8)
    large = np.ones((max(3, round(2 * cell_px) | 1),) * 2, np.uint8)
    blob = cv2.morphologyEx(image.astype(np.uint8), cv2.MORPH_CLOSE, small)
    blob = cv2.morphologyEx(blob, cv2.MORPH_OPEN, large)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(blob)
    if n < 2:
        raise MarkerNotFound("spatial: nothing brightens with the bursts as a solid blob")
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return outline(labels == biggest)


def _square_outline(half: float, per_side: int = 24) -> np.ndarray:
    """(4 * per_side, 2) points along the sides of the square of half-side ``half`` around 0."""
    s = ((np.arange(per_side) + 0.5) / per_side * 2 - 1) * half
    a = np.full(per_side, half)
    return np.vstack([np.c_[s, -a], np.c_[a, s], np.c_[-s, a], np.c_[-a, -s]])


def fit_square(image: np.ndarray, quad: np.ndarray, locator_side: int, ring: int) -> np.ndarray:
    """(4, 2) corners of the square, near ``quad``, whose inner band (the locator ring's cells)
    is the most lit and whose outer band (the dark ring around the locator) the least, in the
    blurred ``image``; a grid of shifts, scales and turns, then finer ones down to
    ``_SQUARE_FINEST_PX``."""
    return _fit_square(_bands(image, locator_side, ring), quad, locator_side)


def _fit_square(
    bands: tuple[np.ndarray, np.ndarray, np.ndarray], quad: np.ndarray, locator_side: int
) -> np.ndarray:
    """``fit_square`` on the blurred image and its bands (``_bands``)."""
    lit, inner, outer = bands
    sides = np.roll(quad, -1, axis=0) - quad
    side = np.linalg.norm(sides, axis=1).mean()
    cell = side / locator_side
    # Mean direction of the sides modulo 90 degrees.
    turn = np.angle(np.mean(np.exp(4j * np.arctan2(sides[:, 1], sides[:, 0])))) / 4

    def contrast(h: np.ndarray) -> np.ndarray:
        return _square_contrast(lit, np.ascontiguousarray(h), inner, outer)

    def grid(*axes: np.ndarray) -> np.ndarray:
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)

    centre = quad.mean(axis=0)
    h = grid(
        centre[0] + cell * _SQUARE_SHIFTS_CELLS,
        centre[1] + cell * _SQUARE_SHIFTS_CELLS,
        side * _SQUARE_SCALES,
        turn + _SQUARE_TURNS,
    )
    best = h[np.argmax(contrast(h))]
    k, r = np.arange(-2, 3), 1.0
    while r * cell / 8 >= _SQUARE_FINEST_PX:  # shifts from half the coarse grid's step
        h = best + grid(
            k * r * cell / 8, k * r * cell / 8, k * r * 0.01 * side, np.radians(k * r / 2)
        )
        best = h[np.argmax(contrast(h))]
        r /= 2
    corners = np.empty((4, 2))
    _square_corners(best, corners)
    return corners


@numba.njit(cache=True)
def _square_corners(h: np.ndarray, out: np.ndarray) -> None:
    """Into ``out`` (4, 2): the corners, clockwise on screen, of the square h = (cx, cy, side,
    turn)."""
    c, s = math.cos(h[3]), math.sin(h[3])
    for i, (u, v) in enumerate(((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))):
        out[i, 0] = h[0] + h[2] * (c * u - s * v)
        out[i, 1] = h[1] + h[2] * (s * u + c * v)


@numba.njit(cache=True)
def _square_contrast(
    lit: np.ndarray, h: np.ndarray, inner: np.ndarray, outer: np.ndarray
) -> np.ndarray:
    """``_quad_contrast`` of squares h = (cx, cy, side, turn), (k, 4): ten thousand hypotheses
    of two hundred samples each, compiled since numpy's temporaries for them cost far more
    than the arithmetic."""
    out = np.empty(h.shape[0])
    corners = np.empty((4, 2))
    for k in range(h.shape[0]):
        _square_corners(h[k], corners)
        out[k] = _band_mean(lit, corners, inner) - _band_mean(lit, corners, outer)
    return out


def _bands(
    image: np.ndarray, locator_side: int, ring: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blurred ``image`` and, in unit square coordinates, the locator ring's band (the
    middle of its cells) and the band of the dark ring around it, which the fits contrast."""
    lit = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.0)
    inner = 0.5 + _square_outline(0.5 - 0.5 / locator_side)
    outer = 0.5 + _square_outline(0.5 + 0.5 * ring / locator_side)
    return lit, inner, outer


def locator_fits(
    image: np.ndarray, blob: np.ndarray, locator_side: int, ring: int
) -> list[np.ndarray]:
    """(4, 2) corners the locator may have in the burst ``image``, the likeliest first: the
    square fitted near the blob's quadrilateral ``blob`` (``fit_square``), after the best
    quadrilateral fitted with each corner free (from the square and from ``blob``) when that
    fits the locator's bands clearly better (``QUAD_MARGIN``). A marker seen obliquely images
    its locator as a skewed quadrilateral that no square fits within a ring width."""
    bands = _bands(image, locator_side, ring)
    square = _fit_square(bands, blob, locator_side)
    lit, inner, outer = bands
    fits = [_fit_quad(lit, start, locator_side, inner, outer) for start in (square, blob)]
    quad, contrast = max(fits, key=lambda fit: fit[1])
    if contrast > QUAD_MARGIN * _quad_contrast(lit, square[None], inner, outer)[0]:
        return [quad, square]
    return [square]


def _fit_quad(
    lit: np.ndarray, quad: np.ndarray, locator_side: int, inner: np.ndarray, outer: np.ndarray
) -> tuple[np.ndarray, float]:
    """The quadrilateral near ``quad`` whose inner band is the most lit and whose outer band the
    least in ``lit`` (``fit_square``'s measure), and that contrast. The bands follow the sides
    bilinearly between the corners, which places them on the sides' lines exactly."""
    best = np.ascontiguousarray(quad, dtype=np.float64)
    cell = np.linalg.norm(np.roll(best, -1, axis=0) - best, axis=1).mean() / locator_side
    moves = np.stack(np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]), -1).reshape(-1, 2)
    step = cell / 2
    score = _quad_contrast(lit, best[None], inner, outer)[0]
    while step >= _SQUARE_FINEST_PX:
        for _ in range(_QUAD_PASSES):
            moved = False
            for corner in range(4):
                h = np.repeat(best[None], len(moves), axis=0)
                h[:, corner] += step * moves
                scores = _quad_contrast(lit, h, inner, outer)
                k = int(np.argmax(scores))
                if scores[k] > score:
                    best, score, moved = h[k], scores[k], True
            if not moved:
                break
        step /= 2
    return best, float(score)


@numba.njit(cache=True)
def _quad_contrast(
    lit: np.ndarray, quads: np.ndarray, inner: np.ndarray, outer: np.ndarray
) -> np.ndarray:
    """Inner minus outer band brightness of quadrilaterals (k, 4, 2), the bands given in unit
    square coordinates (0..1, clockwise from the first corner) and mapped bilinearly."""
    out = np.empty(quads.shape[0])
    for k in range(quads.shape[0]):
        out[k] = _band_mean(lit, quads[k], inner) - _band_mean(lit, quads[k], outer)
    return out


@numba.njit(cache=True, inline="always")
def _band_mean(lit, q, band):
    """Mean of ``lit`` over ``band`` (unit square coordinates) mapped bilinearly onto the
    quadrilateral ``q``: q0 + u (q1 - q0) + v (q3 - q0) + u v (q2 - q1 - q3 + q0)."""
    ux, uy = q[1, 0] - q[0, 0], q[1, 1] - q[0, 1]
    vx, vy = q[3, 0] - q[0, 0], q[3, 1] - q[0, 1]
    wx, wy = q[2, 0] - q[1, 0] - vx, q[2, 1] - q[1, 1] - vy
    total = 0.0
    for i in range(band.shape[0]):
        u, v = band[i, 0], band[i, 1]
        uv = u * v
        xi = min(max(int(np.rint(q[0, 0] + u * ux + v * vx + uv * wx)), 0), lit.shape[1] - 1)
        yi = min(max(int(np.rint(q[0, 1] + u * uy + v * vy + uv * wy)), 0), lit.shape[0] - 1)
        total += lit[yi, xi]
    return total / band.shape[0]


def quadrilateral(points: np.ndarray) -> np.ndarray:
    """(4, 2) float corners, clockwise on screen (y down), approximating a convex point set."""
    hull = cv2.convexHull(points.astype(np.float32).reshape(-1, 1, 2))
    # Start at the largest (x, y), as OpenCV does for points in row order: the corners (which
    # the polygon fit's start sways) then do not depend on being given all pixels or outlines.
    hull = np.roll(hull, -np.lexsort((hull[:, 0, 1], hull[:, 0, 0]))[-1], axis=0)
    perimeter = cv2.arcLength(hull, True)
    for eps in np.linspace(0.01, 0.1, 19):
        poly = cv2.approxPolyDP(hull, eps * perimeter, True).reshape(-1, 2)
        if len(poly) <= 4:
            break
    if len(poly) != 4:
        raise MarkerNotFound(f"spatial: the blinking region has {len(poly)} corners, not 4")
    area2 = np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    return (poly if area2 > 0 else poly[::-1]).astype(np.float64)


def check_quadrilateral(quad: np.ndarray, params: DetectorParams, camera: CameraModel) -> None:
    """The paper's criteria, through the camera: large enough, and a square seen in perspective,
    not too obliquely. The homography from a unit square onto the corners (ideal pixels) is
    K [r1 r2 t] up to scale, where r1 and r2, the plane's axes, are orthogonal and of equal
    length for a square at any view."""
    lengths = np.linalg.norm(np.roll(quad, -1, axis=0) - quad, axis=1)
    if lengths.min() < params.min_side_px:
        raise MarkerNotFound(
            f"spatial: locator side {lengths.min():.0f} px is below "
            f"{params.min_side_px:.0f} px; move closer or use fewer cells"
        )
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    H = cv2.getPerspectiveTransform(unit, camera.undistort_points(quad).astype(np.float32))
    M = np.linalg.solve(camera.K, H)
    r1, r2 = M[:, 0], M[:, 1]
    n1, n2 = np.linalg.norm(r1), np.linalg.norm(r2)
    if max(n1, n2) / min(n1, n2) > params.max_square_stretch:
        raise MarkerNotFound("spatial: the blinking region is not square")
    if abs(r1 @ r2) / (n1 * n2) > params.max_square_skew:
        raise MarkerNotFound("spatial: the blinking region's corners are not right angles")
    normal = np.cross(r1, r2)
    sight = M @ np.array([0.5, 0.5, 1.0])
    cos_view = abs(normal @ sight) / (np.linalg.norm(normal) * np.linalg.norm(sight))
    if np.degrees(np.arccos(min(cos_view, 1.0))) > params.max_view_deg:
        raise MarkerNotFound(
            f"spatial: the marker is seen more obliquely than {params.max_view_deg:g} deg"
        )
