"""Signal events of a moving camera: adaptive sub-steps, closed-form runs between them.

Each chunk is cut into sub-steps short enough that no screen point moves more than
``MAX_STEP_PX`` in the image; the poses in between are interpolated linearly. A pixel's
*footprint* is its optics sample rays (``Optics``) and its *content* at an instant is which
region (a cell, the black screen, the wall) each sample sees: a small sorted list of regions
and sample counts. Cells are convex, so a content equal at both ends of a sub-step holds
throughout it, and while it holds the pixel sees a fixed mix of cells whose light is a known
exponential per refresh: such a *run*, however many sub-steps long, is rendered in closed form
(as for a still camera), with each switch reaching the pixel when the scan-out reaches the screen
row under its centre. Only a sub-step across which the content changes is sampled: its weights
move linearly from one end's to the other's and its log irradiance is interpolated linearly
between samples (ESIM), taken at its end and, where one of its cells switches, just before the
switch, at it and on a geometric ladder after it.

The distance from the footprint's samples to the edges of their regions bounds how many
sub-steps its content stays the same, so a pixel costs a footprint per run (one ray when the
footprint lies well inside one region) instead of one per sub-step. Pixels outside the screen's
image box see the uniform wall and keep their level.

A visit to a pixel costs more than the events of one short window, so each pixel is rendered
several windows ahead (``BLOCK_US``), the pixels staggered so that every window visits an equal
share; events past the window wait for theirs.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numba
import numpy as np

from eventocc.receiver.sim.display import DisplayTimeline
from eventocc.receiver.sim.motion import Trajectory, image_box, project_points
from eventocc.receiver.sim.optics import (
    POSE_C,
    POSE_R,
    centre_rays,
    flat_poses,
    plane_point,
    rays_to_plane,
    sample_offsets,
)
from eventocc.receiver.sim.render import (
    _LADDER_RATIO,
    _LADDER_START,
    SCREEN,
    SETTLED_CONTRAST,
    WALL,
    plane_geometry,
    render_segment,
)
from eventocc.receiver.sim.sensor import (
    EVENT_OUT_DTYPE,
    LAST,
    LEVEL,
    REF,
    EventBuffer,
    PixelArray,
    PixelSink,
    cross_linear,
    pixel_state,
)

MAX_STEP_PX = 0.5
"""Largest image displacement of the screen within one sub-step (ESIM's flow-based step)."""
BLOCK_US = 40_000
"""How far ahead a pixel is rendered at each visit: a few display refreshes."""
_STAGGER_RUN = 64
"""Pixels in a row that share their block phase (neighbours in memory visited together)."""
_BOX_MARGIN_PX = 4
_SETTLED_TAU = 6.0
"""Time constants after which the ladder stops (e^-6: 0.25 % of the step left)."""
_STEP_EPS_US = 1e-3
"""Sample just before a switch, so instantaneous switches make a step at the right time."""
_MAX_POINTS = 96
_LOG_RATIO = math.log(_LADDER_RATIO)
_BOUND_SAFETY = 1.25
"""Margin on the plane-distance bounds that decide when a footprint may leave its region."""
_NO_PWM = (0.0, 0.0)


# The kernels take the screen as float tuples and one array, and the camera path as one array:
# numba charges for every array an inlined call passes (even inside a tuple), and these calls
# run per pixel and sub-step.
#   screen (geo, disp, rad), float tuples:
#   geo   ``plane_geometry`` of the layout
#   disp  (period, scan, tau_rise, tau_fall, first) in us; ``first``: the row of ``lum`` that
#         holds refresh ``start_refresh`` (the one whose scan-out starts at t = 0)
#   rad   (cell ambient, black screen, wall, dark floor) luminances; the kernels that visit
#         pixels put each one's own dark floor (``dark``, per pixel) in the last place
#   lum   (2, refreshes, cells): the level each refresh of the window drives a cell towards,
#         and its level at the switch
#   path  (sub-steps + 1, 13): T_world_cam as ``flat_poses``, then the time
_R, _C, _T = POSE_R, POSE_C, 12


# --- the light a footprint sees ------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _refresh_at(t, v, disp):
    """(refresh counted from the start, time of its switch) that screen row v shows at t."""
    period, scan = disp[0], disp[1]
    k = math.floor((t - v * scan) / period + 1e-9)  # a sample at a switch sees the new refresh
    return k, k * period + v * scan


@numba.njit(cache=True, inline="always")
def _lum_row(k, disp, lum):
    """Row of ``lum`` holding refresh k (counted from the start), clamped to the window."""
    return min(max(int(disp[4]) + k, 0), lum.shape[1] - 1)


@numba.njit(cache=True, inline="always")
def _light(regs, w0, w1, alpha, nd, kk, screen, lum):
    """Luminance of a footprint on regions ``regs[:nd]``, weights ``alpha`` of the way from
    ``w0`` to ``w1``, ``u`` after the switch to window refresh ``kk``: ``a + b_rise exp(-u /
    tau_rise) + b_fall exp(-u / tau_fall)``, returned as (a, b_rise, b_fall)."""
    _, disp, rad = screen
    tau_rise, tau_fall = disp[2], disp[3]
    ambient, black, wall, _ = rad
    a = 0.0
    b_rise = 0.0
    b_fall = 0.0
    for d in range(nd):
        w = w0[d] + alpha * (w1[d] - w0[d])
        r = regs[d]
        if r == SCREEN:
            a += w * black
        elif r == WALL:
            a += w * wall
        else:
            end, begin = lum[0, kk, r], lum[1, kk, r]
            a += w * (ambient + end)
            if abs(begin - end) <= SETTLED_CONTRAST * end:
                continue
            if end > begin:
                b_rise += w * (begin - end) if tau_rise > 0.0 else 0.0
            else:
                b_fall += w * (begin - end) if tau_fall > 0.0 else 0.0
    return a, b_rise, b_fall


@numba.njit(cache=True, inline="always")
def _log_irradiance(t, v, alpha, regs, w0, w1, nd, screen, lum):
    """Log irradiance at time t of a footprint on regions ``regs[:nd]`` with weights
    ``alpha`` of the way from ``w0`` to ``w1``; cells switch when the scan-out reaches row v."""
    _, disp, rad = screen
    tau_rise, tau_fall = disp[2], disp[3]
    k, ts = _refresh_at(t, v, disp)
    a, b_rise, b_fall = _light(regs, w0, w1, alpha, nd, _lum_row(k, disp, lum), screen, lum)
    total = rad[3] + a
    if b_rise != 0.0:
        total += b_rise * math.exp(-(t - ts) / tau_rise)
    if b_fall != 0.0:
        total += b_fall * math.exp(-(t - ts) / tau_fall)
    return math.log(total)


@numba.njit(cache=True, inline="always")
def _switching(k, regs, nd, disp, lum):
    """Whether a cell among ``regs[:nd]`` changes at refresh k (counted from the start)."""
    kk = int(disp[4]) + k
    if kk < 0 or kk >= lum.shape[1]:
        return False
    for d in range(nd):
        c = regs[d]
        if c >= 0 and abs(lum[0, kk, c] - lum[1, kk, c]) > SETTLED_CONTRAST * lum[0, kk, c]:
            return True
    return False


# --- where a footprint lies ----------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _region_and_room(px, py, geo):
    """Region of marker-plane point (px, py) (as ``region_of``) and a lower bound of its
    distance (metres) to the region's edge; NaN points (rays missing the plane) get no room."""
    if np.isnan(px) or np.isnan(py):
        return WALL, 0.0
    cell_m, ring, side, top, screen = geo[0], geo[1], geo[2], geo[3], geo[4]
    col = px / cell_m + ring
    row = py / cell_m + ring
    if col >= 0.0 and col < side and row >= 0.0 and row < side:
        fc = col - math.floor(col)
        fr = row - math.floor(row)
        room = min(min(fc, 1.0 - fc), min(fr, 1.0 - fr)) * cell_m
        return int(row) * int(side) + int(col), room
    lo, hi = -ring * cell_m, (side - ring) * cell_m
    to_marker = max(max(lo - px, px - hi), max(lo - py, py - hi))
    s_hi = top + screen
    if px >= top and px < s_hi and py >= top and py < s_hi:
        inside = min(min(px - top, s_hi - px), min(py - top, s_hi - py))
        return SCREEN, min(to_marker, inside)
    return WALL, max(max(top - px, px - s_hi), max(top - py, py - s_hi))


@numba.njit(cache=True, inline="always")
def _centre(rx, ry, path, s, geo):
    """Region, room (as ``_region_and_room``) and plane y of the centre point at step ``s``."""
    px, py = plane_point(rx, ry, path, s)
    region, room = _region_and_room(px, py, geo)
    return region, room, py


@numba.njit(cache=True, inline="always")
def _row_of(py, geo):
    """Screen-height fraction (scan-out delay) of plane height py; the top row if unknown."""
    if np.isnan(py):
        return 0.0
    return min(max((py - geo[3]) / geo[4], 0.0), 1.0)


@numba.njit(cache=True, inline="always")
def _content(rx, ry, path, s, region, room, reach, offsets, geo, regs, counts):
    """Fill ``regs``/``counts`` with the footprint's regions (ascending) and sample counts at
    step ``s``, given the centre point's ``region`` and ``room`` (``_centre``) and ``reach``, a
    bound of the samples' distance from it. Returns their number and how far (plane metres,
    along either axis) the samples may move before one can leave its region.

    The samples are placed with the ray-to-plane map linearised at the centre ray (over a
    pixel the curvature of a perspective map is ~1e-3 px) and classified in cell units, so a
    sample costs a few multiply-adds instead of a ray intersection and two divisions."""
    if room > reach:  # the whole footprint lies on the centre's region
        regs[0] = region
        counts[0] = offsets.shape[0]
        return 1, room - reach
    dx = path[s, _R] * rx + path[s, _R + 1] * ry + path[s, _R + 2]
    dy = path[s, _R + 3] * rx + path[s, _R + 4] * ry + path[s, _R + 5]
    dz = path[s, _R + 6] * rx + path[s, _R + 7] * ry + path[s, _R + 8]
    inv_dz = 1.0 / dz if dz != 0.0 else 0.0
    depth = -path[s, _C + 2] * inv_dz
    if depth <= 0.0:  # the centre ray misses the plane: the wall, as for a lost sample
        regs[0] = WALL
        counts[0] = offsets.shape[0]
        return 1, 0.0
    cell_m, ring, side, top, screen = geo[0], geo[1], geo[2], geo[3], geo[4]
    per_m = 1.0 / cell_m
    scale = depth * per_m  # plane metres -> cells
    col0 = (path[s, _C] * per_m + ring) + scale * dx
    row0 = (path[s, _C + 1] * per_m + ring) + scale * dy
    # d(plane point)/d(ray), in cells.
    fx, fy = dx * inv_dz, dy * inv_dz
    j00 = scale * (path[s, _R] - fx * path[s, _R + 6])
    j01 = scale * (path[s, _R + 1] - fx * path[s, _R + 7])
    j10 = scale * (path[s, _R + 3] - fy * path[s, _R + 6])
    j11 = scale * (path[s, _R + 4] - fy * path[s, _R + 7])
    lo = top * per_m + ring
    hi = lo + screen * per_m
    nd = 0
    free = np.inf  # in cells
    for q in range(offsets.shape[0]):
        ox, oy = offsets[q, 0], offsets[q, 1]
        col = col0 + j00 * ox + j01 * oy
        row = row0 + j10 * ox + j11 * oy
        if col >= 0.0 and col < side and row >= 0.0 and row < side:
            r = int(row) * int(side) + int(col)
            fc, fr = col - int(col), row - int(row)
            free = min(free, min(min(fc, 1.0 - fc), min(fr, 1.0 - fr)))
        elif col >= lo and col < hi and row >= lo and row < hi:
            r = SCREEN
            to_marker = max(max(-col, col - side), max(-row, row - side))
            to_edge = min(min(col - lo, hi - col), min(row - lo, hi - row))
            free = min(free, min(to_marker, to_edge))
        else:
            r = WALL
            free = min(free, max(max(lo - col, col - hi), max(lo - row, row - hi)))
        pos = 0
        while pos < nd and regs[pos] < r:
            pos += 1
        if pos < nd and regs[pos] == r:
            counts[pos] += 1.0
            continue
        for d in range(nd, pos, -1):
            regs[d], counts[d] = regs[d - 1], counts[d - 1]
        regs[pos], counts[pos] = r, 1.0
        nd += 1
    return nd, free * cell_m


@numba.njit(cache=True, inline="always")
def _same_content(regs, counts, nd_a, nd_b):
    """Whether the contents in rows 0 and 1 of ``regs``/``counts`` are equal."""
    if nd_a != nd_b:
        return False
    for d in range(nd_a):  # noqa: SIM110 (a plain loop: numba compiles it without a generator)
        if regs[0, d] != regs[1, d] or counts[0, d] != counts[1, d]:
            return False
    return True


@numba.njit(cache=True, inline="always")
def _merge(regs, counts, nd_a, nd_b, merged, w0, w1):
    """Union of the contents in rows 0 and 1 (ascending regions), with each one's weights;
    returns its size."""
    inv_s = 1.0 / counts[0, :nd_a].sum()
    a = b = nd = 0
    while a < nd_a or b < nd_b:
        ra = regs[0, a] if a < nd_a else 1 << 62
        rb = regs[1, b] if b < nd_b else 1 << 62
        r = min(ra, rb)
        merged[nd] = r
        w0[nd] = counts[0, a] * inv_s if ra == r else 0.0
        w1[nd] = counts[1, b] * inv_s if rb == r else 0.0
        a += ra == r
        b += rb == r
        nd += 1
    return nd


# --- rendering runs and sampled sub-steps ----------------------------------------------------


@numba.njit(cache=True, inline="always")
def _row_fraction(t, rx, ry, path, geo):
    """Screen-height fraction of the point under ray (rx, ry) at time t (poses interpolated)."""
    s, hi = 0, path.shape[0] - 1  # the sub-step holding t (their lengths vary by window)
    while hi - s > 1:
        mid = (s + hi) // 2
        if path[mid, _T] <= t:
            s = mid
        else:
            hi = mid
    alpha = min(max((t - path[s, _T]) / (path[s + 1, _T] - path[s, _T]), 0.0), 1.0)
    _, y0 = plane_point(rx, ry, path, s)
    _, y1 = plane_point(rx, ry, path, s + 1)
    return _row_of(y0 + alpha * (y1 - y0), geo)


@numba.njit(cache=True, error_model="numpy")
def _run(ta, tb, rx, ry, regs, counts, nd, path, screen, lum, i, state, rfr, out, n):
    """Events of pixel ``i`` (centre ray (rx, ry)) over [ta, tb] while its footprint content
    stays ``regs``/``counts``: per refresh, a jump at the switch and exponentials after it, in
    closed form. The switch reaches the pixel when the scan-out reaches the screen row under its
    centre."""
    if regs[nd - 1] < 0:  # no cell (regions ascend, cells last): the level is already there
        return n
    geo, disp, rad = screen
    period, scan, tau_rise, tau_fall = disp[0], disp[1], disp[2], disp[3]
    per_sample = 1.0 / counts[:nd].sum()
    v = _row_fraction(ta, rx, ry, path, geo)
    k = math.floor((ta - v * scan) / period)
    while True:
        ts = k * period + v * scan
        if ts >= tb:
            break
        if ts > ta:  # the row under the pixel at the switch itself
            v = _row_fraction(ts, rx, ry, path, geo)
            ts = k * period + v * scan
            if ts >= tb:
                break
        a, b_rise, b_fall = _light(
            regs, counts, counts, 0.0, nd, _lum_row(k, disp, lum), screen, lum
        )
        a = rad[3] + a * per_sample
        ub = min(tb - ts, period)
        n = render_segment(
            ts,
            max(ta - ts, 0.0),
            ub,
            a,
            a,
            b_rise * per_sample,
            tau_rise,
            b_fall * per_sample,
            tau_fall,
            _NO_PWM,
            i,
            state,
            rfr,
            out,
            n,
        )
        k += 1
    return n


@numba.njit(cache=True, error_model="numpy")
def _sampled_step(ta, tb, v, regs, w0, w1, nd, times, screen, lum, i, state, rfr, out, n):
    """Events of pixel ``i`` over the sub-step [ta, tb] while its footprint weights move from
    ``w0`` to ``w1``: log irradiance interpolated linearly between samples at the step's end
    and around the display switches of its cells (screen row v)."""
    disp = screen[1]
    period, scan, tau_rise, tau_fall = disp[0], disp[1], disp[2], disp[3]
    tau_slow = max(tau_rise, tau_fall)
    tau_fast = min(tau_rise, tau_fall) if min(tau_rise, tau_fall) > 0.0 else tau_slow
    m = 0
    # Switches more than two steps back have ladder rungs sparser than the step's own ends.
    reach = min(_SETTLED_TAU * tau_slow, 2.0 * (tb - ta))
    k = math.floor((ta - reach - v * scan) / period)
    while True:
        ts = k * period + v * scan
        if ts > tb:
            break
        if _switching(k, regs, nd, disp, lum):
            if ts - _STEP_EPS_US > ta and m < _MAX_POINTS:
                times[m] = ts - _STEP_EPS_US
                m += 1
            if ts > ta and m < _MAX_POINTS:
                times[m] = ts
                m += 1
            u = _LADDER_START * tau_fast
            if ta - ts > u:  # jump to the first rung inside the step
                u *= _LADDER_RATIO ** math.ceil(math.log((ta - ts) / u) / _LOG_RATIO)
            while u < _SETTLED_TAU * tau_slow and ts + u < tb and m < _MAX_POINTS:
                if ts + u > ta:
                    times[m] = ts + u
                    m += 1
                u *= _LADDER_RATIO
        k += 1
    _insertion_sort(times, m)  # a handful of times, mostly in order already
    t_prev = ta
    l_prev = state[LEVEL, i]
    for r in range(m + 1):
        t = times[r] if r < m else tb
        if t <= t_prev and r < m:
            continue
        lt = _log_irradiance(t, v, (t - ta) / (tb - ta), regs, w0, w1, nd, screen, lum)
        n = cross_linear(t_prev, l_prev, t, lt, i, state, rfr, out, n)
        t_prev, l_prev = t, lt
    state[LEVEL, i] = l_prev
    return n


@numba.njit(cache=True, inline="always")
def _same_light(ta, tb, v, regs, w0, w1, nd, disp, lum):
    """Whether the footprint sees the same light over [ta, tb] whether its weights are ``w0``
    or ``w1``: every region whose weight changes is a cell showing what the others show in
    each refresh reaching screen row v in that time (a sample crossing between two cells that
    show the same bits, or between the cells of the white ring)."""
    kk_a = _lum_row(_refresh_at(ta, v, disp)[0], disp, lum)
    kk_b = _lum_row(_refresh_at(tb, v, disp)[0], disp, lum)
    first = -1
    for d in range(nd):
        if w0[d] == w1[d]:
            continue
        c = regs[d]
        if c < 0:
            return False
        if first < 0:
            first = c
            continue
        for kk in range(kk_a, kk_b + 1):
            if lum[0, kk, c] != lum[0, kk, first] or lum[1, kk, c] != lum[1, kk, first]:
                return False
    return True


@numba.njit(cache=True, inline="always")
def _insertion_sort(a, m):
    for r in range(1, m):
        x = a[r]
        q = r - 1
        while q >= 0 and a[q] > x:
            a[q + 1] = a[q]
            q -= 1
        a[q + 1] = x


class Span(NamedTuple):
    """The sub-steps one call of ``_moving_window`` renders: ``path`` spans ``q`` windows from
    the start of window ``w``, window k ending at sub-step ``ends[k + 1]`` (``blocks`` = (w, q,
    last): the recording ends with window ``last``); the pixels in ``box`` (x0, x1, y0, y1)
    may see the screen. ``bounds``: (reach, step), upper bounds on the marker plane of the
    distance from a pixel's centre point to its footprint samples and of how far that point
    moves in one sub-step."""

    path: np.ndarray
    ends: np.ndarray
    blocks: tuple[int, int, int]
    box: tuple[int, int, int, int]
    bounds: tuple[float, float]


class CameraPixels(NamedTuple):
    """Every pixel of a moving camera: its centre ray (rows, columns, 2), its footprint's
    sample offsets from that ray, its dark floor and the time (us) up to which it is rendered
    (both row-major)."""

    rays: np.ndarray
    offsets: np.ndarray
    dark: np.ndarray
    done: np.ndarray


@numba.njit(cache=True, error_model="numpy")
def _moving_window(j_start, span, pixels, screen, lum, sink, closed_form):
    """Events of the pixels ``j_start ..`` of ``span.box`` over the sub-steps of ``span``. A
    pixel rendered up to ``done`` past the first window is skipped; the others are rendered to
    the end of their own block (``q`` windows, staggered by runs of pixels so that each window
    renders a ``1/q`` share) or of the recording. ``closed_form=False`` samples every sub-step
    (the reference the runs are tested against). Returns (next pixel, count), stopping early
    when the output is full."""
    path, ends, blocks, box, bounds = span
    rays, offsets, dark, done = pixels
    x0, x1, y0, y1 = box
    reach_m, step_m = bounds
    w, q, last = blocks
    geo, disp, rad = screen
    state, rfr, out = sink
    if not closed_form:
        reach_m = np.inf
    width = rays.shape[1]
    s = offsets.shape[0]
    window_end = path[ends[1], _T]
    # Contents at both ends of the sub-step in hand: row 0 its start (the run's), row 1 its end.
    regs = np.empty((2, s), np.int64)
    counts = np.empty((2, s))
    merged = np.empty(2 * s, np.int64)
    w0 = np.empty(2 * s)
    w1 = np.empty(2 * s)
    times = np.empty(_MAX_POINTS)
    n = 0
    bw = x1 - x0
    for j in range(j_start, bw * (y1 - y0)):
        y = y0 + j // bw
        x = x0 + j % bw
        i = y * width + x
        if done[i] >= window_end:
            continue
        m = ends[min(q - (w + i // _STAGGER_RUN) % q, last)]
        own = (geo, disp, (rad[0], rad[1], rad[2], dark[i]))
        saved = (state[REF, i], state[LAST, i], state[LEVEL, i])
        n_before = n
        rx, ry = rays[y, x, 0], rays[y, x, 1]
        region, room, _ = _centre(rx, ry, path, 0, geo)
        nd_a, room_a = _content(
            rx, ry, path, 0, region, room, reach_m, offsets, geo, regs[0], counts[0]
        )
        t_run = path[0, _T]
        step = 0
        while step < m:
            end = step + 1
            if closed_form and room_a >= step_m:  # no sample can leave its region before
                end = min(step + int(room_a / step_m), m)
            region, room, py_b = _centre(rx, ry, path, end, geo)
            nd_b, room_b = _content(
                rx, ry, path, end, region, room, reach_m, offsets, geo, regs[1], counts[1]
            )
            if closed_form and _same_content(regs, counts, nd_a, nd_b):
                # Each sample moves straight and is on the same region at both ends: on a
                # convex cell, all the way between (the screen margin and the wall are not
                # convex, but a sub-step is too short to cut a corner of the marker).
                step, room_a = end, room_b
                continue
            # The content changes within the last sub-step: close the run, sample the step.
            t_a, t_b = path[end - 1, _T], path[end, _T]
            if t_a > t_run:
                n = _run(
                    t_run,
                    t_a,
                    rx,
                    ry,
                    regs[0],
                    counts[0],
                    nd_a,
                    path,
                    own,
                    lum,
                    i,
                    state,
                    rfr,
                    out,
                    n,
                )
            nd = _merge(regs, counts, nd_a, nd_b, merged, w0, w1)
            v = _row_of(py_b, geo)
            if closed_form and _same_light(t_a, t_b, v, merged, w0, w1, nd, disp, lum):
                t_run = t_a  # a run of the new content from here on sees the same light
            else:
                n = _sampled_step(
                    t_a, t_b, v, merged, w0, w1, nd, times, own, lum, i, state, rfr, out, n
                )
                t_run = t_b
            regs[0, :nd_b] = regs[1, :nd_b]
            counts[0, :nd_b] = counts[1, :nd_b]
            nd_a = nd_b
            step, room_a = end, room_b
        if path[m, _T] > t_run:
            n = _run(
                t_run,
                path[m, _T],
                rx,
                ry,
                regs[0],
                counts[0],
                nd_a,
                path,
                own,
                lum,
                i,
                state,
                rfr,
                out,
                n,
            )
        if n > out.shape[0]:
            state[REF, i], state[LAST, i], state[LEVEL, i] = saved
            return j, n_before
        done[i] = path[m, _T]
    return bw * (y1 - y0), n


@numba.njit(cache=True, error_model="numpy")
def _fill_levels(path, rays, offsets, screen, lum, dark, level):
    """Log irradiance of every pixel (its own ``dark`` floor) at the path's start, without
    events (the sensor's start state)."""
    h, w = rays.shape[0], rays.shape[1]
    s = offsets.shape[0]
    geo, disp, rad = screen
    regs = np.empty(s, np.int64)
    counts = np.empty(s)
    weights = np.empty(s)
    for y in range(h):
        for x in range(w):
            rx, ry = rays[y, x, 0], rays[y, x, 1]
            _, _, py = _centre(rx, ry, path, 0, geo)
            nd, _ = _content(rx, ry, path, 0, 0, 0.0, 0.0, offsets, geo, regs, counts)
            for d in range(nd):
                weights[d] = counts[d] / s
            own = (geo, disp, (rad[0], rad[1], rad[2], dark[y * w + x]))
            level[y * w + x] = _log_irradiance(
                path[0, _T], _row_of(py, geo), 0.0, regs, weights, weights, nd, own, lum
            )


@numba.njit(cache=True)
def _by_window(events, t0, chunk_us, windows):
    """``events`` stably sorted by their window (of ``windows`` from t0; earlier ones in the
    first, later ones in the last) and the end of each window's run."""
    slot = np.empty(len(events), np.int64)
    counts = np.zeros(windows, np.int64)
    for e in range(len(events)):
        slot[e] = min(max(int((events[e].t - t0) // chunk_us), 0), windows - 1)
        counts[slot[e]] += 1
    ends = np.cumsum(counts)
    at = ends - counts
    ordered = np.empty_like(events)
    for e in range(len(events)):
        ordered[at[slot[e]]] = events[e]
        at[slot[e]] += 1
    return ordered, ends


class _Plan(NamedTuple):
    """The kernels' camera path (sub-steps from ``t_start`` to ``t_stop``, window k's ending
    at ``ends[k + 1]``), pixel box, plane bounds and screen over a span of windows."""

    t_start: int
    t_stop: int
    ends: np.ndarray
    path: np.ndarray
    box: tuple[int, int, int, int]
    bounds: tuple[float, float]
    screen: tuple
    lum: np.ndarray


class MovingRenderer:
    closed_form_runs = True
    """Render runs of unchanged footprint in closed form (False: sample every sub-step, the
    slow reference)."""

    def __init__(
        self,
        scene,
        trajectory: Trajectory,
        timeline: DisplayTimeline,
        pixels: PixelArray,
        chunk_us: int,
        duration_us: int,
        dark: np.ndarray | None = None,
    ) -> None:
        """``dark``: each pixel's dark floor (row-major), ``scene.radiometry.dark`` if None."""
        cam = scene.camera
        self.chunk_us, self.duration_us = chunk_us, duration_us
        self.blocks = max(1, round(BLOCK_US / chunk_us))
        self.camera, self.trajectory, self.timeline = cam, trajectory, timeline
        ys, xs = np.divmod(np.arange(cam.width * cam.height), cam.width)
        self.rays = centre_rays(cam, xs, ys).reshape(cam.height, cam.width, 2)
        self.offsets = sample_offsets(cam, scene.optics)
        lay, rad, d = scene.layout, scene.radiometry, timeline.display
        if d.pwm_hz is not None:
            raise ValueError(
                "backlight PWM is simulated for still cameras only; give the "
                "display pwm_hz=None to simulate a moving camera"
            )
        if scene.sensor.photoreceptor_hz > 0:
            raise ValueError(
                "the photoreceptor low-pass is simulated for still cameras only; give the "
                "sensor photoreceptor_hz=0 to simulate a moving camera (preset evk4-moving)"
            )
        self._geo = plane_geometry(lay)
        self._rad = (rad.screen_ambient, rad.screen_black, rad.wall, rad.dark)
        self.outline = lay.screen_corners()
        self.pix_index = np.arange(cam.width * cam.height)
        self.dark = np.full(cam.width * cam.height, rad.dark) if dark is None else dark
        level = np.empty(cam.width * cam.height)
        win = timeline.window(timeline.start_refresh - 1, timeline.start_refresh)
        screen, lum = self._screen(win)
        _fill_levels(
            self._path(np.zeros(2)), self.rays, self.offsets, screen, lum, self.dark, level
        )
        self.state = pixel_state(level, pixels.threshold_on, pixels.threshold_off)
        self.done = np.zeros(cam.width * cam.height)
        """Time (us) up to which each pixel is rendered."""
        self._pixels = CameraPixels(self.rays, self.offsets, self.dark, self.done)
        self.refractory = float(scene.sensor.refractory_us)
        self._out = EventBuffer()
        self._ahead: deque[list[np.ndarray]] = deque()
        """Events rendered past the window last asked for, by window from the next one."""
        self._plan: _Plan | None = None

    def irradiance_now(self) -> np.ndarray:
        return np.exp(self.state[LEVEL])

    def substeps(self, t0: float, t1: float, windows: int) -> tuple[np.ndarray, np.ndarray]:
        """Step boundaries in [t0, t1], equal within each of its ``windows`` equal parts and
        keeping the screen's image motion per step small there, and the index of the boundary
        that ends each part (and of t0 first)."""
        probe = np.linspace(t0, t1, 8 * windows + 1)
        px = project_points(self.camera, self.trajectory.pose_at(probe), self.outline)
        travel = np.linalg.norm(np.diff(px, axis=0), axis=2).max(axis=1)
        steps = np.maximum(1, np.ceil(travel.reshape(windows, 8).sum(axis=1) / MAX_STEP_PX))
        bounds = np.linspace(t0, t1, windows + 1)
        t_steps = np.concatenate(
            [
                np.linspace(a, b, int(k), endpoint=False)
                for a, b, k in zip(bounds[:-1], bounds[1:], steps, strict=True)
            ]
            + [[t1]]
        )
        return t_steps, np.concatenate([[0], np.cumsum(steps)]).astype(np.int64)

    def window(self, t0: int, t1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signal events in [t0, t1], the next window of ``chunk_us``: times (us, float), sensor
        pixel indices, polarities. Each pixel is rendered ``blocks`` windows at a time (the
        visit, footprint and light of a pixel cost more than a window's events), its events
        past ``t1`` held back."""
        if t0 % self.chunk_us or t1 - t0 > self.chunk_us:
            raise ValueError(f"[{t0}, {t1}] is not one window of {self.chunk_us} us")
        q = self.blocks
        plan = self._plan
        if plan is None or t0 + q * self.chunk_us > plan.t_stop:
            plan = self._plan = self._make_plan(t0)
        k = (t0 - plan.t_start) // self.chunk_us
        span = Span(
            path=plan.path[plan.ends[k] : plan.ends[k + q] + 1],
            ends=plan.ends[k : k + q + 1] - plan.ends[k],
            blocks=(t0 // self.chunk_us, q, -(-(self.duration_us - t0) // self.chunk_us)),
            box=plan.box,
            bounds=plan.bounds,
        )
        parts = [np.empty(0, EVENT_OUT_DTYPE)]  # the box is empty when the screen is out of view
        j, total = 0, (plan.box[1] - plan.box[0]) * (plan.box[3] - plan.box[2])
        while j < total:
            out = self._out.get()
            j_next, n = _moving_window(  # plain tuples: numba types a NamedTuple slower
                j,
                tuple(span),
                tuple(self._pixels),
                plan.screen,
                plan.lum,
                tuple(PixelSink(self.state, self.refractory, out)),
                self.closed_form_runs,
            )
            parts.append(out[:n].copy())
            if j_next < total:
                self._out.grow()
            j = j_next
        events = self._hold_back(np.concatenate(parts), t0)
        return events["t"], events["i"], events["p"]

    def _hold_back(self, events: np.ndarray, t0: int) -> np.ndarray:
        """The events of window ``t0`` (the new ``events`` and those held back before); the new
        ones of later windows are held back, sorted into their windows."""
        ordered, ends = _by_window(events, t0, self.chunk_us, self.blocks)
        groups = np.split(ordered, ends[:-1])
        now = np.concatenate([*self._ahead.popleft(), groups[0]]) if self._ahead else groups[0]
        self._ahead.extend([] for _ in range(self.blocks - 1 - len(self._ahead)))
        for held, group in zip(self._ahead, groups[1:], strict=True):
            held.append(group)
        return now

    def _make_plan(self, t0: int) -> _Plan:
        """What the windows from ``t0`` need of the camera path and the screen, for two
        blocks' worth of windows (planning costs more Python than a window's kernel call)."""
        tl, d, windows = self.timeline, self.timeline.display, 2 * self.blocks
        t_steps, ends = self.substeps(t0, t0 + windows * self.chunk_us, windows)
        T = self.trajectory.pose_at(t_steps)
        settle_us = _SETTLED_TAU * max(d.rise_ms, d.fall_ms) * 1e3
        screen, lum = self._screen(
            tl.window(tl.refresh_at(t0 - settle_us, 1.0), tl.refresh_at(t_steps[-1], 0.0))
        )
        return _Plan(
            t_start=t0,
            t_stop=int(t_steps[-1]),
            ends=ends,
            path=self._path(t_steps, T),
            box=image_box(self.camera, T, self.outline, _BOX_MARGIN_PX + 0.02 * self.camera.width),
            bounds=self._plane_bounds(T),
            screen=screen,
            lum=lum,
        )

    def _path(self, t_steps: np.ndarray, T: np.ndarray | None = None) -> np.ndarray:
        """The kernels' camera path at ``t_steps`` (poses ``T`` there, if known already)."""
        T = self.trajectory.pose_at(t_steps) if T is None else T
        return np.column_stack([flat_poses(T), t_steps])

    def _screen(self, win) -> tuple[tuple, np.ndarray]:
        """``screen`` and ``lum`` (see the kernels' conventions) of a timeline window."""
        d = self.timeline.display
        first = float(self.timeline.start_refresh - win.k_first)
        disp = (d.period_us, d.scan_us, d.rise_ms * 1e3, d.fall_ms * 1e3, first)
        return (self._geo, disp, self._rad), np.stack([win.target, win.at_switch])

    def _plane_bounds(self, T: np.ndarray) -> tuple[float, float]:
        """Upper bounds, on the marker plane, of how far a pixel's footprint samples lie from its
        centre point along either plane axis (regions are axis-aligned boxes, so that is the
        distance that matters) and of how far that point moves in one sub-step, with a safety
        factor for lens distortion and for the variation over the screen (the bounds are taken
        at its corners, where the view is most oblique and distant, at the start, middle and end
        of the path)."""
        px = project_points(self.camera, T, self.outline)  # (steps, 4, 2)
        step_px = float(np.linalg.norm(np.diff(px, axis=0), axis=2).max(initial=0.0))
        K = self.camera.K
        m_per_px = reach_m = 0.0
        probes = [0, len(T) // 2, -1]
        for Ti, corners in zip(T[probes], px[probes], strict=True):
            rays = (corners - K[:2, 2]) / K[[0, 1], [0, 1]]
            centre = rays_to_plane(rays, Ti)
            for shift in np.eye(2):
                moved = rays_to_plane(rays + shift / K[[0, 1], [0, 1]], Ti)
                m_per_px = max(
                    m_per_px, float(np.nanmax(np.linalg.norm(moved - centre, axis=1), initial=0.0))
                )
            samples = rays_to_plane(rays[:, None, :] + self.offsets[None], Ti)
            reach_m = max(reach_m, float(np.nanmax(np.abs(samples - centre[:, None]), initial=0)))
        if not m_per_px > 0:  # the screen is (partly) behind the camera: sample every pixel
            return math.inf, 1.0
        return _BOUND_SAFETY * reach_m, max(_BOUND_SAFETY * m_per_px * step_px, 1e-9)
