"""Data decoding (paper Sec. IV-D): read the cells of one data frame from its events.

For each data frame the events of the frame's own burst are taken row by row, at the time the
display's scan-out reaches that row (the clock below), in ``steps`` time slices. Each slice's
events mark an occupancy image that is unwarped onto a template by projecting template points of
the marker plane through the pose current at that slice, with the full camera model (perspective
and lens distortion: never an affine approximation). Slices are combined by logical OR (as the
paper does), the template is median filtered, and each cell reads as its share of lit template
points. The inner locator's known white and black cells set a per-frame threshold, a per-cell
confidence and a score that says whether the marker is really there.

The frame clock is re-estimated from every frame's own burst (the locator's white cells, row by
row), so neither a display/receiver clock mismatch nor the scan-out slope drifts.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.detector import ring_cells

_SAMPLES = 5
"""Template points per cell side; the inner 3 x 3 are read, the border absorbs blur."""
_HISTORY = 32
"""Frames in the clock fit: long enough to average jitter, short enough to follow drift."""


@dataclass(frozen=True)
class FrameRead:
    index: int
    """Data frames since lock."""
    t_us: int
    """Measured burst time at the middle row of the marker."""
    bits: np.ndarray
    confidence: np.ndarray
    locator_score: float
    """Contrast between the inner locator's white and black cells: ~1 seen, ~0 absent."""
    events: int


class FrameClock:
    """Burst time of data frame ``m`` at locator row ``r``: ``mid(m) + (r - n/2) * slope``."""

    def __init__(self, first_burst_us: float, frame_us: float, rows: int) -> None:
        self.nominal_us = frame_us
        self.rows = rows
        self._fit = (float(first_burst_us), float(frame_us))  # intercept, period
        self.slope_us = 0.0
        self._seen: deque[tuple[int, float]] = deque(maxlen=_HISTORY)

    def mid(self, m: int) -> float:
        return self._fit[0] + m * self._fit[1]

    def row_times(self, m: int, rows: np.ndarray) -> np.ndarray:
        return self.mid(m) + (rows - self.rows / 2) * self.slope_us

    @property
    def period_us(self) -> float:
        return self._fit[1]

    def observe(self, m: int, mid_us: float, slope_us: float) -> None:
        self._seen.append((m, mid_us))
        self.slope_us = (
            slope_us
            if not self._seen or len(self._seen) < 2
            else (0.7 * self.slope_us + 0.3 * slope_us)
        )
        if len(self._seen) >= 3:
            ms, ts = np.array(self._seen).T
            period, intercept = np.polyfit(ms, ts, 1)
            if abs(period / self.nominal_us - 1) < 0.02:
                self._fit = (intercept, period)
                return
        self._fit = (mid_us - m * self._fit[1], self._fit[1])


class CellReader:
    """Reads one data frame's cells; keeps the frame clock."""

    def __init__(self, config: ReceiverConfig, first_burst_us: float) -> None:
        self.config = config
        geo = config.geometry
        n = geo.locator_side
        self.n = n
        c = geo.cell_size_m(config.marker_size_m)
        self._lo, self._cell_m = 2 * geo.ring * c, c
        g = (np.arange(n * _SAMPLES) + 0.5) / _SAMPLES
        gx, gy = np.meshgrid(g, g)
        self._template_world = np.stack(
            [self._lo + gx * c, self._lo + gy * c, np.zeros_like(gx)], -1
        ).reshape(-1, 3)
        cells, white = ring_cells(geo)
        self._ring_cells, self._ring_white = cells, white
        # Event times relative to their row's predicted burst. The search gate finds the burst
        # before the clock is sure of it: wide when a blank refresh separates data frames, inside
        # one refresh for ``fast``. The read gate then keeps one refresh's rise only.
        r = config.refresh_us
        self._search_gate = (-0.8 * r, 1.2 * r) if config.data_every == 2 else (-0.45 * r, 0.5 * r)
        self._read_gate = (-0.35 * r, 0.6 * r)
        self.clock = FrameClock(first_burst_us, config.frame_us, n)
        self.polarities = (1,) if config.data_every == 2 else (1, -1)

    def window(self, m: int) -> tuple[int, int]:
        """Event time span needed for frame ``m``."""
        half = abs(self.clock.slope_us) * self.n / 2
        mid = self.clock.mid(m)
        return int(mid - half + self._search_gate[0]), int(mid + half + self._search_gate[1]) + 1

    def _cell_coords(self, xu, yu, T_cam_world) -> tuple[np.ndarray, np.ndarray]:
        """Locator-grid (column, row) coordinates of ideal pixels through the marker plane."""
        H = self.config.camera.K @ T_cam_world[:3, [0, 1, 3]]
        q = np.linalg.solve(H, np.stack([xu, yu, np.ones_like(xu)]).astype(np.float64))
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (q[0] / q[2] - self._lo) / self._cell_m
            v = (q[1] / q[2] - self._lo) / self._cell_m
        return u, v

    def read(
        self, m: int, ev: dict[str, np.ndarray], pose_at: Callable[[float], np.ndarray]
    ) -> FrameRead:
        """Frame ``m`` from the events ``ev`` (t, x, y, p, xu, yu) of ``window(m)``."""
        n, cam = self.n, self.config.camera
        steps = max(1, self.config.decoder.steps)
        t = ev["t"]
        edges = np.linspace(t[0], t[-1] + 1, steps + 1) if len(t) else np.zeros(steps + 1)
        step = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, steps - 1)
        poses = [pose_at(0.5 * (edges[s] + edges[s + 1])) for s in range(steps)]
        u, v = np.full(len(t), np.nan), np.full(len(t), np.nan)
        for s in range(steps):
            sel = step == s
            u[sel], v[sel] = self._cell_coords(ev["xu"][sel], ev["yu"][sel], poses[s])
        inside = (u >= 0) & (u < n) & (v >= 0) & (v < n)
        inside &= np.isin(ev["p"], self.polarities)
        col = np.where(inside, u, 0).astype(np.int64)
        row = np.where(inside, v, 0).astype(np.int64)
        self._retime(m, t, row, col, inside)
        dt = t - self.clock.row_times(m, row)
        keep = inside & (dt >= self._read_gate[0]) & (dt <= self._read_gate[1])
        template = np.zeros((n * _SAMPLES, n * _SAMPLES), np.uint8)
        for s in range(steps):
            sel = keep & (step == s)
            if not np.any(sel):
                continue
            lit = np.zeros((cam.height, cam.width), np.uint8)
            lit[ev["y"][sel], ev["x"][sel]] = 1
            pc = self._template_world @ poses[s][:3, :3].T + poses[s][:3, 3]
            px = np.rint(cam.project(pc)).astype(np.int64)
            ok = (
                (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
            )
            sampled = np.zeros(len(px), np.uint8)
            sampled[ok] = lit[px[ok, 1], px[ok, 0]]
            template |= sampled.reshape(template.shape)
        template = cv2.medianBlur(template * 255, 3) > 0
        inner = template.reshape(n, _SAMPLES, n, _SAMPLES)[:, 1:-1, :, 1:-1]
        share = inner.mean(axis=(1, 3))
        return self._classify(m, share, int(np.count_nonzero(keep)))

    def _retime(self, m: int, t, row, col, inside) -> None:
        """Fit the burst time and scan-out slope of frame ``m`` to its locator's white cells."""
        loc = self.config.geometry.inner_locator
        white = inside & loc[row, col]
        if np.count_nonzero(white) < 20:
            return
        dt = t[white] - self.clock.row_times(m, row[white])
        lo, hi = self._search_gate
        near = (dt >= lo) & (dt <= hi)
        rows = row[white][near]
        if len(rows) < 20:
            return
        # Per-row medians keep a few stray events from tilting the line.
        uniq = np.unique(rows)
        med = np.array([np.median(dt[near][rows == r]) for r in uniq])
        if len(uniq) >= 3:
            slope, offset = np.polyfit(uniq - self.n / 2, med, 1)
        else:
            slope, offset = 0.0, float(np.median(med))
        self.clock.observe(m, self.clock.mid(m) + offset, self.clock.slope_us + slope)

    def _classify(self, m: int, share: np.ndarray, events: int) -> FrameRead:
        cells = self._ring_cells
        ring = share[cells[:, 1], cells[:, 0]]
        white_ref = float(np.median(ring[self._ring_white]))
        black_ref = float(np.median(ring[~self._ring_white]))
        threshold = float(np.clip(0.5 * (white_ref + black_ref), 0.15, 0.85))
        contrast = max(white_ref - black_ref, 0.2)
        payload = share[1:-1, 1:-1]
        bits = (payload > threshold).astype(np.uint8)
        confidence = np.clip(np.abs(payload - threshold) * 2 / contrast, 0.0, 1.0)
        return FrameRead(m, int(self.clock.mid(m)), bits, confidence, white_ref - black_ref, events)
