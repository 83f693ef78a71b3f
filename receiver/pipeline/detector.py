"""Marker detection (paper Sec. IV-B): where it blinks, when it blinks, and which way is up.

1. *Temporal.* Per pixel, polarity-alternation triplets (pos-neg-pos or neg-pos-neg) whose period
   is close to the blink period vote into a heat map; its largest blob is the region of interest.
   The phase of the ROI's positive-event count at the blink frequency (DFT bin ``f * T``, not a
   fixed index) gives the time of the data frames' positive bursts.
   It is measured on the ON events of the region's outer one-cell band, the locator ring.
2. *Spatial.* The positive events around those bursts outline the inner locator; its convex
   quadrilateral must pass the paper's criteria (four corners, large, right angles, equal sides).
3. *Orientation.* The ring of the inner locator (solid "L" at bottom-left, dashed top and right)
   is read in all four rotations; the best match orders the corners TL, TR, BR, BL.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from occ.marker import MarkerGeometry
from receiver.pipeline.buffer import first_at
from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.locate import MarkerNotFound, check_quadrilateral, quadrilateral


@dataclass(frozen=True)
class Detection:
    corners_px: np.ndarray
    """(4, 2) outer corners of the inner locator in sensor pixels, TL, TR, BR, BL."""
    burst_us: float
    """Time of a positive burst of the inner locator (middle of the marker's scan-out)."""
    blink_hz: float
    harmonic_ratio: float
    orientation_score: float


# --- temporal ------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _triplet_heat(t, x, y, p, freq_hz, sigma_hz, heat, triplets, last_pol, last_flip):
    """Accumulate one part of the events into ``heat`` and ``triplets``; ``last_pol`` and
    ``last_flip`` (the last neg->pos / pos->neg times) carry each pixel's state between parts."""
    for i in range(t.shape[0]):
        xi, yi, pi = x[i], y[i], p[i]
        if pi == last_pol[yi, xi]:
            continue  # runs of one polarity collapse into one transition
        last_pol[yi, xi] = pi
        d = 0 if pi > 0 else 1
        prev = last_flip[d, yi, xi]
        last_flip[d, yi, xi] = t[i]
        if prev >= 0 and t[i] > prev:
            z = (1e6 / (t[i] - prev) - freq_hz) / sigma_hz
            heat[yi, xi] += np.exp(-0.5 * z * z)
            triplets[yi, xi] += 1


def blink_heatmap(
    parts: list[np.ndarray], width: int, height: int, blink_hz: float, sigma_frac: float
) -> tuple[np.ndarray, np.ndarray]:
    """(height, width) sums of the Gaussian weights of the triplets by how well their period
    matches the blink, and the triplet counts, over the time-ordered parts of a window."""
    heat = np.zeros((height, width), np.float32)
    triplets = np.zeros((height, width), np.int32)
    last_pol = np.zeros((height, width), np.int8)
    last_flip = np.full((2, height, width), -1, np.int64)
    for ev in parts:
        _triplet_heat(
            ev["t"],
            ev["x"],
            ev["y"],
            ev["p"],
            blink_hz,
            sigma_frac * blink_hz,
            heat,
            triplets,
            last_pol,
            last_flip,
        )
    return heat, triplets


def largest_region(heat: np.ndarray, threshold: float) -> np.ndarray:
    """Convex hull (k, 2) of the largest above-threshold heat region, nearby blobs included.

    The dashed sides of the inner locator are separate blobs, so blobs within a tenth of the
    largest region's size join it."""
    peak = float(np.percentile(heat[heat > 0], 99.5)) if np.any(heat > 0) else 0.0
    if peak <= 0:
        raise MarkerNotFound("temporal: no pixel blinks at the data-frame rate")
    binary = (heat >= threshold * peak).astype(np.uint8)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    hulls = [cv2.convexHull(c) for c in contours]
    best = hulls[int(np.argmax([cv2.contourArea(h) for h in hulls]))]
    x, y, w, h = cv2.boundingRect(best)
    pad = max(2, int(0.1 * max(w, h)))
    lo, hi = np.array([x - pad, y - pad]), np.array([x + w + pad, y + h + pad])
    pts = np.argwhere(binary)[:, ::-1]
    pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    return cv2.convexHull(pts.astype(np.int32)).reshape(-1, 2)


@numba.njit(cache=True, nogil=True)
def _rising_times(t, x, y, p, mask):
    """Times of the ON events on the pixels of ``mask``."""
    out = np.empty(t.shape[0], np.int64)
    k = 0
    for i in range(t.shape[0]):
        if p[i] > 0 and mask[y[i], x[i]]:
            out[k] = t[i]
            k += 1
    return out[:k]


def locator_band(region: np.ndarray, locator_side: int) -> np.ndarray:
    """The outer one-cell band of the blinking region: the inner locator ring alone.

    The phase must come from the ring, not the payload: in ``fast``, payload cells whose symbol
    bit is the same in successive frames (header fields) toggle on every refresh too, in
    antiphase with the locator after each all-black key refresh."""
    cell_px = np.sqrt(np.count_nonzero(region)) / locator_side
    k = 2 * max(1, round(cell_px)) + 1  # erodes one cell from every side
    inner = cv2.erode(region, np.ones((k, k), np.uint8))
    return region & (1 - inner)


def blink_phase(
    t_us: np.ndarray, t_start: int, window_us: int, blink_hz: float
) -> tuple[float, float]:
    """(burst time, |X_k| / X_0) of event times at the blink frequency.

    ``X_k`` is bin ``k = f * T`` of the DFT of the event count over the window cut to whole
    blink periods (so the bin sits exactly on ``f``), taken in the limit of infinitely fine count
    bins: a sum over the events themselves, free of bin quantisation."""
    period_us = 1e6 / blink_hz
    span = max(1, int(window_us // period_us)) * period_us
    t = t_us[(t_us >= t_start) & (t_us < t_start + span)] - t_start
    if not len(t):
        return float("nan"), 0.0
    x_k = np.sum(np.exp(-2j * np.pi * t / period_us))
    phase = (2 * np.pi - np.angle(x_k)) % (2 * np.pi)
    return float(t_start + phase / (2 * np.pi) * period_us), float(abs(x_k) / len(t))


# --- spatial ---------------------------------------------------------------------------------
def ring_cells(geometry: MarkerGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(k, 2) (column, row) of the inner locator's ring cells and their canonical colour."""
    loc = geometry.inner_locator
    ring = np.zeros_like(loc)
    ring[[0, -1], :] = ring[:, [0, -1]] = True
    rows, cols = np.nonzero(ring)
    return np.stack([cols, rows], 1), loc[rows, cols]


def orient(
    quad: np.ndarray, burst: np.ndarray, geometry: MarkerGeometry
) -> tuple[np.ndarray, float]:
    """Rotate the corner order so that the inner locator reads canonically; (corners, score)."""
    n = geometry.locator_side
    cells, white = ring_cells(geometry)
    canonical = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float64)
    centres = (cells + 0.5).reshape(-1, 1, 2)
    # Average over at most half a cell, so that small cells do not blur into their neighbours.
    cell_px = np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1).mean() / n
    k = max(1, int(cell_px / 2) | 1)
    blurred = cv2.blur(burst.astype(np.float32), (k, k))
    best = (-np.inf, quad)
    for r in range(4):
        corners = np.roll(quad, -r, axis=0)
        H = cv2.getPerspectiveTransform(canonical.astype(np.float32), corners.astype(np.float32))
        px = cv2.perspectiveTransform(centres, H).reshape(-1, 2)
        xi = np.clip(np.rint(px[:, 0]).astype(int), 0, burst.shape[1] - 1)
        yi = np.clip(np.rint(px[:, 1]).astype(int), 0, burst.shape[0] - 1)
        on = blurred[yi, xi] > 0.5
        score = on[white].mean() - on[~white].mean()
        best = max(best, (score, corners), key=lambda b: b[0])
    return best[1], float(best[0])


@numba.njit(cache=True, nogil=True)
def _pixel_harmonics(t, x, y, p, x0, y0, period_us, acc):
    """Add to ``acc`` per pixel of the box from (x0, y0): the ON events' DFT at the blink
    frequency (re, im) and their count."""
    y1, x1 = y0 + acc.shape[1], x0 + acc.shape[2]
    w = 2 * np.pi / period_us
    for i in range(t.shape[0]):
        if p[i] > 0 and x0 <= x[i] < x1 and y0 <= y[i] < y1:
            a = w * t[i]
            yi, xi = y[i] - y0, x[i] - x0
            acc[0, yi, xi] += np.cos(a)
            acc[1, yi, xi] -= np.sin(a)
            acc[2, yi, xi] += 1.0


def burst_image(
    parts: list[np.ndarray],
    burst_us: float,
    period_us: float,
    mask: np.ndarray,
    periods: int = 2,
) -> np.ndarray:
    """Boolean image of the pixels of ``mask`` that brighten in step with the bursts of the last
    ``periods`` blinks.

    A pixel counts when its ON events keep one phase (harmonic ratio >= 0.5) close to the burst's:
    within 0.3 period, because the display's scan-out spreads the rows' bursts over about 0.45
    period and the pixel response delays them further, while cells blinking in antiphase sit
    half a period away. Edges swept by camera motion fire at any phase."""
    since = int(parts[-1]["t"][-1] - periods * period_us)
    x, y, w, h = cv2.boundingRect(mask)
    acc = np.zeros((3, h, w))
    for ev in parts:
        if ev["t"][-1] >= since:
            ev = ev[first_at(ev["t"], since) :]
            _pixel_harmonics(ev["t"], ev["x"], ev["y"], ev["p"], x, y, period_us, acc)
    re, im, count = acc
    amplitude = np.hypot(re, im)
    lag = np.angle((re + 1j * im) * np.exp(2j * np.pi * burst_us / period_us))
    inside = (count >= 2) & (amplitude >= 0.5 * count) & (np.abs(lag) <= 0.3 * 2 * np.pi)
    image = np.zeros(mask.shape, bool)
    image[y : y + h, x : x + w] = inside & (mask[y : y + h, x : x + w] > 0)
    return image


def detect(events: np.ndarray | list[np.ndarray], config: ReceiverConfig) -> Detection:
    """Find the marker in ``events`` (a window of about ``detector.window_us``), given as one
    array or as its time-ordered parts (the receiver's buffered chunks, never copied)."""
    params, cam = config.detector, config.camera
    parts = [p for p in ([events] if isinstance(events, np.ndarray) else events) if len(p)]
    if sum(len(p) for p in parts) < 100:
        raise MarkerNotFound("temporal: almost no events in the detection window")
    heat, triplets = blink_heatmap(parts, cam.width, cam.height, config.blink_hz, params.sigma_frac)
    hull = largest_region(heat, params.heat_threshold)
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillConvexPoly(mask, hull.astype(np.int32), 1)
    # A short window cannot resolve the blink frequency by its DFT, but every triplet measures
    # one period: in the region they must match the told blink, not just come closest to it.
    inside = mask > 0
    match = float(heat[inside].sum() / max(1, triplets[inside].sum()))
    if match < params.min_period_match:
        raise MarkerNotFound(
            f"temporal: the blinking region's period does not match {config.blink_hz:g} Hz "
            f"(mean match {match:.2f}); check --refresh-hz and --profile"
        )
    band = locator_band(mask, config.geometry.locator_side)
    rising = np.concatenate([_rising_times(p["t"], p["x"], p["y"], p["p"], band) for p in parts])
    t_start, t_end = int(parts[0]["t"][0]), int(parts[-1]["t"][-1])
    window = t_end - t_start
    burst, ratio = blink_phase(rising, t_start, window, config.blink_hz)
    if not ratio >= params.min_harmonic_ratio:
        raise MarkerNotFound(
            f"temporal: the blinking region does not pulse at {config.blink_hz:g} "
            f"Hz (harmonic ratio {ratio:.2f}); check --refresh-hz and --profile"
        )
    period = 1e6 / config.blink_hz
    img = burst_image(parts, burst, period, mask)
    points = np.argwhere(img)[:, ::-1]
    if len(points) < 16:
        raise MarkerNotFound("spatial: too few positive events at the blink phase")
    quad = quadrilateral(points)
    check_quadrilateral(quad, params)
    corners, score = orient(quad, img, config.geometry)
    if score < params.min_orientation_score:
        raise MarkerNotFound(
            f"spatial: no inner-locator 'L' found (score {score:.2f}); check --cells"
        )
    # The burst time refers to the latest whole period inside the window.
    last = burst + np.floor((t_end - burst) / period) * period
    return Detection(corners, float(last), config.blink_hz, ratio, score)
