"""Marker detection (paper Sec. IV-B): where it blinks, when it blinks, and which way is up.

Two paths share the first step, a coarse blink map: per tile of ``TILE_PX`` pixels, the events'
DFT at the blink frequency over the window. Its largest blinking region gives a box and the burst
phase, and the burst nearest the window's end, motion-compensated inside that box
(``locate.compensated_burst``), gives the image flow. A still camera (zero flow) takes the
paper's path below; a moving one takes ``_detect_moving``.

Still camera:

1. *Temporal.* Per pixel, polarity-alternation triplets (pos-neg-pos or neg-pos-neg) whose period
   is close to the blink period vote into a heat map; its largest blob is the region of interest.
   The phase of the ROI's positive-event count at the blink frequency (DFT bin ``f * T``, not a
   fixed index) gives the time of the data frames' positive bursts.
   It is measured on the ON events of the region's outer one-cell band, the locator ring.
2. *Spatial.* The positive events around those bursts outline the inner locator; its convex
   quadrilateral must pass the paper's criteria (four corners, large, a square as seen through
   the camera).
   Once oriented, its corners are refined to sub-pixel edges less blur's spread (``edges``).
3. *Orientation.* The ring of the inner locator (solid "L" at bottom-left, dashed top and right)
   is read in all four rotations; the best match orders the corners TL, TR, BR, BL.

Moving camera: per-pixel triplets break once the marker slides a cell per blink, so everything
comes from the one compensated burst and its fitted locator square (``locate``). A slow burst's
square that reads the 'L' clearly gives the pose itself, as a slow ring fires too little to fit
(``DetectorParams.max_square_flow_px_per_ms``). Otherwise the square is only a start for the
ring's edges, one cell wide, and it ignores perspective: a few scaled copies of it are each
pulled onto the ring's edge events around the burst (``EdgeTracker.capture``), and the pose
that puts the most events on the edges wins. The locator's "L" is then read through
that pose; where it is unclear but the fit is sound, the best guess of its turn goes on to the
frames read after the burst, which must confirm it (``Detection.oriented``).

Last resorts: a camera drifting a fraction of a pixel per ms can mislead the flow search (the
display's own OFF events line up at some faster flow) or be too slow for it, while it smears
the still path's image of several blinks; the burst compensated by the sharpest slow flow
(``locate.slow_flow``) then shows a square that may read the 'L' (``_detect_slow``). Under
motion, when nothing reads at the latest burst, the burst a blink period before it gets the
moving and slow paths too: a hand-held camera's turn or jolt smears one burst, not every one,
and the lock tracks the older burst's pose through the buffered events all the same. Right
after the phase's time, the moving path also reads the latest burst where its ON events lie densest
(``locate.densest_burst_us``): the blink map's phase averages the window's bursts with the ON
events that moving edges fire at every phase, and can place the burst a millisecond or two off.

Cost: a still camera must not pay for the motion path. The blink map reads a sample of the
window, the flow is scored on a few thousand OFF events in one compiled pass, and the per-event
DFTs look their phases up in a table, so that the still path's own per-pixel passes take most
of an attempt on a megapixel window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np
from scipy.spatial.transform import Rotation

from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.profiles import get_profile
from eventocc.receiver.pipeline.buffer import EventColumns, first_at, to_columns
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.edges import refine_corners
from eventocc.receiver.pipeline.locate import (
    HALF_WINDOW,
    Box,
    CompensatedBurst,
    MarkerNotFound,
    burst_flow,
    check_quadrilateral,
    compensated_burst,
    densest_burst_us,
    events_between,
    latest_burst_us,
    locator_blob,
    locator_fits,
    outline,
    quadrilateral,
)
from eventocc.receiver.pipeline.pose import pnp, project_ideal
from eventocc.receiver.pipeline.tracker import (
    EdgeTracker,
    _nearest_edge,
    edge_polarities,
)

TILE_PX = 8
"""Side of the blink map's tiles: a couple of cells at the smallest accepted marker."""
_CHECK_BLINK = (
    "check --refresh-hz and --profile, and that the screen runs at full brightness (a dimmed "
    "backlight's PWM flicker hides the blink)"
)
"""What a temporal failure asks the user to check: the link settings, and a flickering screen,
which no refresh rate or profile makes readable."""
_MAP_SAMPLE = 1_000_000
"""Events of the window that the blink map reads (every k-th): a tile's pulse stands out of a
sample as well as of all of them, and a megapixel sensor's window holds ten times as many."""
_BUSY_TILE_SHARE = 0.1
"""Tiles with fewer events than this share of the busiest ones are noise, whatever their DFT."""
_CAPTURE_SCALES = (1.0, 0.96, 1.04)
"""Scales of the fitted locator square tried as capture starts: a start about a ring width off
pulls the ring's inner edge onto the outer one (or the locator's), so neighbours are tried too.
Only close ones: among more starts the largest of their noisy 'L' readings passes more wrong
fits."""
_CAPTURE_HALF_US = 1000
"""Half the span of edge events a capture uses, at most: the span over which the ring moves a
pixel at the burst's flow, from a quarter to a whole millisecond (a capture fits the smeared
ring's middle, and a fixed millisecond either side would smear it over 12 px at 6 px/ms)."""
_CAPTURE_SAMPLE = 30_000
"""Events a capture reads at most (every k-th): a megapixel sensor fires millions around the
burst, and a pose of eight edges needs far fewer."""
_ON_EDGE_PX = 1.0
"""An event within this distance of a projected ring edge counts as on it (capture scoring)."""
_REVERSED_SIDE = -0.6
"""A captured ring's outer side whose events agree with the burst's flow this badly or worse
(``ring_support``) lies on an edge of the other sign, a ring width off: such sides read -0.8
to -1. The tracker's own test (``tracker.REVERSED_AGREEMENT``) is stricter, as it judges each
edge by its own velocity; a burst gives one flow for the whole marker, and where the camera
also turns a side's own flow can be half of it, so a right fit's side reads its events mixed
(down to -0.48 over the randomized suite's and the tracking paths' captures)."""


_PHASE_STEPS = 512
"""Blink phases tabulated for the per-event DFTs: steps of 0.7 degrees, far finer than the
bursts' spread, and a table look-up costs a fraction of a sine and a cosine."""
_COS = np.cos(2 * np.pi * np.arange(_PHASE_STEPS) / _PHASE_STEPS)
_SIN = np.sin(2 * np.pi * np.arange(_PHASE_STEPS) / _PHASE_STEPS)


@numba.njit(cache=True, nogil=True, inline="always")
def _phase_step(t, period_us):
    """Index into ``_COS`` and ``_SIN`` of time ``t``'s phase in the blink period (a product
    and a floor: a float modulo would cost more than the sine it saves)."""
    cycles = t / period_us
    return int((cycles - np.floor(cycles)) * _PHASE_STEPS) % _PHASE_STEPS


@dataclass(frozen=True)
class Detection:
    corners_px: np.ndarray
    """(4, 2) outer corners of the inner locator in sensor pixels, TL, TR, BR, BL, at ``t_us``."""
    T_cam_world: np.ndarray
    """Pose at ``t_us``."""
    t_us: int
    """When the corners and the pose hold: the window's end for a still camera, the
    compensated burst under motion."""
    burst_us: float
    """Time of a positive burst of the inner locator (middle of the marker's scan-out)."""
    blink_hz: float
    harmonic_ratio: float
    orientation_score: float
    flow_px_per_ms: np.ndarray
    """Image flow found at the burst; zero for a still camera."""
    refined: bool = False
    """The still path's corners lie on the locator's edges (``edges.refine_corners`` could
    tell them); otherwise they are the outline's, a pixel or two off on some windows."""
    oriented: bool = True
    """Whether the burst showed the 'L' clearly. Under motion the ring may fit while it does
    not (at 4 px per cell few bursts do): the corner order is then the burst's best guess, which
    the frames read through the pose must confirm before the lock stands."""

    @property
    def moving(self) -> bool:
        return bool(np.any(self.flow_px_per_ms))


# --- temporal ------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _triplet_heat(events, blink, sums, pixels):
    """Accumulate one part of the ``events`` = (t, x, y, p) into ``sums`` = (heat, triplets),
    weighing a triplet by how well its period matches ``blink`` = (freq_hz, sigma_hz);
    ``pixels`` = (last_pol, last_flip) (the last neg->pos / pos->neg times) carries each
    pixel's state between parts."""
    t, x, y, p = events
    freq_hz, sigma_hz = blink
    heat, triplets = sums
    last_pol, last_flip = pixels
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
    blink, sums, pixels = (blink_hz, sigma_frac * blink_hz), (heat, triplets), (last_pol, last_flip)
    for ev in parts:
        _triplet_heat((ev["t"], ev["x"], ev["y"], ev["p"]), blink, sums, pixels)
    return heat, triplets


def largest_region(heat: np.ndarray, threshold: float, locator_side: int) -> np.ndarray:
    """Convex hull (k, 2) of the largest above-threshold heat region, nearby blobs included.

    The marker's heat breaks into blobs wherever its cells stay dark for the window (the
    dashed sides of the inner locator, runs of black payload cells), and at a few pixels per
    cell a whole corner of it can come apart. Blobs less than a cell apart are one region: the
    above-threshold pixels are dilated by about a cell (the largest blob's size over the
    locator's cells) before the regions are told apart."""
    peak = float(np.percentile(heat[heat > 0], 99.5)) if np.any(heat > 0) else 0.0
    if peak <= 0:
        raise MarkerNotFound("temporal: no pixel blinks at the data-frame rate")
    binary = (heat >= threshold * peak).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if n < 2:
        raise MarkerNotFound("temporal: no pixel blinks at the data-frame rate")
    largest = stats[1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))]
    cell_px = max(largest[cv2.CC_STAT_WIDTH], largest[cv2.CC_STAT_HEIGHT]) / locator_side
    reach = max(1, round(cell_px))
    joined = cv2.dilate(binary, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach + 1,) * 2))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
    region = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))) & (binary > 0)
    x, y, w, h = cv2.boundingRect(region.astype(np.uint8))
    # The hull of the region's pixels is that of their outlines: far fewer points.
    box = region[y : y + h, x : x + w].astype(np.uint8)
    return cv2.convexHull(outline(box) + np.array([x, y])).reshape(-1, 2)


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


def _mask_cell_px(region: np.ndarray, locator_side: int) -> float:
    """A cell's side in pixels, roughly, from a blinking region about the inner locator."""
    return math.sqrt(np.count_nonzero(region)) / locator_side


def locator_band(region: np.ndarray, locator_side: int) -> np.ndarray:
    """The outer one-cell band of the blinking region: the inner locator ring alone.

    The phase must come from the ring, not the payload: in ``fast``, payload cells whose symbol
    bit is the same in successive frames (header fields) toggle on every refresh too, in
    antiphase with the locator after each all-black key refresh."""
    k = 2 * max(1, round(_mask_cell_px(region, locator_side))) + 1  # erodes a cell per side
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


@numba.njit(cache=True, nogil=True)
def _tile_harmonics(t, x, y, p, t0, period_us, acc):
    """Add to ``acc`` per tile: the signed events' DFT at the blink frequency (re, im), their
    count, and the same three for the ON events alone; events before ``t0`` are skipped."""
    for i in range(t.shape[0]):
        if t[i] < t0:
            continue
        k = _phase_step(t[i] - t0, period_us)
        ty, tx = y[i] // TILE_PX, x[i] // TILE_PX
        c, s = _COS[k], -_SIN[k]
        acc[0, ty, tx] += p[i] * c
        acc[1, ty, tx] += p[i] * s
        acc[2, ty, tx] += 1.0
        if p[i] > 0:
            acc[3, ty, tx] += c
            acc[4, ty, tx] += s
            acc[5, ty, tx] += 1.0


@dataclass(frozen=True)
class BlinkRegion:
    box: Box
    """Sensor box around the largest blinking region, one tile of margin."""
    burst_us: float
    harmonic_ratio: float


def blinking_region(parts: list[np.ndarray], config: ReceiverConfig) -> BlinkRegion:
    """The largest 8-connected region of tiles whose events pulse at the blink frequency, over
    the latest whole blink periods of the window, and the phase of its ON events.

    Tiles are coarse enough that a marker sliding several cells per blink still blinks in them,
    and a tile's signed DFT needs no per-pixel history."""
    cam, period = config.camera, 1e6 / config.blink_hz
    t_end = int(parts[-1]["t"][-1])
    span = max(1, int((t_end - int(parts[0]["t"][0])) // period)) * period
    t0 = int(t_end - span)
    acc = np.zeros((6, -(-cam.height // TILE_PX), -(-cam.width // TILE_PX)))
    step = max(1, sum(len(ev) for ev in parts) // _MAP_SAMPLE)
    for ev in parts:
        ev = ev[::step]
        _tile_harmonics(ev["t"], ev["x"], ev["y"], ev["p"], t0, period, acc)
    count = acc[2]
    ratio = np.hypot(acc[0], acc[1]) / np.maximum(count, 1.0)
    busy = count >= _BUSY_TILE_SHARE * np.percentile(count, 99)
    # Random phases give a ratio of about 1 / sqrt(count): a tile must stand well above that.
    least = config.detector.min_tile_ratio
    enough = ratio >= np.maximum(least, 3.0 / np.sqrt(np.maximum(count, 1.0)))
    blinking = (busy & enough).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(blinking, connectivity=8)
    if n < 2:
        raise MarkerNotFound(f"temporal: nothing blinks at {config.blink_hz:g} Hz; {_CHECK_BLINK}")
    region = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x_k = complex(acc[3][region].sum(), acc[4][region].sum())
    on = acc[5][region].sum()
    phase = (2 * np.pi - np.angle(x_k)) % (2 * np.pi)
    tx, ty, tw, th = cv2.boundingRect(region.astype(np.uint8))
    box = Box(
        max(0, (tx - 1) * TILE_PX),
        max(0, (ty - 1) * TILE_PX),
        min(cam.width, (tx + tw + 1) * TILE_PX),
        min(cam.height, (ty + th + 1) * TILE_PX),
    )
    return BlinkRegion(box, t0 + phase / (2 * np.pi) * period, abs(x_k) / max(on, 1.0))


# --- spatial ---------------------------------------------------------------------------------
def ring_cells(geometry: MarkerGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(k, 2) (column, row) of the inner locator's ring cells and their canonical colour."""
    loc = geometry.inner_locator
    ring = np.zeros_like(loc)
    ring[[0, -1], :] = ring[:, [0, -1]] = True
    rows, cols = np.nonzero(ring)
    return np.stack([cols, rows], 1), loc[rows, cols]


_CELL_SAMPLES = 6
"""Samples per cell side when the burst image is warped onto the locator grid."""


def locator_cells(corners: np.ndarray, image: np.ndarray, side: int) -> np.ndarray:
    """(side, side) share of lit pixels in the inner half of each locator cell, the grid spanned
    by ``corners`` (TL, TR, BR, BL of the locator in ``image``'s pixels). Cell centres alone
    mislead at a few pixels per cell: blur and motion light up the edges of black cells."""
    size = side * _CELL_SAMPLES
    # Sample centres sit symmetrically in the cells, so a grid of the corners rolled by a
    # quarter turn reads the same samples turned (``turn_readings``).
    grid = np.array([[0, 0], [size, 0], [size, size], [0, size]], np.float32) - 0.5
    H = cv2.getPerspectiveTransform(grid, corners.astype(np.float32))
    flat = cv2.warpPerspective(
        image.astype(np.float32), H, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )
    inner = slice(_CELL_SAMPLES // 4, _CELL_SAMPLES - _CELL_SAMPLES // 4)
    return flat.reshape(side, _CELL_SAMPLES, side, _CELL_SAMPLES)[:, inner, :, inner].mean(
        axis=(1, 3)
    )


def turn_readings(cells: np.ndarray, geometry: MarkerGeometry) -> np.ndarray:
    """(4,) readings of the inner locator's ring in a (side, side) grid of per-cell values, with
    the grid turned by r = 0..3 quarter turns: the mean of the ring's white cells minus that of
    its black ones. Turn r is what the grid of the corners ``np.roll(quad, -r)`` reads, so a
    pose or a corner order a quarter turn off reads best at r != 0."""
    ring, white = ring_cells(geometry)
    lit = np.stack([np.rot90(cells, r) for r in range(4)])[:, ring[:, 1], ring[:, 0]]
    return lit[:, white].mean(axis=1) - lit[:, ~white].mean(axis=1)


def orient(
    quad: np.ndarray, burst: np.ndarray, geometry: MarkerGeometry
) -> tuple[np.ndarray, float]:
    """Rotate the corner order so that the inner locator reads canonically; (corners, score).

    A rotation reads as the mean lit share of the ring's white cells minus that of its black
    ones; the score is the best reading's lead over the runner-up, since under motion or blur
    every rotation can read a little above zero and only a clear lead names the "L"."""
    readings = turn_readings(locator_cells(quad, burst, geometry.locator_side), geometry)
    best, runner_up = np.argsort(readings)[::-1][:2]
    return np.roll(quad, -best, axis=0), float(readings[best] - readings[runner_up])


_IN_PHASE = 0.3
"""How near a burst, in periods, an ON event fires in phase with it (``burst_image``)."""


@numba.njit(cache=True, nogil=True)
def _pixel_harmonics(t, x, y, p, x0, y0, period_us, burst_us, acc):
    """Add to ``acc`` (rows, columns, 5) per pixel of the box from (x0, y0): the ON events' DFT
    at the blink frequency (re, im), their count, the index of the burst (at ``burst_us`` +
    a whole number of periods) of its first one within ``_IN_PHASE`` of one, and 1 once
    another such lies at another burst; a pixel's sums share a cache line."""
    y1, x1 = y0 + acc.shape[0], x0 + acc.shape[1]
    for i in range(t.shape[0]):
        if p[i] > 0 and x0 <= x[i] < x1 and y0 <= y[i] < y1:
            k = _phase_step(t[i], period_us)
            yi, xi = y[i] - y0, x[i] - x0
            acc[yi, xi, 0] += _COS[k]
            acc[yi, xi, 1] -= _SIN[k]
            acc[yi, xi, 2] += 1.0
            phase = (t[i] - burst_us) / period_us
            burst = math.floor(phase + 0.5)
            if abs(phase - burst) > _IN_PHASE:
                continue
            if math.isnan(acc[yi, xi, 3]):
                acc[yi, xi, 3] = burst
            elif burst != acc[yi, xi, 3]:
                acc[yi, xi, 4] = 1.0


def burst_image(
    parts: list[np.ndarray],
    burst_us: float,
    period_us: float,
    mask: np.ndarray,
    periods: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """How strongly each pixel of ``mask`` brightens in step with the bursts of the last
    ``periods`` blinks: 0 where it does not, else its in-phase ON events over those of the
    brightest tenth of such pixels, at most 1; and where it does so at more than one burst.

    A pixel counts when its ON events keep one phase (harmonic ratio >= 0.5) close to the burst's:
    within ``_IN_PHASE`` of a period, because the display's scan-out spreads the rows' bursts
    over about 0.45 period and the pixel response delays them further, while cells blinking in
    antiphase sit half a period away. Edges swept by camera motion fire at any phase. The
    strength tells a lit cell from a dark one that blur lights a little: the sensor answers the
    log of the light, so a dark cell that gets a few per cent of its neighbour's fires in phase
    as well, with fewer events. Only a pixel that fires at two bursts or more is known to
    blink: where the marker appeared within the window, every pixel it lit fired once, the
    static rings included, and the several events of that one switch keep its phase as well
    as a blink's."""
    since = int(parts[-1]["t"][-1] - periods * period_us)
    x, y, w, h = cv2.boundingRect(mask)
    acc = np.zeros((h, w, 5))
    acc[..., 3] = np.nan  # no burst yet
    for ev in parts:
        if ev["t"][-1] >= since:
            ev = ev[first_at(ev["t"], since) :]
            _pixel_harmonics(ev["t"], ev["x"], ev["y"], ev["p"], x, y, period_us, burst_us, acc)
    re, im, count, _, repeated = np.moveaxis(acc, -1, 0)
    amplitude = np.hypot(re, im)
    lag = np.angle((re + 1j * im) * np.exp(2j * np.pi * burst_us / period_us))
    inside = (count >= 2) & (amplitude >= 0.5 * count) & (np.abs(lag) <= _IN_PHASE * 2 * np.pi)
    inside &= mask[y : y + h, x : x + w] > 0
    strength = np.where(inside, amplitude * np.cos(lag), 0.0)
    image = np.zeros(mask.shape, np.float32)
    blinks = np.zeros(mask.shape, bool)
    if inside.any():
        top = np.percentile(strength[inside], 90)
        image[y : y + h, x : x + w] = np.clip(strength / top, 0.0, 1.0) * inside
        blinks[y : y + h, x : x + w] = inside & (repeated > 0)
    return image, blinks


def detect(events: np.ndarray | list[np.ndarray], config: ReceiverConfig) -> Detection:
    """Find the marker in ``events`` (a window of about ``detector.window_us``), given as one
    array or as its time-ordered parts (the receiver's buffered chunks, never copied)."""
    parts = _window_parts(events)
    period = 1e6 / config.blink_hz
    try:
        region = blinking_region(parts, config)
    except MarkerNotFound:  # the still path says why in its own, finer terms
        return _detect_still(parts, config)
    tb = latest_burst_us(parts, region.burst_us, period)
    flow = burst_flow(parts, tb, period, region.box)
    if np.any(flow) and not region.harmonic_ratio >= config.detector.min_harmonic_ratio:
        raise MarkerNotFound(
            f"temporal: the blinking region does not pulse at {config.blink_hz:g} "
            f"Hz (harmonic ratio {region.harmonic_ratio:.2f}); {_CHECK_BLINK}"
        )
    paths = [lambda: _detect_moving(parts, tb, flow, region, config)]
    if np.any(flow):
        paths.append(lambda: _detect_densest(parts, tb, region, config))
    # A small marker's few OFF events can fake a flow: the still path gets its chance too.
    paths += [
        lambda: _detect_still(parts, config),
        lambda: _detect_slow(parts, tb, region, config),
    ]
    # Under motion the latest burst is often unreadable while the one before reads clearly.
    before = tb - period
    if np.any(flow) and before - HALF_WINDOW * period >= parts[0]["t"][0]:
        paths += [
            lambda: _detect_moving(parts, before, None, region, config),
            lambda: _detect_slow(parts, before, region, config),
        ]
    cell_px = region_cell_px(region, config)
    # The coarsest binning first, then each finer one: a thinned readout's corners can come out
    # ragged on one binning and straight on another, with which of them varying by blink.
    b = bin_factor(cell_px, config)
    while b > 1:
        paths.append(lambda b=b: _detect_binned(parts, config, b))
        b //= 2
    # A detection that did not read the 'L' (not ``oriented``) stands only if no later path
    # reads it: a still camera's noise can fake a flow whose burst shows no 'L', where the
    # still path reads it clearly.
    misses, unoriented = [], None
    for path in paths:
        try:
            found = path()
        except MarkerNotFound as miss:
            misses.append(miss)
            continue
        if found is not None and found.oriented:
            return _sharper_if_still(found, parts, config)
        unoriented = unoriented or found
    if unoriented is not None:
        return unoriented
    misses[0].cell_px = cell_px
    raise misses[0]  # the preferred path's reason


def _sharper_if_still(
    found: Detection, parts: list[np.ndarray], config: ReceiverConfig
) -> Detection:
    """``found``, or the still path's detection where ``found`` is a burst's that reads the 'L'
    less clearly than a still marker shows it (``min_still_orientation_score``) and the still
    path reads it more clearly. A still camera's noise can fake a flow of several px/ms whose
    compensated burst still shows a faint 'L', and a lock on it fails its checks where the still
    path's would stand. Under motion the still path's phase-locked image smears, and it fails or
    reads the 'L' fainter."""
    if not found.moving or found.orientation_score >= config.detector.min_still_orientation_score:
        return found
    try:
        still = _detect_still(parts, config)
    except MarkerNotFound:
        return found
    return still if still.orientation_score > found.orientation_score else found


def _window_parts(events: np.ndarray | list[np.ndarray]) -> list[np.ndarray]:
    """The non-empty parts of a detection window, which must hold a hundred events at least."""
    parts = [p for p in ([events] if isinstance(events, np.ndarray) else events) if len(p)]
    if sum(len(p) for p in parts) < 100:
        raise MarkerNotFound("temporal: almost no events in the detection window")
    return parts


def bin_factor(cell_px: float, config: ReceiverConfig) -> int:
    """Pixels binned per side (1, 2 or 4) for the still path's last resorts on sparse events,
    the coarsest of them (``detect`` tries each finer one after it): as many as leave
    ``DetectorParams.min_binned_cell_px`` per cell and divide the sensor."""
    cam, least = config.camera, config.detector.min_binned_cell_px
    b = 1
    while b < 4 and cell_px / (2 * b) >= least and cam.width % (2 * b) == 0 == cam.height % (2 * b):
        b *= 2
    return b


def _detect_binned(parts: list[np.ndarray], config: ReceiverConfig, b: int) -> Detection:
    """The still path on a sensor of ``b`` x ``b`` binned pixels, its corners taken back to the
    full one. A readout that caps the event rate (a rate controller, a slow link) leaves a
    large marker's pixels a fraction of an event per blink, too few for a pixel's own triplets
    and phase, while a binned pixel collects a cell's worth."""
    cam = config.camera
    coarse = replace(config, camera=cam.binned(cam.width // b, cam.height // b))
    found = _detect_still(_binned(parts, b), coarse)
    corners = (found.corners_px + 0.5) * b - 0.5
    return replace(found, corners_px=corners, T_cam_world=_solve_pnp(corners, config))


def _binned(parts: list[np.ndarray], b: int) -> list[np.ndarray]:
    """Copies of ``parts`` on ``b`` x ``b`` binned pixels."""
    binned = []
    for p in parts:
        q = p.copy()
        q["x"] //= b
        q["y"] //= b
        binned.append(q)
    return binned


def region_cell_px(region: BlinkRegion, config: ReceiverConfig) -> float:
    """A cell's side in pixels, roughly, from the blinking region's box: the region is about the
    inner locator (``_SQUARE_SCALES``), its box a tile wider on each side."""
    box = region.box
    side = min(box.x1 - box.x0, box.y1 - box.y0) - 2 * TILE_PX
    return max(side, 0) / config.geometry.locator_side


def _detect_still(parts: list[np.ndarray], config: ReceiverConfig) -> Detection:
    """The paper's path: per-pixel triplets, the locator band's phase, the phase-locked image."""
    params, cam = config.detector, config.camera
    heat, triplets = blink_heatmap(parts, cam.width, cam.height, config.blink_hz, params.sigma_frac)
    hull = largest_region(heat, params.heat_threshold, config.geometry.locator_side)
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillConvexPoly(mask, hull.astype(np.int32), 1)
    # A short window cannot resolve the blink frequency by its DFT, but every triplet measures
    # one period: in the region they must match the told blink, not just come closest to it.
    match = _period_match(heat, triplets, mask)
    if match < params.min_period_match and not _binned_blink(parts, mask, config):
        raise MarkerNotFound(
            f"temporal: the blinking region's period does not match {config.blink_hz:g} Hz "
            f"(mean match {match:.2f}); {_CHECK_BLINK}"
        )
    return _still_in_region(parts, config, mask)


_HELD_PAD_CELLS = 0.5
"""How far a recheck's region reaches beyond the held locator's outline, in cells: beyond
the blur of the ring's outer pixels, so that the phase-locked image is not clipped."""


def recheck_still(
    parts: list[np.ndarray], config: ReceiverConfig, held_px: np.ndarray
) -> Detection:
    """The still path on the region of a lock's held locator corners ``held_px`` (4, 2),
    without searching for it: a still lock's recheck, which the blink's heat map and period
    check (about half the path's CPU) would only find again where the lock stands. The
    locator band is the held ring's."""
    parts = _window_parts(parts)
    cam, side = config.camera, config.geometry.locator_side
    cell_px = np.hypot(*(held_px - np.roll(held_px, 1, axis=0)).T).mean() / side

    def region(pad_px: float) -> np.ndarray:
        inward = held_px.mean(axis=0) - held_px
        corners = held_px - pad_px * inward / np.linalg.norm(inward, axis=1, keepdims=True)
        mask = np.zeros((cam.height, cam.width), np.uint8)
        cv2.fillConvexPoly(mask, np.round(corners).astype(np.int32), 1)
        return mask

    band = locator_band(region(1.0), side)  # the held ring, blurred by a pixel
    return _still_in_region(parts, config, region(_HELD_PAD_CELLS * cell_px), band)


def _still_in_region(
    parts: list[np.ndarray],
    config: ReceiverConfig,
    mask: np.ndarray,
    band: np.ndarray | None = None,
) -> Detection:
    """The still path inside the blinking region ``mask``: the locator band's phase (``band``,
    by default the region's outer cell), the phase-locked image, its quadrilateral read the
    way the 'L' stands (``_oriented_quad``), refined to its edges."""
    params, cam = config.detector, config.camera
    if band is None:
        band = locator_band(mask, config.geometry.locator_side)
    rising = np.concatenate([_rising_times(p["t"], p["x"], p["y"], p["p"], band) for p in parts])
    t_start, t_end = int(parts[0]["t"][0]), int(parts[-1]["t"][-1])
    window = t_end - t_start
    burst, ratio = blink_phase(rising, t_start, window, config.blink_hz)
    if not ratio >= params.min_harmonic_ratio:
        raise MarkerNotFound(
            f"temporal: the blinking region does not pulse at {config.blink_hz:g} "
            f"Hz (harmonic ratio {ratio:.2f}); {_CHECK_BLINK}"
        )
    period = 1e6 / config.blink_hz
    img, blinks = burst_image(parts, burst, period, mask)
    lit = img > 0
    cell_px = _mask_cell_px(mask, config.geometry.locator_side)
    try:
        corners, score = _oriented_quad(lit, img, cell_px, config)
        refined = refine_corners(corners, lit, config.geometry, cam)
    except MarkerNotFound as miss:
        # The marker may have appeared within the window and lit its static rings once: the
        # pixels that blinked twice give the quadrilateral then, if the edges confirm it.
        try:
            corners, score = _oriented_quad(blinks, img, cell_px, config)
        except MarkerNotFound:
            raise miss from None
        refined = refine_corners(corners, blinks, config.geometry, cam)
        if refined is corners:
            raise miss from None
    # The burst time refers to the latest whole period inside the window.
    last = burst + np.floor((t_end - burst) / period) * period
    T = _solve_pnp(refined, config)
    return Detection(
        refined,
        T,
        t_end,
        float(last),
        config.blink_hz,
        ratio,
        score,
        np.zeros(2),
        refined=refined is not corners,
    )


def _oriented_quad(
    shaping: np.ndarray, img: np.ndarray, cell_px: float, config: ReceiverConfig
) -> tuple[np.ndarray, float]:
    """The quadrilateral of the pixels ``shaping`` (those in company: ``_in_company``), its
    corners read the way the 'L' stands in the phase-locked image ``img``, and that reading's
    score."""
    params = config.detector
    shaping = _in_company(shaping, cell_px)
    if np.count_nonzero(shaping) < 16:
        raise MarkerNotFound("spatial: too few positive events at the blink phase")
    quad = quadrilateral(outline(shaping))
    check_quadrilateral(quad, params, config.camera)
    # Which pixels fire in phase reads a sparse sensor's 'L' best, how strongly they fire a
    # blurred one's: the clearer reading decides.
    corners, score = max(
        (orient(quad, im, config.geometry) for im in (img > 0, img)), key=lambda o: o[1]
    )
    checked = get_profile(config.profile).framed
    least = params.min_checked_orientation_score if checked else params.min_still_orientation_score
    if score < least:
        raise MarkerNotFound(
            f"spatial: no inner-locator 'L' found (score {score:.2f}); check --cells"
        )
    return corners, score


_COMPANY = 0.1
"""A lit pixel shapes the still path's quadrilateral when the lit pixels in the cell around
it are at least this share of a lit pixel's median count, and two (``_in_company``)."""


def _in_company(lit: np.ndarray, cell_px: float) -> np.ndarray:
    """The pixels of ``lit`` with lit neighbours around them (``_COMPANY``).

    The quadrilateral is the hull of every lit pixel, and a noise event or two in phase
    outside the marker pulls a corner out by cells. A lit cell keeps its pixels company
    however sparse the sensor, where a stray pixel is alone; a locator corner's pixels see a
    quarter of their cell lit. A wider box would reach into the marker from the strays near
    it."""
    if not lit.any():
        return lit
    k = max(3, round(cell_px) | 1)
    count = cv2.boxFilter(lit.astype(np.float32), -1, (k, k), normalize=False)
    return lit & (count >= max(2.0, _COMPANY * np.median(count[lit])))


def _period_match(heat: np.ndarray, triplets: np.ndarray, mask: np.ndarray) -> float:
    """Mean Gaussian weight of the triplets inside ``mask``: how well their periods match the
    told blink (``DetectorParams.min_period_match``)."""
    inside = mask > 0
    return float(heat[inside].sum() / max(1, triplets[inside].sum()))


def _binned_blink(parts: list[np.ndarray], mask: np.ndarray, config: ReceiverConfig) -> bool:
    """Whether the events on 2 x 2 binned pixels inside ``mask`` match the told blink better
    than blinks two widths (``2 * sigma_frac``) slower and faster, by more than chance would
    (three standard errors of the told blink's mean weight: a weight in [0, 1] of mean m has a
    variance of at most m).

    A readout that thins the events (a rate controller, a full link) leaves a pixel a couple
    of events per blink: it misses whole bursts and times the others by whichever of their
    events survived, so its own triplets' periods spread even at the right blink. Four pixels
    together keep an event of nearly every burst. How well their periods match the told blink
    then depends on how thin the readout left them, and a display a sixth off the told rate can
    match them about as well as dense pixels match the right one: only the told blink beating
    its neighbours on the same events tells the two apart. Where each pixel is dense, binning
    mixes neighbouring cells' bursts and matches less well than the pixels themselves, so this
    is asked only where those fail."""
    cam, params = config.camera, config.detector
    if cam.width % 2 or cam.height % 2:
        return False
    binned, inside = _binned(parts, 2), mask[::2, ::2]
    off = 2 * params.sigma_frac
    maps = [
        blink_heatmap(binned, cam.width // 2, cam.height // 2, hz, params.sigma_frac)
        for hz in (config.blink_hz, config.blink_hz * (1 - off), config.blink_hz * (1 + off))
    ]
    told, slower, faster = (_period_match(heat, triplets, inside) for heat, triplets in maps)
    periods = int(maps[0][1][inside > 0].sum())  # the same triplets at every blink
    return told - max(slower, faster) > 3 * math.sqrt(told / max(periods, 1))


def _solve_pnp(corners: np.ndarray, config: ReceiverConfig) -> np.ndarray:
    world = config.geometry.locator_corners(config.marker_size_m)
    try:
        return pnp(corners, world, config.camera)
    except ValueError as exc:  # a degenerate quadrilateral
        raise MarkerNotFound(f"spatial: {exc}") from exc


def nearest_turn(found: Detection, prior: np.ndarray, config: ReceiverConfig) -> Detection:
    """``found`` with its corners in the quarter turn whose pose turns least from ``prior`` (a
    T_cam_world that read a verified frame moments before); not ``oriented`` if that is not
    the turn its 'L' gave, so the frames read through it must confirm it.

    A lock a quarter or half turn off passes the lock's checks now and then, while a hand-held
    camera turns a few degrees between a verified frame and a relock moments later."""
    turns = [np.roll(found.corners_px, -r, axis=0) for r in range(4)]
    poses = [found.T_cam_world, *(_solve_pnp(c, config) for c in turns[1:])]
    turned = Rotation.from_matrix(np.stack([T[:3, :3] for T in poses]) @ prior[:3, :3].T)
    best = int(np.argmin(turned.magnitude()))
    if best == 0:
        return found
    return replace(found, corners_px=turns[best], T_cam_world=poses[best], oriented=False)


def _locator_square(burst: CompensatedBurst, config: ReceiverConfig) -> np.ndarray:
    """(4, 2) corners, in the burst's box, of the square fitted to its locator."""
    geo = config.geometry
    # The blob's own size sets the cell size: a first guess from the box, then from its outline.
    cell_px = min(burst.box.shape) / (2 * geo.locator_side)
    for _ in range(2):
        quad = quadrilateral(locator_blob(burst.image, cell_px))
        cell_px = np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1).mean() / geo.locator_side
    fits = locator_fits(burst.image, quad, geo.locator_side, geo.ring)
    for fit in fits[:-1]:  # the likeliest that is a square seen through the camera
        try:
            check_quadrilateral(fit, config.detector, config.camera)
            return fit
        except MarkerNotFound:
            continue
    check_quadrilateral(fits[-1], config.detector, config.camera)
    return fits[-1]


def _burst_detection(
    corners: np.ndarray,
    score: float,
    burst: CompensatedBurst,
    region: BlinkRegion,
    config: ReceiverConfig,
    oriented: bool = True,
) -> Detection:
    """The detection at ``corners`` (in the burst's box, canonical order), at the burst."""
    corners = corners + np.array([burst.box.x0, burst.box.y0])
    return Detection(
        corners,
        _solve_pnp(corners, config),
        round(burst.t_us),
        burst.t_us,
        config.blink_hz,
        region.harmonic_ratio,
        score,
        burst.flow,
        oriented=oriented,
    )


def _moving_burst(
    parts: list[np.ndarray],
    tb: float,
    region: BlinkRegion,
    config: ReceiverConfig,
    flow: np.ndarray | None = None,
    most_px_per_ms: float | None = None,
) -> CompensatedBurst | None:
    """The burst at ``tb`` compensated along ``flow`` (when None, measured: ``burst_flow``, up
    to ``most_px_per_ms`` if given); None if the camera looks still there."""
    period = 1e6 / config.blink_hz
    if flow is None:
        flow = burst_flow(parts, tb, period, region.box, most_px_per_ms)
    if not np.any(flow):
        return None
    return compensated_burst(parts, tb, period, region.box, flow)


def _detect_densest(
    parts: list[np.ndarray], tb: float, region: BlinkRegion, config: ReceiverConfig
) -> Detection | None:
    """The moving path at the latest burst, read where its ON events lie densest
    (``locate.densest_burst_us``) rather than at the phase's time ``tb``, which under motion can
    miss it by a millisecond or two; None if that is ``tb`` itself, or if the blank frame after
    it is not in the window yet."""
    period = 1e6 / config.blink_hz
    tm = densest_burst_us(parts, tb, period, region.box)
    if tm == tb or tm + period / 2 + HALF_WINDOW * period > parts[-1]["t"][-1]:
        return None
    return _detect_moving(parts, tm, None, region, config)


def _detect_slow(
    parts: list[np.ndarray], tb: float, region: BlinkRegion, config: ReceiverConfig
) -> Detection | None:
    """The square of the burst compensated by the sharpest slow flow (``locate.slow_flow``),
    if it reads the 'L' clearly: the other paths' last resort when a slow drift misleads the
    flow search (or is too slow for it to call the camera moving, while it smears the still
    path's image of several blinks)."""
    params = config.detector
    slow = params.max_square_flow_px_per_ms
    burst = _moving_burst(parts, tb, region, config, most_px_per_ms=slow)
    if burst is None:
        return None  # the still path's case
    square, score = orient(_locator_square(burst, config), burst.image, config.geometry)
    if score < params.min_square_orientation_score:
        raise MarkerNotFound(f"spatial: no inner-locator 'L' found (score {score:.2f})")
    return _burst_detection(square, score, burst, region, config)


def _detect_moving(
    parts: list[np.ndarray],
    tb: float,
    flow: np.ndarray | None,
    region: BlinkRegion,
    config: ReceiverConfig,
) -> Detection | None:
    """Blob, fitted square, ring capture and "L" of the burst at ``tb`` compensated along its
    ``flow`` (measured if None), all at the burst's time; None if the burst gives no flow."""
    burst = _moving_burst(parts, tb, region, config, flow)
    if burst is None:
        return None
    params, geo = config.detector, config.geometry
    origin = np.array([burst.box.x0, burst.box.y0])
    quad = _locator_square(burst, config)
    t_us, speed = round(tb), float(np.linalg.norm(burst.flow))
    if speed <= params.max_square_flow_px_per_ms:
        square, score = orient(quad, burst.image, geo)
        if score >= params.min_square_orientation_score:
            return _burst_detection(square, score, burst, region, config)
    quad = quad + origin
    world = geo.locator_corners(config.marker_size_m)
    half = int(np.clip(1e3 / max(speed, 1e-9), 250, _CAPTURE_HALF_US))
    ring_events = to_columns(
        events_between(parts, t_us - half, t_us + half, most=_CAPTURE_SAMPLE),
        config.camera.undistort_table,
    )
    T, agree, worst = _capture_ring(ring_events, quad, t_us, burst.flow, config)
    if agree < params.min_edge_polarity or worst <= _REVERSED_SIDE:
        raise MarkerNotFound(
            f"spatial: the ring's edges fire against the motion at the fitted pose (polarity "
            f"agreement {agree:+.2f}, {worst:+.2f} on its worst side), as a fit a ring width "
            "off does"
        )
    corners = config.camera.project(world @ T[:3, :3].T + T[:3, 3])
    oriented, score = orient(corners - origin, burst.image, geo)
    clear = score >= params.min_orientation_score
    if not clear and (
        agree < params.unoriented_edge_polarity or speed > params.max_unoriented_flow_px_per_ms
    ):
        raise MarkerNotFound(
            f"spatial: no inner-locator 'L' found under motion (score {score:.2f}); check --cells"
        )
    return _burst_detection(oriented, score, burst, region, config, oriented=clear)


def _capture_ring(
    events: EventColumns, quad: np.ndarray, t_us: int, flow: np.ndarray, config: ReceiverConfig
) -> tuple[np.ndarray, float, float]:
    """The pose at ``t_us`` whose ring edges the most of ``events`` (those around ``t_us``) lie
    on, preferring poses whose edges fire as the image ``flow`` makes them (``capture_rank``),
    and its polarity agreements (overall, the worst side's). Captures start at scaled copies
    of the locator's quadrilateral (any rotation: the ring is square), and at the same a ring
    width smaller: the blob and the fitted square often take the ring's inner edge for the
    locator's outline. The quadrilateral itself and the one a ring width smaller also start a
    ring width off along either side's direction: a burst's fit lies a cell or two off under
    motion, and a capture from there settles on the edges of the rings beside the right ones."""
    xu, yu = events["xu"], events["yu"]
    geo = config.geometry
    smaller = geo.tracked_side / (geo.tracked_side + 2 * geo.ring)
    centre = quad.mean(axis=0)
    scales = _CAPTURE_SCALES + tuple(smaller * s for s in _CAPTURE_SCALES)
    starts = [centre + scale * (quad - centre) for scale in scales]
    sides = np.array([quad[1] - quad[0], quad[3] - quad[0]]) * geo.ring / geo.locator_side
    for scale in (1.0, smaller):
        start = centre + scale * (quad - centre)
        starts += [start + step for step in (*sides, *-sides)]
    best, best_key = None, None
    for start in starts:
        tracker = EdgeTracker(config, _solve_pnp(start, config), t_us)
        if not tracker.capture(xu, yu, t_us, (events["p"], flow)):
            continue
        key = capture_rank(*ring_support(tracker.T_cam_world, events, flow, config), config)
        if best_key is None or key > best_key:
            best, best_key = tracker.T_cam_world, key
    if best is None:
        raise MarkerNotFound("spatial: too few ring-edge events around the burst to fit the ring")
    return best, best_key[2], best_key[3]


def capture_rank(
    on: int, agree: float, worst: float, config: ReceiverConfig
) -> tuple[bool, int, float, float]:
    """How a ring capture ranks, from its ``ring_support``: first whether no side reads
    reversed and the edges agree with the flow (``min_edge_polarity``), then its events on
    the edges."""
    sound = worst > _REVERSED_SIDE and agree >= config.detector.min_edge_polarity
    return sound, on, agree, worst


def ring_support(
    T: np.ndarray, events: EventColumns, flow: np.ndarray, config: ReceiverConfig
) -> tuple[int, float, float]:
    """How many of ``events`` lie within ``_ON_EDGE_PX`` of a ring edge at pose ``T``, the mean
    agreement (-1..1) of their polarities with those that image ``flow`` gives them
    (``edge_polarities``; edges of unknown polarity left out), and the lowest such agreement
    of an outer edge with ``min_polarity_events`` judged events (+1 if none). A fit a ring
    width too large lies on the edges of the black ring around the white one, whose sides are
    the other way round: the truth agrees at about +1, such fits well below. A fit a ring
    width off on one side only keeps the mean up with its three others, but that side's outer
    edge reads reversed (the tracker's own test, ``EdgeTracker.reversed_edges``)."""
    edges = project_ideal(T, config.camera.K, config.geometry.tracked_edges(config.marker_size_m))
    a, b = np.ascontiguousarray(edges[:, 0]), np.ascontiguousarray(edges[:, 1])
    dist, edge = _nearest_edge(events["xu"], events["yu"], a, b, _ON_EDGE_PX)  # the tracker's
    on = dist <= _ON_EDGE_PX
    expected = edge_polarities(a, b, flow)[edge]
    judged = on & (expected != 0)
    signed = events["p"][judged] * expected[judged]
    agree = float(np.mean(signed)) if judged.any() else 0.0
    judged_edge = edge[judged]
    outer = judged_edge < 4
    count = np.bincount(judged_edge[outer], minlength=4)
    total = np.bincount(judged_edge[outer], weights=signed[outer], minlength=4)
    seen = count >= config.tracker.min_polarity_events
    worst = float((total[seen] / count[seen]).min()) if seen.any() else 1.0
    return int(np.count_nonzero(on)), agree, worst
