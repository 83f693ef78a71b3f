"""Signal events of a moving camera: adaptive sub-steps over the screen's image only.

Each chunk is cut into sub-steps short enough that no screen point moves more than
``MAX_STEP_PX`` in the image. Within a sub-step, every pixel inside the screen's image bounding
box evaluates its footprint at the step's end (sample points interpolated linearly between the two
poses) and, where one of its cells is switching, at the switch instant and on a geometric ladder
after it, so display transitions keep their exact timing under motion. Log intensity is
interpolated linearly between those samples (ESIM). Pixels outside the box see the uniform wall
and keep their level.
"""

from __future__ import annotations

import itertools
import math

import numba
import numpy as np

from receiver.sim.display import DisplayTimeline
from receiver.sim.motion import Trajectory, project_points
from receiver.sim.optics import centre_rays, sample_offsets
from receiver.sim.render import _LADDER_RATIO, _LADDER_START
from receiver.sim.sensor import PixelArray, cross_linear

MAX_STEP_PX = 0.5
"""Largest image displacement of the screen within one sub-step (ESIM's flow-based step)."""
_BOX_MARGIN_PX = 4
_SETTLED_TAU = 6.0
"""Time constants after which the ladder stops (e^-6: 0.25 % of the step left)."""
_STEP_EPS_US = 1e-3
"""Sample just before a switch, so instantaneous switches make a step at the right time."""
_MAX_POINTS = 96


@numba.njit(cache=True, inline="always")
def _plane(rx, ry, R, C):
    dx = R[0, 0] * rx + R[0, 1] * ry + R[0, 2]
    dy = R[1, 0] * rx + R[1, 1] * ry + R[1, 2]
    dz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]
    s = -C[2] / dz if dz != 0.0 else -1.0
    if s <= 0.0:
        return np.nan, np.nan
    return C[0] + s * dx, C[1] + s * dy


@numba.njit(cache=True, inline="always")
def _cell_of(px, py, geo):
    cell_m, ring, side = geo[0], geo[1], geo[2]
    col = px / cell_m + ring
    row = py / cell_m + ring
    if col >= 0.0 and col < side and row >= 0.0 and row < side:
        return int(row) * int(side) + int(col)
    return -1


@numba.njit(cache=True, inline="always")
def _region(px, py, geo):
    """Cell index, or -1 on the black screen, or -2 on the wall (also for NaN points)."""
    c = _cell_of(px, py, geo)
    if c >= 0:
        return c
    top, screen = geo[3], geo[4]
    if px >= top and px < top + screen and py >= top and py < top + screen:
        return -1
    return -2


@numba.njit(cache=True)
def _luminance(px, py, t, geo, disp, rad, k_first, target, at_switch):
    """Luminance (cd/m²) of marker-plane point (px, py) at time t."""
    top, screen = geo[3], geo[4]
    c = _cell_of(px, py, geo)
    if c < 0:
        if px >= top and px < top + screen and py >= top and py < top + screen:
            return rad[1]
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
def _log_irradiance(alpha, t, p0, p1, geo, disp, rad, k_first, target, at_switch):
    total = 0.0
    s = p0.shape[0]
    for q in range(s):
        px = p0[q, 0] + alpha * (p1[q, 0] - p0[q, 0])
        py = p0[q, 1] + alpha * (p1[q, 1] - p0[q, 1])
        total += _luminance(px, py, t, geo, disp, rad, k_first, target, at_switch)
    return math.log(rad[3] + total / s)


@numba.njit(cache=True)
def _switching(p, k, geo, k_first, target, at_switch):
    """Whether any footprint sample at points ``p`` lies on a cell changing at refresh k."""
    kk = int(k - k_first)
    if kk < 0 or kk >= target.shape[0]:
        return False
    for q in range(p.shape[0]):
        c = _cell_of(p[q, 0], p[q, 1], geo)
        if c >= 0 and abs(target[kk, c] - at_switch[kk, c]) > 1e-9 * target[kk, c]:
            return True
    return False


@numba.njit(cache=True)
def _moving_step(ta, tb, box, j_start, Ra, Ca, Rb, Cb, rays, offsets, geo, disp, rad,
                 k_first, target, at_switch, level, ref, last, c_on, c_off, refractory,
                 out_t, out_i, out_p):
    """Events of the pixels ``j_start ..`` of ``box`` (x0, x1, y0, y1) in the sub-step
    [ta, tb]. Returns (next pixel, count), stopping early when the output is full."""
    x0, x1, y0, y1 = box
    width = rays.shape[1]
    s = offsets.shape[0]
    p0 = np.empty((s, 2))
    p1 = np.empty((s, 2))
    times = np.empty(_MAX_POINTS)
    start, period, scan, tau_rise, tau_fall = disp
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
        uniform = True
        first = -3
        for q in range(s):
            rx = rays[y, x, 0] + offsets[q, 0]
            ry = rays[y, x, 1] + offsets[q, 1]
            p0[q, 0], p0[q, 1] = _plane(rx, ry, Ra, Ca)
            p1[q, 0], p1[q, 1] = _plane(rx, ry, Rb, Cb)
            if uniform:
                r0 = _region(p0[q, 0], p0[q, 1], geo)
                if first == -3:
                    first = r0
                uniform = r0 == first and _region(p1[q, 0], p1[q, 1], geo) == first
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
        if uniform and m == 0:
            continue  # one steady region under the whole footprint: nothing changes
        pts = np.sort(times[:m])
        t_prev = ta
        l_prev = level[i]
        for r in range(m + 1):
            t = pts[r] if r < m else tb
            if t <= t_prev and r < m:
                continue
            lt = _log_irradiance((t - ta) / (tb - ta), t, p0, p1, geo, disp, rad, k_first,
                                 target, at_switch)
            n = cross_linear(t_prev, l_prev, t, lt, i, ref, last, c_on, c_off, refractory,
                             out_t, out_i, out_p, n)
            t_prev, l_prev = t, lt
        level[i] = l_prev
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
    for y in range(h):
        for x in range(w):
            for q in range(s):
                p[q, 0], p[q, 1] = _plane(rays[y, x, 0] + offsets[q, 0],
                                          rays[y, x, 1] + offsets[q, 1], R, C)
            level[y * w + x] = _log_irradiance(0.0, t, p, p, geo, disp, rad, k_first, target,
                                               at_switch)


class MovingRenderer:
    def __init__(self, scene, trajectory: Trajectory, timeline: DisplayTimeline,
                 pixels: PixelArray) -> None:
        cam = scene.camera
        self.camera, self.trajectory, self.timeline = cam, trajectory, timeline
        ys, xs = np.divmod(np.arange(cam.width * cam.height), cam.width)
        self.rays = centre_rays(cam, xs, ys).reshape(cam.height, cam.width, 2)
        self.offsets = sample_offsets(cam, scene.optics)
        lay, rad, d = scene.layout, scene.radiometry, timeline.display
        self.geo = (lay.cell_m, float(lay.ring), float(lay.side), lay.screen_top_m,
                    lay.screen_side_m)
        self.disp = (float(timeline.start_refresh), d.period_us, d.scan_us, d.rise_ms * 1e3,
                     d.fall_ms * 1e3)
        self.rad = (rad.screen_ambient, rad.screen_black, rad.wall, rad.dark)
        self.outline = lay.screen_corners()
        self.c_on, self.c_off = pixels.threshold_on, pixels.threshold_off
        self.refractory = float(scene.sensor.refractory_us)
        self.pix_index = np.arange(cam.width * cam.height)
        self.level = np.empty(cam.width * cam.height)
        T0 = trajectory.pose_at(np.zeros(1))[0]
        win = timeline.window(timeline.start_refresh - 1, timeline.start_refresh)
        _fill_levels(0.0, T0[:3, :3], T0[:3, 3], self.rays, self.offsets, self.geo, self.disp,
                     self.rad, win.k_first, win.target, win.at_switch, self.level)
        self.ref = self.level.copy()
        self.last = np.full(cam.width * cam.height, -np.inf)
        self._capacity = 1 << 20

    def irradiance_now(self) -> np.ndarray:
        return np.exp(self.level)

    def _box(self, Ta: np.ndarray, Tb: np.ndarray) -> tuple[int, int, int, int]:
        px = project_points(self.camera, np.stack([Ta, Tb]), self.outline).reshape(-1, 2)
        margin = _BOX_MARGIN_PX + 0.02 * self.camera.width
        x0 = int(np.clip(np.floor(px[:, 0].min() - margin), 0, self.camera.width))
        x1 = int(np.clip(np.ceil(px[:, 0].max() + margin), 0, self.camera.width))
        y0 = int(np.clip(np.floor(px[:, 1].min() - margin), 0, self.camera.height))
        y1 = int(np.clip(np.ceil(px[:, 1].max() + margin), 0, self.camera.height))
        return x0, max(x0, x1), y0, max(y0, y1)

    def substeps(self, t0: float, t1: float) -> np.ndarray:
        """Step boundaries in [t0, t1] keeping the screen's image motion per step small."""
        probe = np.linspace(t0, t1, 9)
        px = project_points(self.camera, self.trajectory.pose_at(probe), self.outline)
        travel = np.linalg.norm(np.diff(px, axis=0), axis=2).max(axis=1).sum()
        steps = max(1, math.ceil(travel / MAX_STEP_PX))
        return np.linspace(t0, t1, steps + 1)

    def window(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        bounds = self.substeps(t0, t1)
        for ta, tb in itertools.pairwise(bounds):
            parts.extend(self._step(float(ta), float(tb)))
        if not parts:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int8)
        return tuple(np.concatenate(c) for c in zip(*parts, strict=True))

    def _step(self, ta: float, tb: float) -> list:
        tl, d = self.timeline, self.timeline.display
        Ta, Tb = self.trajectory.pose_at(np.array([ta, tb]))
        box = self._box(Ta, Tb)
        settle_us = _SETTLED_TAU * max(d.rise_ms, d.fall_ms) * 1e3
        win = tl.window(tl.refresh_at(ta - settle_us, 1.0), tl.refresh_at(tb, 0.0))
        out = []
        j, total = 0, (box[1] - box[0]) * (box[3] - box[2])
        while j < total:
            out_t = np.empty(self._capacity)
            out_i = np.empty(self._capacity, np.int64)
            out_p = np.empty(self._capacity, np.int8)
            j_next, n = _moving_step(
                ta, tb, box, j, Ta[:3, :3], Ta[:3, 3], Tb[:3, :3],
                Tb[:3, 3], self.rays, self.offsets, self.geo, self.disp, self.rad, win.k_first,
                win.target, win.at_switch, self.level, self.ref, self.last, self.c_on,
                self.c_off, self.refractory, out_t, out_i, out_p)
            out.append((out_t[:n], out_i[:n], out_p[:n]))
            if j_next < total:
                self._capacity *= 2
            j = j_next
        return out
