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

Everything works in a box of the sensor around the blinking region (``Box``): contrast
maximisation tries a few hundred flows, each a histogram and a blur of the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from receiver.pipeline.config import DetectorParams

MAX_FLOW_PX_PER_MS = 2.5
"""Largest image flow searched: a brisk hand-held sweep of a marker at arm's length."""
_FLOW_SAMPLE = 30_000
"""Events used to score a flow: plenty for a sharp ring outline, cheap enough per candidate."""
_MIN_GAIN = 1.05
"""A flow must sharpen the image by this factor over zero flow, or the camera counts as still."""
HALF_WINDOW = 0.2
"""Half-width of a burst window in blink periods (paper Sec. IV-B)."""
_SQUARE_SHIFTS_PX = np.arange(-6.0, 6.5, 1.0)
_SQUARE_SCALES = np.arange(0.84, 1.07, 0.02)
"""The blob is up to a cell and a half larger than the locator on each side."""
_SQUARE_TURNS = np.radians([-3.0, -1.5, 0.0, 1.5, 3.0])


class MarkerNotFound(Exception):
    """Detection failed; the message says which stage and why."""


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


def events_between(parts: list[np.ndarray], t0: float, t1: float) -> np.ndarray:
    """The events of the time-ordered parts in [t0, t1), as one array."""
    out = [p[np.searchsorted(p["t"], t0) : np.searchsorted(p["t"], t1)] for p in parts]
    out = [p for p in out if len(p)]
    return np.concatenate(out) if out else parts[0][:0]


def warped_counts(events: np.ndarray, t_ref: float, flow: np.ndarray, box: Box) -> np.ndarray:
    """Event counts per pixel of ``box`` after moving each event along ``flow`` (px/ms) to
    ``t_ref``."""
    h, w = box.shape
    dt = (t_ref - events["t"]) / 1000.0
    x = np.rint(events["x"] + flow[0] * dt).astype(np.int64) - box.x0
    y = np.rint(events["y"] + flow[1] * dt).astype(np.int64) - box.y0
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return np.bincount(y[ok] * w + x[ok], minlength=h * w).reshape(h, w).astype(np.float32)


def motion_flow(events: np.ndarray, t_ref: float, box: Box) -> np.ndarray:
    """(vx, vy) px/ms that makes ``events`` sharpest when warped to ``t_ref``: a coarse grid,
    then finer ones around the best."""
    sample = events[:: max(1, len(events) // _FLOW_SAMPLE)]

    def sharpness(v: np.ndarray) -> float:
        img = cv2.GaussianBlur(warped_counts(sample, t_ref, v, box), (0, 0), 1.0)
        return float(np.square(img).sum())

    zero = np.zeros(2)
    if len(sample) < 100:
        return zero
    grid = np.arange(-MAX_FLOW_PX_PER_MS, MAX_FLOW_PX_PER_MS + 1e-9, 0.25)
    best = max((np.array([vx, vy]) for vx in grid for vy in grid), key=sharpness)
    for step in (0.1, 0.04):
        near = (best + step * np.array([i, j]) for i in range(-2, 3) for j in range(-2, 3))
        best = max(near, key=sharpness)
    return best if sharpness(best) > _MIN_GAIN * sharpness(zero) else zero


def compensated_burst(
    parts: list[np.ndarray], burst_us: float, period_us: float, box: Box
) -> CompensatedBurst:
    """The latest burst whose following half period is in ``parts``: pixels of ``box`` with
    more ON events in the burst than in either blank frame beside it, all warped to the burst
    time."""
    half = HALF_WINDOW * period_us
    t_end = float(parts[-1]["t"][-1])
    tb = burst_us + np.floor((t_end - period_us / 2 - half - burst_us) / period_us) * period_us
    burst = events_between(parts, tb - half, tb + half)
    flow = motion_flow(burst[burst["p"] < 0], tb, box)
    blank = period_us / 2  # the blank frames' switches, where only motion fires ON
    windows = (events_between(parts, tb + d - half, tb + d + half) for d in (0, -blank, blank))
    on = [warped_counts(ev[ev["p"] > 0], tb, flow, box) for ev in windows]
    return CompensatedBurst(on[0] - np.maximum(on[1], on[2]) >= 1, box, float(tb), flow)


def locator_blob(image: np.ndarray, cell_px: float) -> np.ndarray:
    """(k, 2) pixels of the largest blob after joining cells (closing by one cell) and removing
    lines thinner than two cells (opening)."""
    small = np.ones((max(3, round(cell_px) | 1),) * 2, np.uint8)
    large = np.ones((max(3, round(2 * cell_px) | 1),) * 2, np.uint8)
    blob = cv2.morphologyEx(image.astype(np.uint8), cv2.MORPH_CLOSE, small)
    blob = cv2.morphologyEx(blob, cv2.MORPH_OPEN, large)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(blob)
    if n < 2:
        raise MarkerNotFound("spatial: nothing brightens with the bursts as a solid blob")
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return np.argwhere(labels == biggest)[:, ::-1]


def _square_outline(half: float, per_side: int = 24) -> np.ndarray:
    """(4 * per_side, 2) points along the sides of the square of half-side ``half`` around 0."""
    s = ((np.arange(per_side) + 0.5) / per_side * 2 - 1) * half
    a = np.full(per_side, half)
    return np.vstack([np.c_[s, -a], np.c_[a, s], np.c_[-s, a], np.c_[-a, -s]])


def fit_square(image: np.ndarray, quad: np.ndarray, locator_side: int, ring: int) -> np.ndarray:
    """(4, 2) corners of the square, near ``quad``, whose inner band (the locator ring's cells)
    is the most lit and whose outer band (the dark ring around the locator) the least, in the
    blurred ``image``; a grid of shifts, scales and turns, then two finer ones."""
    lit = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.0)
    inner = _square_outline(0.5 - 0.5 / locator_side)
    outer = _square_outline(0.5 + 0.5 * ring / locator_side)
    sides = np.roll(quad, -1, axis=0) - quad
    side = np.linalg.norm(sides, axis=1).mean()
    # Mean direction of the sides modulo 90 degrees.
    turn = np.angle(np.mean(np.exp(4j * np.arctan2(sides[:, 1], sides[:, 0])))) / 4

    def contrast(h: np.ndarray) -> np.ndarray:
        """Inner minus outer band brightness of squares h = (cx, cy, side, turn), (k, 4)."""
        c, s = np.cos(h[:, 3:]), np.sin(h[:, 3:])
        band = []
        for u in (inner, outer):
            x = h[:, :1] + h[:, 2:3] * (c * u[:, 0] - s * u[:, 1])
            y = h[:, 1:2] + h[:, 2:3] * (s * u[:, 0] + c * u[:, 1])
            xi = np.clip(np.rint(x).astype(np.int64), 0, lit.shape[1] - 1)
            yi = np.clip(np.rint(y).astype(np.int64), 0, lit.shape[0] - 1)
            band.append(lit[yi, xi].mean(axis=1))
        return band[0] - band[1]

    def grid(*axes: np.ndarray) -> np.ndarray:
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)

    centre = quad.mean(axis=0)
    h = grid(
        centre[0] + _SQUARE_SHIFTS_PX,
        centre[1] + _SQUARE_SHIFTS_PX,
        side * _SQUARE_SCALES,
        turn + _SQUARE_TURNS,
    )
    best = h[np.argmax(contrast(h))]
    for step in (0.5, 0.25):
        k = np.arange(-2, 3) * step
        h = best + grid(k, k, k * 0.02 * side, np.radians(k))
        best = h[np.argmax(contrast(h))]
    cx, cy, length, angle = best
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    unit = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    return np.array([cx, cy]) + length * unit @ rotation.T


def quadrilateral(points: np.ndarray) -> np.ndarray:
    """(4, 2) float corners, clockwise on screen (y down), approximating a convex point set."""
    hull = cv2.convexHull(points.astype(np.float32).reshape(-1, 1, 2))
    perimeter = cv2.arcLength(hull, True)
    for eps in np.linspace(0.01, 0.1, 19):
        poly = cv2.approxPolyDP(hull, eps * perimeter, True).reshape(-1, 2)
        if len(poly) <= 4:
            break
    if len(poly) != 4:
        raise MarkerNotFound(f"spatial: the blinking region has {len(poly)} corners, not 4")
    area2 = np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    return (poly if area2 > 0 else poly[::-1]).astype(np.float64)


def check_quadrilateral(quad: np.ndarray, params: DetectorParams) -> None:
    """The paper's criteria: large enough, corners near right angles, sides of similar length."""
    sides = np.roll(quad, -1, axis=0) - quad
    lengths = np.linalg.norm(sides, axis=1)
    if lengths.min() < params.min_side_px:
        raise MarkerNotFound(
            f"spatial: locator side {lengths.min():.0f} px is below "
            f"{params.min_side_px:.0f} px; move closer or use fewer cells"
        )
    if lengths.max() / lengths.min() > params.max_side_ratio:
        raise MarkerNotFound("spatial: the blinking region is not square (view too oblique?)")
    cosines = np.abs(np.sum(sides * np.roll(sides, 1, axis=0), axis=1)) / (
        lengths * np.roll(lengths, 1)
    )
    if cosines.max() > params.max_abs_cos:
        raise MarkerNotFound("spatial: the blinking region's corners are not right angles")
