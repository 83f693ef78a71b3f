"""Signal events of a moving camera: adaptive sub-steps over the screen's image only.

Each chunk is cut into sub-steps short enough that no screen point moves more than
``MAX_STEP_PX`` in the image, and one compiled pass renders every pixel of the screen's image box
through all of them. A pixel whose whole footprint stays on one region (a cell, the black screen,
the wall) for several sub-steps sees that region's light only: the display transitions of a cell
are exponentials solved in closed form (as for a still camera, with the scan-out delay of the
screen row under the pixel at the switch), so such runs cost one look-up per refresh. A pixel
whose footprint meets a region boundary is sampled: its footprint at the sub-step's end (sample
points interpolated linearly between the two poses) and, where one of its cells is switching, at
the switch instant and on a geometric ladder after it. Log intensity is interpolated linearly
between those samples (ESIM). Pixels outside the box see the uniform wall and keep their level.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from receiver.sim.display import DisplayTimeline
from receiver.sim.motion import Trajectory, image_box, project_points
from receiver.sim.optics import centre_rays, plane_point, rays_to_plane, sample_offsets
from receiver.sim.render import (
    _LADDER_RATIO,
    _LADDER_START,
    SCREEN,
    WALL,
    cell_of,
    plane_geometry,
    region_of,
    render_segment,
)
from receiver.sim.sensor import EventBuffer, PixelArray, cross_linear

MAX_STEP_PX = 0.5
"""Largest image displacement of the screen within one sub-step (ESIM's flow-based step)."""
_BOX_MARGIN_PX = 4
_SETTLED_TAU = 6.0
"""Time constants after which the ladder stops (e^-6: 0.25 % of the step left)."""
_STEP_EPS_US = 1e-3
"""Sample just before a switch, so instantaneous switches make a step at the right time."""
_MAX_POINTS = 96
_BOUND_SAFETY = 1.25
"""Margin on the plane-distance bounds that decide when a footprint may leave its region."""
_NO_PWM = (0.0, 0.0)


@numba.njit(cache=True)
def _luminance(px, py, t, geo, disp, rad, k_first, target, at_switch):
    """Luminance (cd/m²) of marker-plane point (px, py) at time t."""
    top, screen = geo[3], geo[4]
    c = region_of(px, py, geo)
    if c == SCREEN:
        return rad[1]
    if c == WALL:
        return rad[2]
    start, period, scan, tau_rise, tau_fall = disp
    v = min(max((py - top) / screen, 0.0), 1.0)
    k = start + math.floor((t - v * scan) / period)
    kk = min(max(int(k - k_first), 0), target.shape[0] - 1)
    u = t - ((k - start) * period + v * scan)
    end = target[kk, c]
    begin = at_switch[kk, c]
    tau = tau_rise if end > begin else tau_fall
    lum = end if tau == 0.0 else end + (begin - end) * math.exp(-u / tau)
    return lum + rad[0]


@numba.njit(cache=True)
def _log_irradiance(alpha, t, p0, p1, geo, disp, rad, k_first, target, at_switch, seen):
    """Log irradiance of a footprint whose samples are interpolated ``alpha`` of the way from
    ``p0`` to ``p1``. Each distinct region is evaluated once, at its first sample (the scan-out
    delay across one footprint is tens of microseconds); ``seen`` is (S, 3) scratch."""
    s = p0.shape[0]
    distinct = 0
    for q in range(s):
        px = p0[q, 0] + alpha * (p1[q, 0] - p0[q, 0])
        py = p0[q, 1] + alpha * (p1[q, 1] - p0[q, 1])
        r = region_of(px, py, geo)
        for d in range(distinct + 1):
            if d == distinct:
                seen[d, 0] = r
                seen[d, 1] = 1.0
                seen[d, 2] = _luminance(px, py, t, geo, disp, rad, k_first, target, at_switch)
                distinct += 1
                break
            if seen[d, 0] == r:
                seen[d, 1] += 1.0
                break
    total = 0.0
    for d in range(distinct):
        total += seen[d, 1] * seen[d, 2]
    return math.log(rad[3] + total / s)


@numba.njit(cache=True)
def _switching(p, k, geo, k_first, target, at_switch):
    """Whether any footprint sample at points ``p`` lies on a cell changing at refresh k."""
    kk = int(k - k_first)
    if kk < 0 or kk >= target.shape[0]:
        return False
    for q in range(p.shape[0]):
        c = cell_of(p[q, 0], p[q, 1], geo)
        if c >= 0 and abs(target[kk, c] - at_switch[kk, c]) > 1e-9 * target[kk, c]:
            return True
    return False


@numba.njit(cache=True, inline="always")
def _region_and_room(px, py, geo):
    """Region of marker-plane point (px, py) (as ``_region``) and a lower bound of its distance
    (metres) to the region's edge; NaN points (rays missing the plane) get no room."""
    if np.isnan(px) or np.isnan(py):
        return -2, 0.0
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
        return -1, min(to_marker, inside)
    return -2, max(max(top - px, px - s_hi), max(top - py, py - s_hi))


@numba.njit(cache=True, inline="always")
def _region_under(rx, ry, R, C, geo):
    """``_region_and_room`` of the marker-plane point under ray (rx, ry) from pose (R, C)."""
    px, py = plane_point(rx, ry, R, C)
    return _region_and_room(px, py, geo)


@numba.njit(cache=True)
def _cell_run(
    ta,
    tb,
    c,
    i,
    rx,
    ry,
    t_steps,
    Rs,
    Cs,
    geo,
    disp,
    rad,
    k_first,
    target,
    at_switch,
    level,
    ref,
    last,
    c_on,
    c_off,
    refractory,
    out_t,
    out_i,
    out_p,
    n,
):
    """Events of pixel ``i`` (centre ray (rx, ry)) over [ta, tb] while its whole footprint sees
    cell ``c``: per refresh, a jump at the switch and an exponential after it, both exact. The
    switch reaches the pixel when the scan-out reaches the screen row under its centre."""
    top, screen = geo[3], geo[4]
    start, period, scan, tau_rise, tau_fall = disp[0], disp[1], disp[2], disp[3], disp[4]
    base = rad[0] + rad[3]  # panel reflection and dark floor
    m = t_steps.shape[0] - 1
    dt = (t_steps[m] - t_steps[0]) / m
    v = _row_fraction(ta, rx, ry, t_steps, dt, Rs, Cs, top, screen)
    k = int(start) + math.floor((ta - v * scan) / period)
    while True:
        ts = (k - start) * period + v * scan
        if ts >= tb:
            break
        if ts > ta:  # the row under the pixel at the switch itself
            v = _row_fraction(ts, rx, ry, t_steps, dt, Rs, Cs, top, screen)
            ts = (k - start) * period + v * scan
            if ts >= tb:
                break
        kk = min(max(k - k_first, 0), target.shape[0] - 1)
        end = target[kk, c]
        begin = at_switch[kk, c]
        tau = tau_rise if end > begin else tau_fall
        b = begin - end if tau > 0.0 else 0.0
        ub = min(tb - ts, period)
        n = render_segment(
            ts,
            max(ta - ts, 0.0),
            ub,
            base + end,
            base,
            b,
            tau,
            0.0,
            tau,
            _NO_PWM,
            i,
            level,
            ref,
            last,
            c_on,
            c_off,
            refractory,
            out_t,
            out_i,
            out_p,
            n,
        )
        k += 1
    return n


@numba.njit(cache=True, inline="always")
def _row_fraction(t, rx, ry, t_steps, dt, Rs, Cs, top, screen):
    """Screen-height fraction of the point under ray (rx, ry) at time t (poses interpolated)."""
    m = t_steps.shape[0] - 1
    s = min(max(int((t - t_steps[0]) / dt), 0), m - 1)
    alpha = min(max((t - t_steps[s]) / dt, 0.0), 1.0)
    _, y0 = plane_point(rx, ry, Rs[s], Cs[s])
    _, y1 = plane_point(rx, ry, Rs[s + 1], Cs[s + 1])
    y = y0 + alpha * (y1 - y0)
    if np.isnan(y):
        return 0.0
    return min(max((y - top) / screen, 0.0), 1.0)


@numba.njit(cache=True)
def _sampled_step(
    ta,
    tb,
    i,
    p0,
    p1,
    geo,
    disp,
    rad,
    k_first,
    target,
    at_switch,
    tau_fast,
    tau_slow,
    times,
    seen,
    level,
    ref,
    last,
    c_on,
    c_off,
    refractory,
    out_t,
    out_i,
    out_p,
    n,
):
    """Events of pixel ``i`` over the sub-step [ta, tb] from its footprint samples at both ends
    (``p0``, ``p1``), adding samples at the display switches of its cells."""
    start, period, scan = disp[0], disp[1], disp[2]
    s = p0.shape[0]
    # Sample times: display switches of the cells under this pixel, then the step's end.
    m = 0
    cy = p1[s // 2, 1]
    if not np.isnan(cy):
        v = min(max((cy - geo[3]) / geo[4], 0.0), 1.0)
        k = int(start) + math.floor((ta - _SETTLED_TAU * tau_slow - v * scan) / period)
        while True:
            ts = (k - start) * period + v * scan
            if ts > tb:
                break
            if _switching(p1, k, geo, k_first, target, at_switch):
                if ts - _STEP_EPS_US > ta and m < _MAX_POINTS:
                    times[m] = ts - _STEP_EPS_US
                    m += 1
                if ts > ta and m < _MAX_POINTS:
                    times[m] = ts
                    m += 1
                u = _LADDER_START * tau_fast
                while u < _SETTLED_TAU * tau_slow and ts + u < tb and m < _MAX_POINTS:
                    if ts + u > ta:
                        times[m] = ts + u
                        m += 1
                    u *= _LADDER_RATIO
            k += 1
    # Backlight edges: steps at their instant, like instantaneous switches.
    _insertion_sort(times, m)  # a handful of times, mostly in order already
    t_prev = ta
    l_prev = level[i]
    for r in range(m + 1):
        t = times[r] if r < m else tb
        if t <= t_prev and r < m:
            continue
        lt = _log_irradiance(
            (t - ta) / (tb - ta), t, p0, p1, geo, disp, rad, k_first, target, at_switch, seen
        )
        n = cross_linear(
            t_prev, l_prev, t, lt, i, ref, last, c_on, c_off, refractory, out_t, out_i, out_p, n
        )
        t_prev, l_prev = t, lt
    level[i] = l_prev
    return n


@numba.njit(cache=True, inline="always")
def _insertion_sort(a, m):
    for r in range(1, m):
        x = a[r]
        q = r - 1
        while q >= 0 and a[q] > x:
            a[q + 1] = a[q]
            q -= 1
        a[q + 1] = x


@numba.njit(cache=True, inline="always")
def _common_region(p0, p1, geo):
    """The region all footprint samples lie on at both ends of a sub-step, or -3 if several."""
    first = region_of(p0[0, 0], p0[0, 1], geo)
    for q in range(p0.shape[0]):
        if (
            region_of(p0[q, 0], p0[q, 1], geo) != first
            or region_of(p1[q, 0], p1[q, 1], geo) != first
        ):
            return -3
    return first


@numba.njit(cache=True)
def _moving_window(
    t_steps,
    Rs,
    Cs,
    box,
    j_start,
    reach_m,
    step_m,
    rays,
    offsets,
    geo,
    disp,
    rad,
    k_first,
    target,
    at_switch,
    level,
    ref,
    last,
    c_on,
    c_off,
    refractory,
    out_t,
    out_i,
    out_p,
):
    """Events of the pixels ``j_start ..`` of ``box`` (x0, x1, y0, y1) over the sub-steps
    ``t_steps`` (poses ``Rs``, ``Cs``). ``reach_m`` bounds the distance on the marker plane from
    a pixel's centre point to its footprint samples, ``step_m`` how far that point moves in one
    sub-step. Returns (next pixel, count), stopping early when the output is full."""
    x0, x1, y0, y1 = box
    width = rays.shape[1]
    s = offsets.shape[0]
    m = t_steps.shape[0] - 1
    p0 = np.empty((s, 2))
    p1 = np.empty((s, 2))
    times = np.empty(_MAX_POINTS)
    seen = np.empty((s, 3))
    tau_rise, tau_fall = disp[3], disp[4]
    tau_fast = min(tau_rise, tau_fall) if min(tau_rise, tau_fall) > 0 else max(tau_rise, tau_fall)
    tau_slow = max(tau_rise, tau_fall)
    n = 0
    bw = x1 - x0
    for j in range(j_start, bw * (y1 - y0)):
        y = y0 + j // bw
        x = x0 + j % bw
        i = y * width + x
        saved = (ref[i], last[i], level[i])
        n_before = n
        rx, ry = rays[y, x, 0], rays[y, x, 1]
        step = 0
        sampled_up_to = -1
        region, room = _region_under(rx, ry, Rs[0], Cs[0], geo)
        while step < m:
            safe = int((room - reach_m) / step_m) if room > reach_m else 0
            if safe >= 1:  # the footprint stays on one region for ``safe`` sub-steps
                end = min(step + safe, m)
                if region >= 0:
                    n = _cell_run(
                        t_steps[step],
                        t_steps[end],
                        region,
                        i,
                        rx,
                        ry,
                        t_steps,
                        Rs,
                        Cs,
                        geo,
                        disp,
                        rad,
                        k_first,
                        target,
                        at_switch,
                        level,
                        ref,
                        last,
                        c_on,
                        c_off,
                        refractory,
                        out_t,
                        out_i,
                        out_p,
                        n,
                    )
                step = end
                if step < m:
                    region, room = _region_under(rx, ry, Rs[step], Cs[step], geo)
                continue
            # Both ends of this sub-step with room for the footprint on the same (convex) cell:
            # the samples in between are on it too.
            region_b, room_b = _region_under(rx, ry, Rs[step + 1], Cs[step + 1], geo)
            if region_b == region and min(room, room_b) > reach_m:
                if region >= 0:
                    n = _cell_run(
                        t_steps[step],
                        t_steps[step + 1],
                        region,
                        i,
                        rx,
                        ry,
                        t_steps,
                        Rs,
                        Cs,
                        geo,
                        disp,
                        rad,
                        k_first,
                        target,
                        at_switch,
                        level,
                        ref,
                        last,
                        c_on,
                        c_off,
                        refractory,
                        out_t,
                        out_i,
                        out_p,
                        n,
                    )
                step += 1
                room = room_b
                continue
            for q in range(s):
                if sampled_up_to == step:  # the previous sub-step ended where this one starts
                    p0[q, 0], p0[q, 1] = p1[q, 0], p1[q, 1]
                else:
                    p0[q, 0], p0[q, 1] = plane_point(
                        rx + offsets[q, 0], ry + offsets[q, 1], Rs[step], Cs[step]
                    )
                p1[q, 0], p1[q, 1] = plane_point(
                    rx + offsets[q, 0], ry + offsets[q, 1], Rs[step + 1], Cs[step + 1]
                )
            region = _common_region(p0, p1, geo)
            if region >= 0:  # on one cell after all: its light alone, in closed form
                n = _cell_run(
                    t_steps[step],
                    t_steps[step + 1],
                    region,
                    i,
                    rx,
                    ry,
                    t_steps,
                    Rs,
                    Cs,
                    geo,
                    disp,
                    rad,
                    k_first,
                    target,
                    at_switch,
                    level,
                    ref,
                    last,
                    c_on,
                    c_off,
                    refractory,
                    out_t,
                    out_i,
                    out_p,
                    n,
                )
            elif region == -3:
                n = _sampled_step(
                    t_steps[step],
                    t_steps[step + 1],
                    i,
                    p0,
                    p1,
                    geo,
                    disp,
                    rad,
                    k_first,
                    target,
                    at_switch,
                    tau_fast,
                    tau_slow,
                    times,
                    seen,
                    level,
                    ref,
                    last,
                    c_on,
                    c_off,
                    refractory,
                    out_t,
                    out_i,
                    out_p,
                    n,
                )
            step += 1
            sampled_up_to = step
            region, room = region_b, room_b
        if n > out_t.shape[0]:
            ref[i], last[i], level[i] = saved
            return j, n_before
    return bw * (y1 - y0), n


@numba.njit(cache=True)
def _fill_levels(t, R, C, rays, offsets, geo, disp, rad, k_first, target, at_switch, level):
    """Log irradiance of every pixel at time t, without events (the sensor's start state)."""
    h, w = rays.shape[0], rays.shape[1]
    s = offsets.shape[0]
    p = np.empty((s, 2))
    seen = np.empty((s, 3))
    for y in range(h):
        for x in range(w):
            for q in range(s):
                p[q, 0], p[q, 1] = plane_point(
                    rays[y, x, 0] + offsets[q, 0], rays[y, x, 1] + offsets[q, 1], R, C
                )
            level[y * w + x] = _log_irradiance(
                0.0, t, p, p, geo, disp, rad, k_first, target, at_switch, seen
            )


class MovingRenderer:
    def __init__(
        self, scene, trajectory: Trajectory, timeline: DisplayTimeline, pixels: PixelArray
    ) -> None:
        cam = scene.camera
        self.camera, self.trajectory, self.timeline = cam, trajectory, timeline
        ys, xs = np.divmod(np.arange(cam.width * cam.height), cam.width)
        self.rays = centre_rays(cam, xs, ys).reshape(cam.height, cam.width, 2)
        self.offsets = sample_offsets(cam, scene.optics)
        lay, rad, d = scene.layout, scene.radiometry, timeline.display
        self.geo = plane_geometry(lay)
        if d.pwm_hz is not None:
            raise ValueError(
                "backlight PWM is simulated for still cameras only; give the "
                "display pwm_hz=None to simulate a moving camera"
            )
        self.disp = (
            float(timeline.start_refresh),
            d.period_us,
            d.scan_us,
            d.rise_ms * 1e3,
            d.fall_ms * 1e3,
        )
        self.rad = (rad.screen_ambient, rad.screen_black, rad.wall, rad.dark)
        self.outline = lay.screen_corners()
        self.c_on, self.c_off = pixels.threshold_on, pixels.threshold_off
        self.refractory = float(scene.sensor.refractory_us)
        self.pix_index = np.arange(cam.width * cam.height)
        self.level = np.empty(cam.width * cam.height)
        T0 = trajectory.pose_at(np.zeros(1))[0]
        win = timeline.window(timeline.start_refresh - 1, timeline.start_refresh)
        _fill_levels(
            0.0,
            T0[:3, :3],
            T0[:3, 3],
            self.rays,
            self.offsets,
            self.geo,
            self.disp,
            self.rad,
            win.k_first,
            win.target,
            win.at_switch,
            self.level,
        )
        self.ref = self.level.copy()
        self.last = np.full(cam.width * cam.height, -np.inf)
        self._out = EventBuffer()

    def irradiance_now(self) -> np.ndarray:
        return np.exp(self.level)

    def substeps(self, t0: float, t1: float) -> np.ndarray:
        """Step boundaries in [t0, t1] keeping the screen's image motion per step small."""
        probe = np.linspace(t0, t1, 9)
        px = project_points(self.camera, self.trajectory.pose_at(probe), self.outline)
        travel = np.linalg.norm(np.diff(px, axis=0), axis=2).max(axis=1).sum()
        steps = max(1, math.ceil(travel / MAX_STEP_PX))
        return np.linspace(t0, t1, steps + 1)

    def window(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signal events in [t0, t1]: times (us, float), sensor pixel indices, polarities."""
        tl, d = self.timeline, self.timeline.display
        t_steps = self.substeps(t0, t1)
        T = self.trajectory.pose_at(t_steps)
        box = image_box(self.camera, T, self.outline, _BOX_MARGIN_PX + 0.02 * self.camera.width)
        reach_m, step_m = self._plane_bounds(T)
        settle_us = _SETTLED_TAU * max(d.rise_ms, d.fall_ms) * 1e3
        win = tl.window(tl.refresh_at(t0 - settle_us, 1.0), tl.refresh_at(t1, 0.0))
        Rs, Cs = np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3])
        parts = []
        j, total = 0, (box[1] - box[0]) * (box[3] - box[2])
        while j < total:
            out_t, out_i, out_p = self._out.get()
            j_next, n = _moving_window(
                t_steps,
                Rs,
                Cs,
                box,
                j,
                reach_m,
                step_m,
                self.rays,
                self.offsets,
                self.geo,
                self.disp,
                self.rad,
                win.k_first,
                win.target,
                win.at_switch,
                self.level,
                self.ref,
                self.last,
                self.c_on,
                self.c_off,
                self.refractory,
                out_t,
                out_i,
                out_p,
            )
            parts.append((out_t[:n].copy(), out_i[:n].copy(), out_p[:n].copy()))
            if j_next < total:
                self._out.grow()
            j = j_next
        if not parts:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int8)
        return tuple(np.concatenate(c) for c in zip(*parts, strict=True))

    def _plane_bounds(self, T: np.ndarray) -> tuple[float, float]:
        """Upper bounds, on the marker plane, of a pixel footprint's reach from its centre
        point and of that point's travel in one sub-step, with a safety factor for lens
        distortion and for the variation over the screen (the bounds are taken at its corners,
        where the view is most oblique and distant)."""
        px = project_points(self.camera, T, self.outline)  # (steps, 4, 2)
        step_px = float(np.linalg.norm(np.diff(px, axis=0), axis=2).max(initial=0.0))
        K = self.camera.K
        m_per_px = 0.0
        for Ti, corners in zip(T[[0, -1]], px[[0, -1]], strict=True):
            rays = (corners - K[:2, 2]) / K[[0, 1], [0, 1]]
            centre = rays_to_plane(rays, Ti)
            for shift in np.eye(2):
                moved = rays_to_plane(rays + shift / K[[0, 1], [0, 1]], Ti)
                m_per_px = max(
                    m_per_px, float(np.nanmax(np.linalg.norm(moved - centre, axis=1), initial=0.0))
                )
        if not m_per_px > 0:  # the screen is (partly) behind the camera: sample every pixel
            return math.inf, 1.0
        reach_px = float(np.linalg.norm(self.offsets * K[[0, 1], [0, 1]], axis=1).max())
        scale = _BOUND_SAFETY * m_per_px
        return scale * reach_px, max(scale * step_px, 1e-9)
