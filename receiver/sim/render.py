"""From the screen to events: the irradiance each pixel sees over time, and its level crossings.

The scene is one plane (marker frame, z = 0): the marker's cells, the black screen around them,
and a uniform wall beyond. A sample ray hits a *region*: a cell (index >= 0), the black screen
(``SCREEN``) or the wall (``WALL``). Cells emit what the display timeline says; everything else is
constant, so a pixel that sees no cell never produces signal events.

Still camera (``StaticRenderer``): each pixel sees a fixed mix of cells. Between two switches of
its screen row, each cell's luminance is an exponential towards the new level, so the pixel's
irradiance is ``a + b_rise exp(-u / tau_rise) + b_fall exp(-u / tau_fall)``: one exponential
(solved exactly) unless rising and falling cells with different time constants share the pixel
(then sampled on a geometric ladder). A backlight PWM gates that light on and off. Only the
pixels that see cells are visited, one whole refresh at a time, and only at the refreshes where
one of their cells changes (most cells hold their light from one refresh to the next): a pixel is
touched at most once per refresh, not once per window, and the events it fires past the window
are held back by the caller.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

from eventocc.receiver.sim.display import DisplayTimeline, ScreenLayout
from eventocc.receiver.sim.sensor import (
    LAST,
    LEVEL,
    PHOTORECEPTOR_REF_NITS,
    REF,
    EventBuffer,
    PixelSink,
    cross_exponential,
    cross_linear,
    cross_relaxation,
    pixel_state,
)

SCREEN, WALL = -1, -2
_LADDER_START = 1e-3
"""First ladder step as a fraction of the faster time constant."""
_LADDER_RATIO = 1.5
_SETTLED = 12.0
"""Time constants after which a transition counts as finished."""
_FILTER_FIRST = 0.2
"""First step of the photoreceptor's ladder as a fraction of the faster time constant."""
_FILTER_RATIO = 1.5
_FILTER_SETTLED = 1e-4
"""A filtered level this close (ln units) to its pixel's light is at rest."""
SETTLED_CONTRAST = 1e-3
"""A cell whose level at a switch is within this fraction of its new target does not switch:
what is left of its transition moves a pixel's log irradiance by less than a tenth of the
smallest threshold, and skipping it spares a slow exponential (a pixel that mixes a rising and a
falling cell has no closed form)."""


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


def plane_geometry(layout: ScreenLayout) -> tuple[float, float, float, float, float]:
    """The layout as the kernels take it: (cell_m, ring, side, screen_top_m, screen_side_m)."""
    return (
        layout.cell_m,
        float(layout.ring),
        float(layout.side),
        layout.screen_top_m,
        layout.screen_side_m,
    )


@numba.njit(cache=True, inline="always")
def cell_of(px, py, geo):
    """Cell index of marker-plane point (px, py), -1 off the marker (``geo``: plane_geometry)."""
    cell_m, ring, side = geo[0], geo[1], geo[2]
    col = px / cell_m + ring
    row = py / cell_m + ring
    if col >= 0.0 and col < side and row >= 0.0 and row < side:
        return int(row) * int(side) + int(col)
    return -1


@numba.njit(cache=True, inline="always")
def region_of(px, py, geo):
    """Cell index, or SCREEN on the black screen, or WALL (also for NaN points)."""
    c = cell_of(px, py, geo)
    if c >= 0:
        return c
    top, screen = geo[3], geo[4]
    if px >= top and px < top + screen and py >= top and py < top + screen:
        return SCREEN
    return WALL


@numba.njit(cache=True)
def _regions(points, geo):
    out = np.empty(points.shape[0], np.int32)
    for j in range(points.shape[0]):
        out[j] = region_of(points[j, 0], points[j, 1], geo)
    return out


def regions(points: np.ndarray, layout: ScreenLayout) -> np.ndarray:
    """Region code (int32) of marker-plane points (..., 2); NaN points see the wall."""
    flat = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    return _regions(flat, plane_geometry(layout)).reshape(points.shape[:-1])


def screen_fraction(points: np.ndarray, layout: ScreenLayout) -> np.ndarray:
    """Screen-height fraction (0 top, 1 bottom) of marker-plane points: their scan-out delay."""
    return np.clip((points[..., 1] - layout.screen_top_m) / layout.screen_side_m, 0.0, 1.0)


@numba.njit(cache=True)
def _group_cells(region: np.ndarray, sample_weight: np.ndarray):
    """Per pixel (row of ``region``), the distinct cells its samples hit and their weights
    (the sum of ``sample_weight`` over the samples on each)."""
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
                    weights[m] += sample_weight[k]
                    found = True
                    break
            if not found:
                cells[q] = c
                weights[q] = sample_weight[k]
                q += 1
        ptr[j + 1] = q
    return ptr, cells[:q], weights[:q]


class StillPixels(NamedTuple):
    """A still camera's pixels that see cells, one entry each: the cells a pixel sees
    (``cells[ptr[j] : ptr[j + 1]]``, with the share of its footprint on each), the constant part
    of its light, its scan-out delay (screen-height fraction), and how far it is rendered (the
    next display switch to render; whether its level rests on its cells' light)."""

    ptr: np.ndarray
    cells: np.ndarray
    weights: np.ndarray
    const: np.ndarray
    scan_v: np.ndarray
    next_switch: np.ndarray
    at_rest: np.ndarray


class Refreshes(NamedTuple):
    """The display's refreshes from ``k_first`` on (a ``TimelineWindow``), indexed (refresh,
    cell): the level each cell is driven to, its level at the switch, and whether those differ
    enough for the cell to move during the refresh (``SETTLED_CONTRAST``)."""

    k_first: int
    target: np.ndarray
    at_switch: np.ndarray
    switching: np.ndarray


class StillDisplay(NamedTuple):
    """The display and photoreceptor as the still-camera kernel takes them (times in us)."""

    start_refresh: int
    """The refresh that reaches each pixel at its own scan-out delay after t = 0."""
    period: float
    scan: float
    tau_rise: float
    tau_fall: float
    pwm: tuple[float, float]
    """Backlight (period, on time); period 0: always on."""
    skip_resting: bool
    photo_k: float
    """Photoreceptor time constant times luminance; 0: no low-pass."""


@numba.njit(cache=True)
def _static_window(t1, j_start, pixels, refreshes, display, sink):
    """Events of the still-camera pixels ``j_start ..`` from their next display switch on, one
    whole refresh at a time, for every switch before ``t1`` (events may run up to a refresh
    period past ``t1``: the caller holds them back). ``refreshes.switching`` (refresh, cell):
    whether the cell's level at the switch is off its target (it moves during that refresh).
    With ``display.skip_resting``, a refresh in which none of a pixel's cells moves is rendered
    once, which puts its level exactly on their light (a transition whose tail ends on a
    threshold fires there, as when every refresh is rendered), and skipped after that
    (``at_rest``). Returns (next pixel, count): stops early, with that pixel untouched, when
    the output is full. ``display.photo_k`` > 0: the photoreceptor low-pass
    (``filtered_segment``; no backlight PWM)."""
    ptr, cells, weights, pix_const, pix_v, next_switch, at_rest = pixels
    k_first, target, at_switch, switching = refreshes
    start_refresh, period, scan, tau_rise, tau_fall, pwm, skip, photo_k = display
    state, refractory, out = sink
    n = 0
    nk = target.shape[0]
    for j in range(j_start, pix_v.shape[0]):
        if next_switch[j] >= t1:
            continue  # this pixel's light is settled or already rendered beyond t1
        saved = (state[REF, j], state[LAST, j], state[LEVEL, j], next_switch[j], at_rest[j])
        n_before = n
        while next_switch[j] < t1:
            ts = next_switch[j]
            k = start_refresh + round((ts - pix_v[j] * scan) / period)
            kk = min(max(k - k_first, 0), nk - 1)
            next_switch[j] = ts + period
            if skip:
                for q in range(ptr[j], ptr[j + 1]):
                    if switching[kk, cells[q]]:
                        at_rest[j] = False
                        break
                else:  # every cell holds its light
                    if at_rest[j]:
                        continue
                    at_rest[j] = True
            a = pix_const[j]
            b_rise = 0.0
            b_fall = 0.0
            for q in range(ptr[j], ptr[j + 1]):
                c = cells[q]
                w = weights[q]
                lum_end = target[kk, c]
                lum_start = at_switch[kk, c]
                a += w * lum_end
                if not switching[kk, c]:
                    continue
                if lum_end > lum_start:
                    if tau_rise > 0:
                        b_rise += w * (lum_start - lum_end)
                elif tau_fall > 0:
                    b_fall += w * (lum_start - lum_end)
            if photo_k > 0.0:
                n = filtered_segment(
                    ts, period, a, b_rise, tau_rise, b_fall, tau_fall, photo_k, j, state,
                    refractory, out, n,
                )  # fmt: skip
                if at_rest[j] and abs(state[LEVEL, j] - math.log(a)) > _FILTER_SETTLED:
                    at_rest[j] = False  # the photoreceptor still moves towards the light
                continue
            n = render_segment(
                ts,
                0.0,
                period,
                a,
                pix_const[j],
                b_rise,
                tau_rise,
                b_fall,
                tau_fall,
                pwm,
                j,
                state,
                refractory,
                out,
                n,
            )
        if n > out.shape[0]:
            state[REF, j], state[LAST, j], state[LEVEL, j], next_switch[j], at_rest[j] = saved
            return j, n_before
    return pix_v.shape[0], n


@numba.njit(cache=True)
def filtered_segment(
    t0, ub, a, b_rise, tau_rise, b_fall, tau_fall, photo_k, j, state, refractory, out, n
):
    """Events of pixel ``j`` over [t0, t0 + ub] after a display switch at ``t0`` when its
    photoreceptor low-passes the log irradiance ``L = ln(a + b_rise exp(-u/tau_rise) + b_fall
    exp(-u/tau_fall))`` (v2e): ``dy/du = (L - y) / tau_p`` with ``tau_p = photo_k / exp(L)``
    (the cut-off scales with the light), ``y`` starting at the pixel's level. While the light
    moves, ``y`` is stepped on a geometric ladder (exact for an input linear over each step,
    at the step's mean light) and crossed linearly between steps; once the light has settled,
    ``y`` is an exponential towards it and crossed exactly."""
    la = math.log(a)
    y = state[LEVEL, j]
    moving = b_rise != 0.0 or b_fall != 0.0
    tau_display = 1e300
    if b_rise != 0.0:
        tau_display = min(tau_display, tau_rise)
    if b_fall != 0.0:
        tau_display = min(tau_display, tau_fall)
    tau_slow = max(tau_rise if b_rise != 0.0 else 0.0, tau_fall if b_fall != 0.0 else 0.0)
    settled_at = _SETTLED * tau_slow if moving else 0.0
    lum0 = a + b_rise + b_fall
    u = 0.0
    lu = math.log(lum0)
    h = _FILTER_FIRST * min(tau_display, photo_k / max(lum0, a))
    while moving and u < min(ub, settled_at):
        un = min(u + h, ub, settled_at)
        lum = a
        if b_rise != 0.0:
            lum += b_rise * math.exp(-un / tau_rise)
        if b_fall != 0.0:
            lum += b_fall * math.exp(-un / tau_fall)
        ln = math.log(lum)
        step = un - u
        tau = photo_k / math.exp(0.5 * (lu + ln))
        g = (ln - lu) / step
        yn = ln - g * tau + (y - lu + g * tau) * math.exp(-step / tau)
        n = cross_linear(t0 + u, y, t0 + un, yn, j, state, refractory, out, n)
        u, lu, y = un, ln, yn
        h *= _FILTER_RATIO
    if u < ub:  # the light has settled at ``a``: y relaxes exponentially towards ln(a)
        tau = photo_k / a
        n = cross_relaxation(t0 + u, ub - u, y, la, tau, j, state, refractory, out, n)
        y = la + (y - la) * math.exp(-(ub - u) / tau)
    state[LEVEL, j] = y
    return n


@numba.njit(cache=True, inline="always")
def backlight(t, pwm):
    """1.0 if a backlight with ``pwm`` = (period, on time) in us is on at time t (on at the
    start of each period from t = 0; period 0: always on), else 0.0."""
    period, on = pwm
    if period <= 0.0:
        return 1.0
    return 1.0 if t - period * math.floor(t / period) < on else 0.0


@numba.njit(cache=True, inline="always")
def render_segment(
    t0,
    ua,
    ub,
    a_on,
    a_off,
    b_rise,
    tau_rise,
    b_fall,
    tau_fall,
    pwm,
    j,
    state,
    refractory,
    out,
    n,
):
    """Events of pixel ``j`` over [t0 + ua, t0 + ub] after a display switch at ``t0``: its
    irradiance is ``a_on + b_rise exp(-u/tau_rise) + b_fall exp(-u/tau_fall)`` while the
    backlight is on and ``a_off`` while it is off (the light the screen does not emit). Steps
    (the switch, backlight edges) fire at their instant; exponentials are crossed exactly."""
    period, on_us = pwm
    if period <= 0.0:
        return _lit_piece(
            t0,
            ua,
            ub,
            a_on,
            b_rise,
            tau_rise,
            b_fall,
            tau_fall,
            j,
            state,
            refractory,
            out,
            n,
        )
    cycle = math.floor((t0 + ua) / period)  # counted in whole cycles: always moves on
    while True:
        start = cycle * period - t0
        if start >= ub:
            return n
        lo, hi = max(start, ua), min(start + on_us, ub)
        if lo < hi:
            n = _lit_piece(
                t0,
                lo,
                hi,
                a_on,
                b_rise,
                tau_rise,
                b_fall,
                tau_fall,
                j,
                state,
                refractory,
                out,
                n,
            )
        lo, hi = max(start + on_us, ua), min(start + period, ub)
        if lo < hi:
            n = _step_to(
                t0 + lo,
                math.log(a_off),
                j,
                state,
                refractory,
                out,
                n,
            )
        cycle += 1


@numba.njit(cache=True, inline="always")
def _step_to(t, value, j, state, refractory, out, n):
    """An instantaneous change of pixel ``j``'s log irradiance to ``value`` at time t."""
    if value != state[LEVEL, j]:
        n = cross_linear(t, state[LEVEL, j], t, value, j, state, refractory, out, n)
        state[LEVEL, j] = value
    return n


@numba.njit(cache=True, inline="always")
def _lit_piece(
    t0,
    ua,
    ub,
    a,
    b_rise,
    tau_rise,
    b_fall,
    tau_fall,
    j,
    state,
    refractory,
    out,
    n,
):
    """``render_segment`` over [ua, ub] with the backlight on throughout."""
    lum = a + b_rise + b_fall  # at the switch itself
    if ua > 0.0:
        lum = a
        if b_rise != 0.0:
            lum += b_rise * math.exp(-ua / tau_rise)
        if b_fall != 0.0:
            lum += b_fall * math.exp(-ua / tau_fall)
    n = _step_to(t0 + ua, math.log(lum), j, state, refractory, out, n)
    if b_rise == 0.0 and b_fall == 0.0:
        return n
    if b_fall == 0.0 or b_rise == 0.0 or tau_rise == tau_fall:
        tau = tau_rise if b_rise != 0.0 else tau_fall
        return cross_exponential(t0, ua, ub, a, b_rise + b_fall, tau, j, state, refractory, out, n)
    return _cross_two_exponentials(
        t0,
        ua,
        ub,
        a,
        b_rise,
        tau_rise,
        b_fall,
        tau_fall,
        j,
        state,
        refractory,
        out,
        n,
    )


@numba.njit(cache=True)
def _cross_two_exponentials(
    t0,
    ua,
    ub,
    a,
    b1,
    tau1,
    b2,
    tau2,
    j,
    state,
    refractory,
    out,
    n,
):
    """Level crossings of ``a + b1 exp(-u/tau1) + b2 exp(-u/tau2)`` over [ua, ub], linearly
    interpolated between samples on a geometric ladder from the switch."""
    end = min(ub, _SETTLED * max(tau1, tau2))
    u_next = _LADDER_START * min(tau1, tau2)
    while u_next <= ua:
        u_next *= _LADDER_RATIO
    u, lu = ua, state[LEVEL, j]
    while u < end:
        un = min(u_next, end)
        ln = math.log(a + b1 * math.exp(-un / tau1) + b2 * math.exp(-un / tau2))
        n = cross_linear(t0 + u, lu, t0 + un, ln, j, state, refractory, out, n)
        u, lu = un, ln
        u_next *= _LADDER_RATIO
    state[LEVEL, j] = lu
    return n


@numba.njit(cache=True)
def _region_shares(region: np.ndarray, sample_weight: np.ndarray):
    """Per pixel (row of ``region``), the weight of its samples on cells, on the black screen
    and on the wall."""
    n = region.shape[0]
    cells, screen, wall = np.zeros(n), np.zeros(n), np.zeros(n)
    for j in range(n):
        for k in range(region.shape[1]):
            c = region[j, k]
            if c >= 0:
                cells[j] += sample_weight[k]
            elif c == SCREEN:
                screen[j] += sample_weight[k]
            else:
                wall[j] += sample_weight[k]
    return cells, screen, wall


_FOOTPRINT_CHUNK = 8192
"""Pixels whose sampled point-spread functions are mapped at once (bounds the memory)."""


def _weighted_footprints(
    pix_index: np.ndarray,
    points_of: Callable[[np.ndarray], np.ndarray],
    sample_weight: np.ndarray,
    layout: ScreenLayout,
    rad: Radiometry,
    dark: np.ndarray,
):
    """``StaticRenderer``'s per-pixel tables (pixels, ptr, cells, weights, constant light,
    scan-out delay) for footprints of weighted samples, pixels that see no cell left out;
    ``dark``: each pixel's (of ``pix_index``) dark floor."""
    kept, ptrs, cells, weights, const, v = [], [np.zeros(1, np.int64)], [], [], [], []
    offset = 0
    for lo in range(0, len(pix_index), _FOOTPRINT_CHUNK):
        idx = pix_index[lo : lo + _FOOTPRINT_CHUNK]
        points = points_of(idx)
        region = regions(points, layout)
        sees = (region >= 0).any(axis=1)
        region, points = region[sees], points[sees]
        ptr, c, w = _group_cells(region, sample_weight)
        kept.append(idx[sees])
        ptrs.append(ptr[1:] + offset)
        offset += len(c)
        cells.append(c)
        weights.append(w)
        on_cells, on_screen, on_wall = _region_shares(region, sample_weight)
        const.append(
            dark[lo : lo + _FOOTPRINT_CHUNK][sees]
            + rad.screen_ambient * on_cells
            + rad.screen_black * on_screen
            + rad.wall * on_wall
        )
        v.append(screen_fraction(points, layout) @ sample_weight)
    return (
        np.concatenate(kept),
        np.concatenate(ptrs),
        np.concatenate(cells) if cells else np.zeros(0, np.int32),
        np.concatenate(weights) if weights else np.zeros(0),
        np.concatenate(const) if const else np.zeros(0),
        np.concatenate(v) if v else np.zeros(0),
    )


class StaticRenderer:
    """Signal events of a still camera: each pixel's cell mix is fixed, its state compact."""

    skip_resting = True
    """Skip the refreshes in which none of a pixel's cells moves, once its level rests on their
    light (False: render every refresh of every pixel, the slow reference)."""

    def __init__(
        self,
        pix_index: np.ndarray,
        sample_points: np.ndarray | Callable[[np.ndarray], np.ndarray],
        layout: ScreenLayout,
        timeline: DisplayTimeline,
        radiometry: Radiometry,
        c_on: np.ndarray,
        c_off: np.ndarray,
        refractory_us: float,
        photoreceptor_hz: float = 0.0,
        dark: np.ndarray | None = None,
        sample_weights: np.ndarray | None = None,
    ) -> None:
        """``sample_points``: (n, S, 2) marker-plane points of each pixel's footprint samples,
        equally weighted; or, with ``sample_weights`` (S,), a function giving them for a chunk
        of ``pix_index`` (a sampled point-spread function has many samples per pixel).
        ``dark``: each pixel's (of ``pix_index``) dark floor, ``radiometry.dark`` if None."""
        dark = np.full(len(pix_index), radiometry.dark) if dark is None else dark
        if sample_weights is not None:
            assert callable(sample_points)
            self.pix_index, self.ptr, self.cells, self.weights, self.pix_const, self.pix_v = (
                _weighted_footprints(
                    pix_index, sample_points, sample_weights, layout, radiometry, dark
                )
            )
        else:
            assert not callable(sample_points)
            region = regions(sample_points, layout)
            sees_marker = (region >= 0).any(axis=1)
            region, sample_points = region[sees_marker], sample_points[sees_marker]
            self.pix_index = pix_index[sees_marker]
            s = region.shape[1]
            self.ptr, self.cells, self.weights = _group_cells(region, np.full(s, 1.0 / s))
            rad = radiometry
            # Constant part of each pixel's irradiance: reflection on its cell samples, the
            # black screen and wall it also sees, and the dark floor.
            self.pix_const = (
                dark[sees_marker]
                + rad.screen_ambient * (region >= 0).sum(1) / s
                + rad.screen_black * (region == SCREEN).sum(1) / s
                + rad.wall * (region == WALL).sum(1) / s
            )
            self.pix_v = screen_fraction(sample_points, layout).mean(axis=1)
        self.timeline = timeline
        d = timeline.display
        self._tau = (d.rise_ms * 1e3, d.fall_ms * 1e3)
        self._pwm = d.backlight_us()
        # Initial state: the screen settled on the refresh before the first one.
        first = timeline.window(timeline.start_refresh - 1, timeline.start_refresh - 1)
        lum = np.zeros(len(self.pix_index))
        np.add.at(
            lum,
            np.repeat(np.arange(len(lum)), np.diff(self.ptr)),
            self.weights * first.target[0, self.cells],
        )
        self.state = pixel_state(
            np.log(self.pix_const + lum), c_on[self.pix_index], c_off[self.pix_index]
        )
        self.refractory = float(refractory_us)
        self._photo_k = 0.0
        """Photoreceptor time constant (us) times luminance (cd/m²); 0: no low-pass."""
        if photoreceptor_hz > 0:
            if self._pwm[0] > 0:
                raise ValueError(
                    "the photoreceptor low-pass is not simulated under a PWM backlight; give "
                    "the sensor photoreceptor_hz=0 or the display pwm_hz=None"
                )
            self._photo_k = PHOTORECEPTOR_REF_NITS / (2 * math.pi * photoreceptor_hz) * 1e6
        # Refresh start_refresh reaches each pixel's screen row at its scan-out delay.
        self.next_switch = self.pix_v * d.scan_us
        self.at_rest = np.zeros(len(self.pix_index), bool)
        """Whether a pixel's level is exactly the light its cells hold (set by the first refresh
        in which none of them changes; until one does, its refreshes have nothing to render)."""
        self._pixels = StillPixels(
            self.ptr,
            self.cells,
            self.weights,
            self.pix_const,
            self.pix_v,
            self.next_switch,
            self.at_rest,
        )
        self._out = EventBuffer()

    def irradiance_now(self) -> np.ndarray:
        """Current irradiance (dark floor included) of the rendered pixels."""
        return np.exp(self.state[LEVEL])

    def window(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signal events of the display switches in [t0, t1): times (us, float; up to a refresh
        period past ``t1``), sensor pixel indices, polarities."""
        d = self.timeline.display
        tl = self.timeline
        win = tl.window(tl.refresh_at(t0, 1.0), tl.refresh_at(t1, 0.0))
        refreshes = Refreshes(
            win.k_first,
            win.target,
            win.at_switch,
            np.abs(win.at_switch - win.target) > SETTLED_CONTRAST * win.target,
        )
        display = StillDisplay(
            tl.start_refresh,
            d.period_us,
            d.scan_us,
            *self._tau,
            self._pwm,
            self.skip_resting and self._pwm[0] <= 0,  # a backlight gates resting cells too
            self._photo_k,
        )
        parts_t, parts_i, parts_p = [np.zeros(0)], [np.zeros(0, np.int64)], [np.zeros(0, np.int8)]
        j = 0
        while j < len(self.pix_index):
            out = self._out.get()
            sink = PixelSink(self.state, self.refractory, out)
            # Plain tuples: numba types a NamedTuple argument ~15 us slower per call.
            j_next, n = _static_window(
                float(t1), j, tuple(self._pixels), tuple(refreshes), tuple(display), tuple(sink)
            )
            parts_t.append(out["t"][:n].copy())
            parts_i.append(self.pix_index[out["i"][:n]])
            parts_p.append(out["p"][:n].copy())
            if j_next < len(self.pix_index):
                self._out.grow()
            j = j_next
        return np.concatenate(parts_t), np.concatenate(parts_i), np.concatenate(parts_p)
