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
   thin remains of swept edges; its convex quadrilateral is the locator's outline.

Not yet wired into ``detector.detect``: the outline is found to a few pixels under motion, but
reading the locator's orientation from the compensated image is still unreliable (about half of
the windows of a 0.5 px/ms hand-held clip pick a wrong rotation), so a lock would often start
rotated. ``quadrilateral`` and ``check_quadrilateral`` serve both paths.
"""

from __future__ import annotations

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


class MarkerNotFound(Exception):
    """Detection failed; the message says which stage and why."""


def _select(parts: list[np.ndarray], t0: float, t1: float) -> np.ndarray:
    """The events of the time-ordered parts in [t0, t1)."""
    out = [p[np.searchsorted(p["t"], t0) : np.searchsorted(p["t"], t1)] for p in parts]
    out = [p for p in out if len(p)]
    return np.concatenate(out) if out else parts[0][:0]


def warped_counts(
    events: np.ndarray, t_ref: float, flow: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """Event counts per pixel after moving each event along ``flow`` (px/ms) to ``t_ref``."""
    h, w = shape
    dt = (t_ref - events["t"]) / 1000.0
    x = np.rint(events["x"] + flow[0] * dt).astype(np.int64)
    y = np.rint(events["y"] + flow[1] * dt).astype(np.int64)
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return np.bincount(y[ok] * w + x[ok], minlength=h * w).reshape(h, w).astype(np.float32)


def motion_flow(events: np.ndarray, t_ref: float, shape: tuple[int, int]) -> np.ndarray:
    """(vx, vy) px/ms that makes ``events`` sharpest when warped to ``t_ref``: a coarse grid,
    then finer ones around the best."""
    sample = events[:: max(1, len(events) // _FLOW_SAMPLE)]

    def sharpness(v: np.ndarray) -> float:
        img = cv2.GaussianBlur(warped_counts(sample, t_ref, v, shape), (0, 0), 1.0)
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
    parts: list[np.ndarray], burst_us: float, period_us: float, shape: tuple[int, int]
) -> tuple[np.ndarray, float, np.ndarray]:
    """(blink image, its time, flow px/ms) of the latest burst whose following half period is in
    ``parts``: pixels with more ON events in the burst than in either blank frame beside it, all
    warped to the burst time."""
    half = HALF_WINDOW * period_us
    t_end = float(parts[-1]["t"][-1])
    tb = burst_us + np.floor((t_end - period_us / 2 - half - burst_us) / period_us) * period_us
    burst = _select(parts, tb - half, tb + half)
    flow = motion_flow(burst[burst["p"] < 0], tb, shape)
    on = [
        warped_counts(ev[ev["p"] > 0], tb, flow, shape)
        for ev in (
            _select(parts, tb + d - half, tb + d + half) for d in (0, -period_us / 2, period_us / 2)
        )
    ]
    return on[0] - np.maximum(on[1], on[2]) >= 1, float(tb), flow


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
