"""Edge tracking (paper Sec. IV-C): event clusters on the 8 static edges of the white ring drive
asynchronous pose updates.

Each event (ideal pixel coordinates) joins every edge within the gate; an edge is cut into
``alpha * length`` bins that each keep their newest event, so a cluster stays spread along its
edge. An edge's latency indicator is the mean distance of its cluster; when more than one edge's
indicator exceeds half the gate, the pose is re-solved (``pose.refine_pose``), the edges are
re-projected and the clusters re-binned, dropping events now beyond the gate or too old.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.pose import project_ideal, refine_pose

_MIN_FILL = 0.25
"""An edge's indicator counts only once this share of its bins holds events (noise alone rarely
fills a cluster)."""
_MIN_EDGES = 4
"""Edges with enough fresh events for a pose solve: four lines fix a plane's pose."""


@numba.njit(cache=True, nogil=True)
def _assign(
    xu, yu, t, start, a, b, gate, cap, sx, sy, st, sd, sum_d, n_valid, earliest_update_us, min_fill
):
    """Add events ``start..`` to the clusters; stop after the first event that makes more than
    one indicator exceed half its gate. Returns (index to resume from, whether it stopped)."""
    for i in range(start, t.shape[0]):
        px, py = xu[i], yu[i]
        for e in range(a.shape[0]):
            dx, dy = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
            L2 = dx * dx + dy * dy
            w = ((px - a[e, 0]) * dx + (py - a[e, 1]) * dy) / L2 if L2 > 0 else 0.0
            w = min(max(w, 0.0), 1.0)
            ex, ey = a[e, 0] + w * dx - px, a[e, 1] + w * dy - py
            d = np.sqrt(ex * ex + ey * ey)
            if d > gate[e]:
                continue
            s = min(int(w * cap[e]), cap[e] - 1)
            if st[e, s] >= 0:
                sum_d[e] -= sd[e, s]
            else:
                n_valid[e] += 1
            sx[e, s], sy[e, s], st[e, s], sd[e, s] = px, py, t[i], d
            sum_d[e] += d
        if t[i] >= earliest_update_us:
            late = 0
            for e in range(a.shape[0]):
                if (
                    n_valid[e] >= max(3, min_fill * cap[e])
                    and sum_d[e] > 0.5 * gate[e] * n_valid[e]
                ):
                    late += 1
            if late > 1:
                return i + 1, True
    return t.shape[0], False


@dataclass
class TrackUpdate:
    t_us: int
    T_cam_world: np.ndarray
    cost: float
    support: int


class EdgeTracker:
    """Clusters + pose for one tracking session (created at each (re-)detection)."""

    def __init__(self, config: ReceiverConfig, T_cam_world: np.ndarray) -> None:
        self.config = config
        geo = config.geometry
        self.edges_world = geo.tracked_edges(config.marker_size_m)
        self._ring_m = geo.ring * geo.cell_size_m(config.marker_size_m)
        self.K = config.camera.K
        self.T_cam_world = T_cam_world
        self.last_update_us = -(1 << 62)
        self._last_rebin_us = 0
        self._slots = None
        self._rebin(T_cam_world, now_us=0)

    # --- geometry of the current pose ----------------------------------------------------------
    def _project_edges(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px = project_ideal(T, self.K, self.edges_world)  # (8, 2, 2)
        return np.ascontiguousarray(px[:, 0]), np.ascontiguousarray(px[:, 1])

    def _gates(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """theta_d, narrowed where the ring is thin in the image so that the blinking inner
        locator (one ring width inside the inner edges) never feeds a cluster."""
        length = np.linalg.norm(b - a, axis=1)
        ring_px = (
            length
            * self._ring_m
            / np.linalg.norm(self.edges_world[:, 1] - self.edges_world[:, 0], axis=1)
        )
        share = np.where(np.arange(len(a)) < 4, 0.45, 0.3)  # inner edges: 1 ring from the locator
        return np.minimum(self.config.tracker.gate_px, share * ring_px)

    def _rebin(self, T: np.ndarray, now_us: int) -> None:
        a, b = self._project_edges(T)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise ValueError("marker behind the camera")
        cap = np.maximum(3, (self.config.tracker.alpha * np.linalg.norm(b - a, axis=1))).astype(
            np.int64
        )
        width = int(cap.max())
        old = self._slots
        sx, sy = np.zeros((8, width)), np.zeros((8, width))
        st, sd = np.full((8, width), -1, np.int64), np.zeros((8, width))
        self._slots = (sx, sy, st, sd, np.zeros(8), np.zeros(8, np.int64))
        self._a, self._b, self._gate, self._cap = a, b, self._gates(a, b), cap
        self._last_rebin_us = now_us
        if old is None:
            return
        valid = old[2] >= max(0, now_us - self.config.tracker.max_age_us)
        order = np.argsort(old[2][valid], kind="stable")  # oldest first: newest wins its bin
        ex, ey, et = old[0][valid][order], old[1][valid][order], old[2][valid][order]
        for e in range(8):  # re-assign per edge so an event keeps only the edge it was on
            on = np.nonzero(valid)[0][order] == e
            if np.any(on):
                _assign(
                    ex[on],
                    ey[on],
                    et[on],
                    0,
                    a[e : e + 1],
                    b[e : e + 1],
                    self._gate[e : e + 1],
                    cap[e : e + 1],
                    sx[e : e + 1],
                    sy[e : e + 1],
                    st[e : e + 1],
                    sd[e : e + 1],
                    self._slots[4][e : e + 1],
                    self._slots[5][e : e + 1],
                    1 << 62,
                    _MIN_FILL,
                )

    # --- streaming -----------------------------------------------------------------------------
    def push(self, xu: np.ndarray, yu: np.ndarray, t: np.ndarray) -> list[TrackUpdate]:
        """Feed events (ideal pixels, time-sorted); returns the pose updates they triggered."""
        updates = []
        start = 0
        q = self.config.tracker
        while start < len(t):
            sx, sy, st, sd, sum_d, n_valid = self._slots
            stop, due = _assign(
                xu,
                yu,
                t,
                start,
                self._a,
                self._b,
                self._gate,
                self._cap,
                sx,
                sy,
                st,
                sd,
                sum_d,
                n_valid,
                self.last_update_us + q.min_update_interval_us,
                _MIN_FILL,
            )
            now = int(t[stop - 1])
            if due:
                update = self._update(now)
                if update is not None:
                    updates.append(update)
            elif now - self._last_rebin_us >= q.max_age_us // 2:
                self._rebin(self.T_cam_world, now)  # age stale slots out of the indicators
            start = stop
        return updates

    def _update(self, now_us: int) -> TrackUpdate | None:
        """Re-solve the pose, unless too few edges hold fresh events (sensor noise alone must not
        move a camera that stands still)."""
        sx, sy, st, _, _, _ = self._slots
        fresh = st >= now_us - self.config.tracker.max_age_us
        supported = fresh.sum(axis=1) >= np.maximum(3, _MIN_FILL * self._cap)
        if supported.sum() < _MIN_EDGES:
            self.last_update_us = now_us
            self._rebin(self.T_cam_world, now_us)
            return None
        edge = np.nonzero(fresh)[0]
        pts = np.stack([sx[fresh], sy[fresh]], 1)
        T, cost = refine_pose(
            self.T_cam_world,
            self.K,
            pts,
            edge,
            self.edges_world,
            self.config.tracker.huber_px,
            self.config.tracker.max_iterations,
        )
        self.T_cam_world = T
        self.last_update_us = now_us
        self._rebin(T, now_us)
        return TrackUpdate(now_us, T, cost, len(edge))
