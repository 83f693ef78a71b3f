"""What a receiver tells the closed loop about each frame it reads: the measurements the
transmitter's ``auto`` mode chooses its settings from (``eventocc.occ.link_policy``).

Per frame: whether its code and CRC passed, the share of its cells the Reed-Solomon code
corrected (BER before FEC, measured on the frames that passed, whose corrected bits are known
right), pixels per cell at the tracked pose, the event rate against the camera's readout, the
marker's image speed (from the tracked poses) and the receiver's real-time margin (event time
processed per second of its own).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.receiver import FrameOutput, PoseEstimate

FLOW_SPAN_US = 20_000
"""Poses this far apart give the marker's image speed (shorter spans see the pose jitter)."""
MARGIN_SPAN_S = 1.0
"""The real-time margin is measured over about this much of the receiver's own time."""


@dataclass(frozen=True)
class FrameQuality:
    passed: bool
    ber_before_fec: float | None
    px_per_cell: float | None
    readout_share: float | None
    flow_px_per_ms: float | None
    realtime_margin: float | None


class FlowMeter:
    """The marker centre's image speed, from the receiver's poses."""

    def __init__(self, camera: CameraModel, marker_size_m: float) -> None:
        self.K = camera.K
        self.centre = np.array([marker_size_m / 2, marker_size_m / 2, 0.0, 1.0])
        self._points: deque[tuple[int, np.ndarray]] = deque()
        self.px_per_ms: float | None = None

    def add(self, pose: PoseEstimate) -> None:
        cam = np.linalg.solve(pose.T_world_cam, self.centre)[:3]
        if cam[2] <= 0:
            return
        uv = (self.K @ (cam / cam[2]))[:2]
        self._points.append((pose.t_us, uv))
        while len(self._points) > 2 and pose.t_us - self._points[1][0] >= FLOW_SPAN_US:
            self._points.popleft()
        t0, uv0 = self._points[0]
        if pose.t_us - t0 >= FLOW_SPAN_US // 2:
            self.px_per_ms = float(np.hypot(*(uv - uv0)) / ((pose.t_us - t0) / 1e3))

    def forget(self) -> None:
        """The lock was lost: the next poses start a new track."""
        self._points.clear()
        self.px_per_ms = None


class MarginMeter:
    """Event time processed per second of the receiver's own time: below 1 it falls behind a
    live camera. ``clock``: the receiver's time (wall time for a live daemon)."""

    def __init__(self, clock=time.perf_counter) -> None:
        self.clock = clock
        self._spans: deque[tuple[float, float]] = deque()  # (receiver s, event s) per push
        self.margin: float | None = None

    def timed(self, event_span_us: int, seconds: float) -> None:
        self._spans.append((seconds, event_span_us / 1e6))
        while len(self._spans) > 1 and sum(s for s, _ in self._spans) > MARGIN_SPAN_S:
            self._spans.popleft()
        spent = sum(s for s, _ in self._spans)
        if spent > 0:
            self.margin = sum(e for _, e in self._spans) / spent


def frame_quality(
    out: FrameOutput,
    *,
    px_per_cell: float | None,
    events_per_s: float,
    readout_events_per_s: float | None,
    flow_px_per_ms: float | None,
    realtime_margin: float | None,
) -> FrameQuality:
    passed = out.payload_bits > 0
    ber = None
    if passed and out.corrected is not None:
        ber = float(np.count_nonzero(out.corrected)) / out.corrected.size
    return FrameQuality(
        passed=passed,
        ber_before_fec=ber,
        px_per_cell=px_per_cell,
        readout_share=(events_per_s / readout_events_per_s if readout_events_per_s else None),
        flow_px_per_ms=flow_px_per_ms,
        realtime_margin=realtime_margin,
    )
