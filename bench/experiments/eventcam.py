"""Run the event receiver on a simulated scene and score it against the simulator's truth."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from bench.tracking import POSE_GAP_US, WRONG_M, hand_held_config
from eventocc.occ.profiles import get_profile
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.config import ReceiverConfig, TrackerParams
from eventocc.receiver.pipeline.metrics import held_s
from eventocc.receiver.pipeline.receiver import FrameOutput, Receiver
from eventocc.receiver.pipeline.report import DecodeLog, FrameTruth, pushes
from eventocc.receiver.sim import HandHeldMotion, Optics, Scene, SensorModel, simulate

Sensor = tuple[int, int] | None
"""A smaller sensor (width, height) standing in for the paper's 1280 x 720 one, which None
keeps. It sees the marker with fewer pixels and simulates faster: as a centred crop for the
still camera (``camera``), as the whole view binned for the hand-held ones (``binned_camera``)."""

MESSAGE_SHARE = 0.2
"""A clip's message takes this share of the clip's raw capacity, leaving room for detection,
FEC and a missed first pass; it still spans many frames, so its rate is a rate."""
HAND_HELD_DISTANCE_M = 0.6
"""Mean camera-to-marker distance of the hand-held experiments."""
HAND_HELD_MARKER_M = 0.272
"""The paper's screen: the marker's white ring in full-screen mode."""
HAND_HELD_SENSOR = "evk4-moving"
"""The paper's camera as the moving renderer simulates it (no photoreceptor low-pass)."""
HAND_HELD_TRACKER = hand_held_config().tracker
"""The receiver's tracker setting for a moving camera (the one ``bench.tracking`` measures)."""


def raw_bps(cells: int, refresh_hz: float, data_every: int) -> float:
    """Physical limit: N^2 bits per data frame at the data frame rate."""
    return cells**2 * refresh_hz / data_every


def clip_message(
    profile: str, cells: int, refresh_hz: float, duration_s: float, seed: int
) -> bytes:
    """Random bytes, ``MESSAGE_SHARE`` of what a clip of ``duration_s`` carries raw (>= 16)."""
    limit = raw_bps(cells, refresh_hz, get_profile(profile).data_every)
    size = max(16, int(limit * duration_s * MESSAGE_SHARE / 8))
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()


def camera(sensor: Sensor) -> CameraModel:
    """The paper's lens on ``sensor`` (same pixel pitch, centred crop): a still camera keeps the
    paper's pixels per cell from further away."""
    cam = CameraModel.paper()
    return cam if sensor is None else cam.resized(*sensor)


def binning(sensor: Sensor) -> float:
    """Sensor pixels per paper pixel of ``binned_camera(sensor)`` (1 for the whole sensor)."""
    return 1.0 if sensor is None else sensor[1] / CameraModel.paper().height


def binned_camera(sensor: Sensor) -> CameraModel:
    """The paper's whole field of view on ``sensor``'s pixels, as if binned. A crop would need
    the camera further away to fit the marker, and the narrower view then weakens perspective
    so much that the tilt of a 0.27 m marker becomes ambiguous (the pose flips); binning keeps
    the paper's distances, angles and motions, and only the pixels per cell drop."""
    cam = CameraModel.paper()
    return cam if sensor is None else cam.binned(*sensor)


def hand_held_scene(
    encoder: StreamEncoder, flow_px_per_ms: float, seed: int, sensor: Sensor
) -> Scene:
    """The paper's hand-held set-up on the binned ``sensor``: the 0.272 m marker about 0.6 m
    away, office light, a wander at a mean marker flow of ``flow_px_per_ms`` paper pixels."""
    return Scene(
        encoder=encoder,
        marker_size_m=HAND_HELD_MARKER_M,
        camera=binned_camera(sensor),
        motion=HandHeldMotion(HAND_HELD_DISTANCE_M, flow_px_per_ms * binning(sensor), seed=seed),
        sensor=SensorModel.preset(HAND_HELD_SENSOR, lux=250.0),
        optics=Optics.preset(HAND_HELD_SENSOR),
        seed=seed,
    )


@dataclass(frozen=True)
class EventRun:
    report: dict
    """``DecodeLog.report()``: BER, goodput, lock, frames, messages (each compared with the
    message sent: ``matches_sent``)."""
    pose_t_us: np.ndarray
    poses: np.ndarray
    """(n, 4, 4) estimated T_world_cam at ``pose_t_us``."""
    truth: np.ndarray
    """(n, 4, 4) ground-truth T_world_cam at ``pose_t_us``."""
    frames: np.ndarray
    """(m, 3) int64: time (us), bit errors and whether its FEC and CRC passed (framed profiles;
    0 for ``paper``) of every data frame the receiver accepted."""
    first_read_s: float | None
    """When the receiver read its first data frame (accepted or not), on the clock of the
    report's times (seconds since the first event)."""
    wall_s: float

    def tracked_s(self, wrong: bool = False) -> float:
        """Seconds the receiver held a pose (``wrong``: one more than ``WRONG_M`` off)."""
        off = np.linalg.norm(self.poses[:, :3, 3] - self.truth[:, :3, 3], axis=1)
        return held_s(self.pose_t_us, POSE_GAP_US, off > WRONG_M if wrong else None)

    def goodput_bps(self, message_bits: int, frame_s: float) -> float:
        """The first message that matches the one sent, its bits over the time its frames took
        to stream, from the first frame read to the one that completed it (the paper's
        throughput: bits recovered per second of streaming); 0 if none completed."""
        done = [m for m in self.report["messages"] if m["matches_sent"]]
        if not done or self.first_read_s is None:
            return 0.0
        return message_bits / (done[0]["t_s"] - self.first_read_s + frame_s)


def run_event_receiver(
    scene: Scene, duration_s: float, tracker: TrackerParams | None = None
) -> EventRun:
    """Simulate ``duration_s`` of ``scene`` and decode it with the streaming receiver (``tracker``:
    its tracker setting, the default one if None)."""
    t0 = time.perf_counter()
    enc = scene.encoder
    config = ReceiverConfig(
        scene.camera,
        cells=enc.geometry.cells,
        profile=enc.profile.name,
        refresh_hz=scene.display.refresh_hz,
        marker_size_m=scene.marker_size_m,
        tracker=tracker or TrackerParams(),
    )
    receiver = Receiver(config, message_size=len(enc.message))
    truth_frames = FrameTruth(enc, scene.display.refresh_hz, scene.start_refresh)
    recording = simulate(scene, duration_s=duration_s)
    frames: list[tuple[int, int]] = []
    first_read_us = None

    log = DecodeLog(receiver, truth_frames)
    for _, outputs in pushes(receiver, recording):
        log.add(outputs)
        for o in outputs:
            if isinstance(o, FrameOutput) and first_read_us is None:
                first_read_us = o.read.t_us
            if isinstance(o, FrameOutput) and o.accepted:
                errors = truth_frames.errors(o.read.bits, o.read.t_us)
                if errors is not None:  # None: the read matched a blank, not a data refresh
                    frames.append((o.read.t_us, errors, o.payload_bits > 0))
    t = np.array(log.pose_t, np.int64)
    poses = np.array(log.poses).reshape(-1, 4, 4)
    truth = recording.pose_at(t) if len(t) else np.empty((0, 4, 4))
    start = receiver.stats.first_event_us or 0
    return EventRun(
        log.report(),
        t,
        poses,
        truth,
        np.array(frames, np.int64).reshape(-1, 3),
        None if first_read_us is None else (first_read_us - start) / 1e6,
        time.perf_counter() - t0,
    )
