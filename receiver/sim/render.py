"""From the screen to events: the irradiance each pixel sees over time, and its level crossings.

The scene is one plane (marker frame, z = 0): the marker's cells, the black screen around them,
and a uniform wall beyond. A sample ray hits a *region*: a cell (index >= 0), the black screen
(``SCREEN``) or the wall (``WALL``). Cells emit what the display timeline says; everything else is
constant, so a pixel that sees no cell never produces signal events.

Still camera (``StaticRenderer``): each pixel sees a fixed mix of cells. Between two switches of
its screen row, each cell's luminance is an exponential towards the new level, so the pixel's
irradiance is ``a + b_rise exp(-u / tau_rise) + b_fall exp(-u / tau_fall)``: one exponential
(solved exactly) unless rising and falling cells with different time constants share the pixel
(then sampled on a geometric ladder). Only the pixels that see cells are visited.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from receiver.sim.display import DisplayTimeline, ScreenLayout
from receiver.sim.sensor import cross_exponential, cross_linear

SCREEN, WALL = -1, -2
_LADDER_START = 1e-3
"""First ladder step as a fraction of the faster time constant."""
_LADDER_RATIO = 1.5
_SETTLED = 12.0
"""Time constants after which a transition counts as finished."""


@dataclass(frozen=True)
class Radiometry:
    """Constant luminances of the scene (cd/m²) and the sensor's dark floor."""

    screen_ambient: float
    """Ambient light reflected by the panel, added to every screen pixel."""
    screen_black: float
    """Black screen around the marker: emitted black level plus reflection."""
    wall: float
    dark: float
    white: float
    """A white cell, reflection included: the scale of relative intensities."""


def regions(points: np.ndarray, layout: ScreenLayout) -> np.ndarray:
    """Region code (int32) of marker-plane points (..., 2); NaN points see the wall."""
    col = points[..., 0] / layout.cell_m + layout.ring
    row = points[..., 1] / layout.cell_m + layout.ring
    lo, hi = layout.screen_top_m, layout.screen_top_m + layout.screen_side_m
    inside_screen = ((points[..., 0] >= lo) & (points[..., 0] < hi)
                     & (points[..., 1] >= lo) & (points[..., 1] < hi))
    in_marker = (col >= 0) & (col < layout.side) & (row >= 0) & (row < layout.side)
    cell = (np.floor(np.where(in_marker, row, 0)) * layout.side
            + np.floor(np.where(in_marker, col, 0))).astype(np.int32)
    return np.where(in_marker, cell, np.where(inside_screen, SCREEN, WALL)).astype(np.int32)


def screen_fraction(points: np.ndarray, layout: ScreenLayout) -> np.ndarray:
    """Screen-height fraction (0 top, 1 bottom) of marker-plane points: their scan-out delay."""
    return np.clip((points[..., 1] - layout.screen_top_m) / layout.screen_side_m, 0.0, 1.0)


@numba.njit(cache=True)
def _group_cells(region: np.ndarray):
    """Per pixel (row of ``region``), the distinct cells its samples hit and their weights."""
    n, s = region.shape
    ptr = np.zeros(n + 1, np.int64)
    cells = np.empty(n * s, np.int32)
    weights = np.empty(n * s, np.float64)
    q = 0
    for j in range(n):
        for k in range(s):
            c = region[j, k]
            if c < 0:
                continue
            found = False
            for m in range(ptr[j], q):
                if cells[m] == c:
                    weights[m] += 1.0 / s
                    found = True
                    break
            if not found:
                cells[q] = c
                weights[q] = 1.0 / s
                q += 1
        ptr[j + 1] = q
    return ptr, cells[:q], weights[:q]


@numba.njit(cache=True)
def _static_window(t0, t1, j_start, pix_index, pix_v, pix_const, ptr, cells, weights,
                   k_first, target, at_switch, start_refresh, period, scan, tau_rise, tau_fall,
                   level, ref, last, c_on, c_off, refractory, out_t, out_i, out_p):
    """Events of the still-camera pixels ``j_start ..`` in [t0, t1). Returns (next pixel, count):
    stops early, with that pixel untouched, when the output is full."""
    n = 0
    nk = target.shape[0]
    tau_slow = max(tau_rise, tau_fall)
    for j in range(j_start, pix_index.shape[0]):
        saved = (ref[j], last[j], level[j])
        n_before = n
        v = pix_v[j]
        k = start_refresh + math.floor((t0 - v * scan) / period)
        while True:
            ts = (k - start_refresh) * period + v * scan
            if ts >= t1:
                break
            kk = min(max(k - k_first, 0), nk - 1)
            a = pix_const[j]
            b_rise = 0.0
            b_fall = 0.0
            for q in range(ptr[j], ptr[j + 1]):
                c = cells[q]
                w = weights[q]
                lum_end = target[kk, c]
                lum_start = at_switch[kk, c]
                a += w * lum_end
                if abs(lum_start - lum_end) <= 1e-9 * lum_end:
                    continue
                if lum_end > lum_start:
                    if tau_rise > 0:
                        b_rise += w * (lum_start - lum_end)
                elif tau_fall > 0:
                    b_fall += w * (lum_start - lum_end)
            ua = max(t0 - ts, 0.0)
            ub = min(t1 - ts, period)
            if ua == 0.0:  # the switch itself: a step where the response is instantaneous
                jump = math.log(a + b_rise + b_fall)
                if jump != level[j]:
                    n = cross_linear(ts, level[j], ts, jump, j, ref, last, c_on, c_off,
                                     refractory, out_t, out_i, out_p, n)
                    level[j] = jump
            if (b_rise != 0.0 or b_fall != 0.0) and ua < _SETTLED * tau_slow:
                if b_fall == 0.0 or b_rise == 0.0 or tau_rise == tau_fall:
                    tau = tau_rise if b_rise != 0.0 else tau_fall
                    n, level[j] = cross_exponential(ts, ua, ub, a, b_rise + b_fall, tau, j, ref,
                                                    last, c_on, c_off, refractory,
                                                    out_t, out_i, out_p, n)
                else:
                    n = _cross_two_exponentials(ts, ua, ub, a, b_rise, tau_rise, b_fall,
                                                tau_fall, j, level, ref, last, c_on, c_off,
                                                refractory, out_t, out_i, out_p, n)
            k += 1
        if n > out_t.shape[0]:
            ref[j], last[j], level[j] = saved
            return j, n_before
    return pix_index.shape[0], n


@numba.njit(cache=True)
def _cross_two_exponentials(t0, ua, ub, a, b1, tau1, b2, tau2, j, level, ref, last, c_on,
                            c_off, refractory, out_t, out_i, out_p, n):
    """Level crossings of ``a + b1 exp(-u/tau1) + b2 exp(-u/tau2)`` over [ua, ub], linearly
    interpolated between samples on a geometric ladder from the switch."""
    end = min(ub, _SETTLED * max(tau1, tau2))
    u_next = _LADDER_START * min(tau1, tau2)
    while u_next <= ua:
        u_next *= _LADDER_RATIO
    u, lu = ua, level[j]
    while u < end:
        un = min(u_next, end)
        ln = math.log(a + b1 * math.exp(-un / tau1) + b2 * math.exp(-un / tau2))
        n = cross_linear(t0 + u, lu, t0 + un, ln, j, ref, last, c_on, c_off, refractory,
                         out_t, out_i, out_p, n)
        u, lu = un, ln
        u_next *= _LADDER_RATIO
    level[j] = lu
    return n


class StaticRenderer:
    """Signal events of a still camera: each pixel's cell mix is fixed, its state compact."""

    def __init__(self, pix_index: np.ndarray, sample_points: np.ndarray, layout: ScreenLayout,
                 timeline: DisplayTimeline, radiometry: Radiometry, c_on: np.ndarray,
                 c_off: np.ndarray, refractory_us: float) -> None:
        region = regions(sample_points, layout)
        sees_marker = (region >= 0).any(axis=1)
        region, sample_points = region[sees_marker], sample_points[sees_marker]
        self.pix_index = pix_index[sees_marker]
        self.ptr, self.cells, self.weights = _group_cells(region)
        s = region.shape[1]
        rad = radiometry
        # Constant part of each pixel's irradiance: reflection on its cell samples, the black
        # screen and wall it also sees, and the dark floor.
        self.pix_const = (rad.dark + rad.screen_ambient * (region >= 0).sum(1) / s
                          + rad.screen_black * (region == SCREEN).sum(1) / s
                          + rad.wall * (region == WALL).sum(1) / s)
        self.pix_v = screen_fraction(sample_points, layout).mean(axis=1)
        self.timeline = timeline
        self.c_on, self.c_off = c_on[self.pix_index], c_off[self.pix_index]
        self.refractory = float(refractory_us)
        d = timeline.display
        self._tau = (d.rise_ms * 1e3, d.fall_ms * 1e3)
        # Initial state: the screen settled on the refresh before the first one.
        first = timeline.window(timeline.start_refresh - 1, timeline.start_refresh - 1)
        lum = np.zeros(len(self.pix_index))
        np.add.at(lum, np.repeat(np.arange(len(lum)), np.diff(self.ptr)),
                  self.weights * first.target[0, self.cells])
        self.level = np.log(self.pix_const + lum)
        self.ref = self.level.copy()
        self.last = np.full(len(lum), -np.inf)
        self._capacity = 1 << 20

    def irradiance_now(self) -> np.ndarray:
        """Current irradiance (dark floor included) of the rendered pixels."""
        return np.exp(self.level)

    def window(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signal events in [t0, t1): times (us, float), sensor pixel indices, polarities."""
        d = self.timeline.display
        tl = self.timeline
        win = tl.window(tl.refresh_at(t0, 1.0), tl.refresh_at(t1, 0.0))
        parts_t, parts_i, parts_p = [np.zeros(0)], [np.zeros(0, np.int64)], [np.zeros(0, np.int8)]
        j = 0
        while j < len(self.pix_index):
            out_t = np.empty(self._capacity)
            out_i = np.empty(self._capacity, np.int32)
            out_p = np.empty(self._capacity, np.int8)
            j_next, n = _static_window(
                float(t0), float(t1), j, self.pix_index, self.pix_v, self.pix_const, self.ptr,
                self.cells, self.weights, win.k_first, win.target, win.at_switch,
                tl.start_refresh, d.period_us, d.scan_us, *self._tau, self.level, self.ref,
                self.last, self.c_on, self.c_off, self.refractory, out_t, out_i, out_p)
            parts_t.append(out_t[:n])
            parts_i.append(self.pix_index[out_i[:n]])
            parts_p.append(out_p[:n])
            if j_next < len(self.pix_index):
                self._capacity *= 2
            j = j_next
        return np.concatenate(parts_t), np.concatenate(parts_i), np.concatenate(parts_p)
