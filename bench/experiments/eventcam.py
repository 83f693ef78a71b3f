"""Run the event receiver on a simulated scene and score it against the simulator's truth."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from receiver.camera import CameraModel
from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.receiver import FrameOutput, Receiver
from receiver.pipeline.report import DecodeLog, FrameTruth
from receiver.sim import Scene, simulate

Sensor = tuple[int, int] | None
"""Sensor crop (width, height) of the paper's camera (same lens and pixel pitch); None: the whole
1280 x 720 sensor. Smaller crops see the marker with fewer pixels and simulate faster."""


def camera(sensor: Sensor) -> CameraModel:
    cam = CameraModel.paper()
    return cam if sensor is None else cam.resized(*sensor)


def fitting_distance(sensor: Sensor, full_sensor_m: float) -> float:
    """Distance at which the marker fills a crop as much as it fills the whole sensor at
    ``full_sensor_m`` (its size in pixels scales with the crop's height)."""
    return full_sensor_m * 720 / camera(sensor).height


@dataclass(frozen=True)
class EventRun:
    report: dict
    """``DecodeLog.report()``: BER, goodput, lock, frames, messages."""
    pose_t_us: np.ndarray
    poses: np.ndarray
    """(n, 4, 4) estimated T_world_cam at ``pose_t_us``."""
    truth: np.ndarray
    """(n, 4, 4) ground-truth T_world_cam at ``pose_t_us``."""
    frames: np.ndarray
    """(m, 2) int64: time (us) and bit errors of every data frame the receiver accepted."""
    wall_s: float


def run_event_receiver(scene: Scene, duration_s: float) -> EventRun:
    """Simulate ``duration_s`` of ``scene`` and decode it with the streaming receiver."""
    t0 = time.perf_counter()
    enc = scene.encoder
    config = ReceiverConfig(
        scene.camera,
        cells=enc.geometry.cells,
        profile=enc.profile.name,
        refresh_hz=scene.display.refresh_hz,
        marker_size_m=scene.marker_size_m,
    )
    receiver = Receiver(config, message_size=len(enc.message))
    log = DecodeLog(receiver, FrameTruth(enc, scene.display.refresh_hz, scene.start_refresh))
    recording = simulate(scene, duration_s=duration_s)
    frames: list[tuple[int, int]] = []
    for chunk in recording:
        outputs = receiver.push(chunk)
        log.add(outputs)
        for o in outputs:
            if isinstance(o, FrameOutput) and o.accepted:
                errors = log.truth.errors(o.read.bits, o.read.t_us)
                if errors is not None:  # None: the read matched a blank, not a data refresh
                    frames.append((o.read.t_us, errors))
    log.add(receiver.finish())
    t = np.array(log.pose_t, np.int64)
    poses = np.array(log.poses).reshape(-1, 4, 4)
    truth = recording.pose_at(t) if len(t) else np.empty((0, 4, 4))
    return EventRun(
        log.report(),
        t,
        poses,
        truth,
        np.array(frames, np.int64).reshape(-1, 2),
        time.perf_counter() - t0,
    )
