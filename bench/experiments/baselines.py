"""Paper Fig. "comparison": streaming success per marker optical flow, and throughput per system.

Frame-camera baselines: a 120 Hz global-shutter camera (``bench.framecam``) films a 60 Hz screen
that shows a new code on every refresh, or on every other refresh with a black refresh between
(the paper's two streams). A code counts as received when any frame decodes its exact payload.
Our event receiver watches the same hand-held motions (same seeds, same camera and display),
with the paper's link profile (the paper's set-up) and with ``robust``. Flows are in the paper's
pixels (``eventcam.hand_held_scene``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from bench.experiments.eventcam import (
    HAND_HELD_TRACKER,
    Sensor,
    binning,
    clip_message,
    hand_held_scene,
    run_event_receiver,
)
from bench.framecam import FrameCamera, Slideshow
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.sim import Scene
from eventocc.receiver.sim.motion import project_points

FLOW_EDGES = (0.0, 1.0, 2.0, 3.0, 5.0, 8.0)
"""Bins of the marker's mean optical flow (paper px/ms) for the success-rate plot."""
EVENT_PROFILES = ("paper", "robust")


@dataclass(frozen=True)
class CodeFamily:
    """A kind of 2D code: how to draw payload ``i`` as modules, and read payloads from an image."""

    name: str
    capacity: int
    """Distinct payloads: a clip shows at most this many codes, so each is told apart."""
    draw: Callable[[int], np.ndarray]
    read: Callable[[np.ndarray], set[int]]

    @property
    def bits(self) -> float:
        """Payload bits per code (what the throughput counts)."""
        return math.log2(self.capacity)

    def __reduce__(self):
        return code_family, (self.name,)  # by name: draw and read are closures


def _qr_payload(i: int) -> str:
    return f"{i:017d}"  # 17 bytes: the byte-mode capacity of version 1 at ECC level L


def _qr_family() -> CodeFamily:
    params = cv2.QRCodeEncoder_Params()
    params.version = 1
    params.correction_level = cv2.QRCodeEncoder_CORRECT_LEVEL_L
    params.mode = cv2.QRCodeEncoder_MODE_BYTE
    encoder = cv2.QRCodeEncoder.create(params)
    detector = cv2.QRCodeDetector()

    def draw(i: int) -> np.ndarray:
        return encoder.encode(_qr_payload(i)) > 127  # one pixel per module, quiet zone included

    def read(image: np.ndarray) -> set[int]:
        text, *_ = detector.detectAndDecode(image)
        return {int(text)} if text.isdigit() else set()

    return CodeFamily("QR v1-L", 256**17, draw, read)  # 17 bytes: 136 bits


def _aruco_family(name: str, dictionary_id: int) -> CodeFamily:
    dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id)
    detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
    side = dictionary.markerSize + 2  # data bits plus the black border

    def draw(i: int) -> np.ndarray:
        tag = cv2.aruco.generateImageMarker(dictionary, i, side) > 127
        return np.pad(tag, 1, constant_values=True)  # a one-module white quiet zone

    def read(image: np.ndarray) -> set[int]:
        _, ids, _ = detector.detectMarkers(image)
        return set() if ids is None else {int(j) for j in ids.ravel()}

    return CodeFamily(name, len(dictionary.bytesList), draw, read)


def code_families() -> list[CodeFamily]:
    return [
        _qr_family(),
        _aruco_family("AprilTag 36h11", cv2.aruco.DICT_APRILTAG_36h11),
        _aruco_family("ArUco 6x6", cv2.aruco.DICT_6X6_1000),
    ]


def code_family(name: str) -> CodeFamily:
    """The family called ``name`` (how one reaches a worker process)."""
    return next(f for f in code_families() if f.name == name)


def marker_flow(scene: Scene, sensor: Sensor, points: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """Mean image speed (paper px/ms) of ``points`` at each time, by a 1 ms central difference."""
    trajectory, cam = _trajectory(scene), scene.camera
    before = trajectory.pose_at(np.asarray(t_us) - 500.0)
    after = trajectory.pose_at(np.asarray(t_us) + 500.0)
    flow = [
        np.linalg.norm(project_points(cam, a, points) - project_points(cam, b, points), axis=1)
        for a, b in zip(before, after, strict=True)
    ]
    return np.array([f.mean() for f in flow]) / binning(sensor)


@dataclass(frozen=True)
class Outcome:
    """Per transmitted code or data frame: its marker flow (px/ms) and whether it was received."""

    system: str
    flow: np.ndarray
    received: np.ndarray
    throughput_bps: float
    """Payload bits delivered per second (codes: received codes x payload bits; ours: verified
    message bits after FEC)."""
    wall_s: float
    exact: np.ndarray | None = None
    """Ours only: whether each data frame was read bit-exact before FEC (``received`` counts a
    framed profile's frames once their FEC and CRC pass, as the codes count theirs once their
    own error correction decodes them)."""
    tracking: dict[str, float | int | None] | None = None
    """Ours only, to say why frames were missed: the first lock (s), tracking losses, and the
    shares of the clip tracked and tracked more than ``WRONG_M`` off the truth."""


@lru_cache(maxsize=8)
def _motion(flow: float, seed: int, sensor: Sensor) -> Scene:
    """The hand-held scene whose motion, camera and display every system of one (flow, seed)
    shares; the frame baselines replace its screen, our receiver its message."""
    return hand_held_scene(StreamEncoder(b"", cells=16), flow, seed, sensor)


@lru_cache(maxsize=8)
def _trajectory(scene: Scene):
    return scene.motion.trajectory(scene.rig)  # calibrating a hand-held motion takes seconds


def run_frame_baseline(
    family: CodeFamily,
    blank_between: bool,
    flow: float,
    seed: int,
    duration_s: float,
    sensor: Sensor,
) -> Outcome:
    t0 = time.perf_counter()
    scene = _motion(flow, seed, sensor)
    refreshes = int(duration_s * scene.display.refresh_hz)
    if refreshes > family.capacity:
        raise ValueError(
            f"{duration_s} s shows {refreshes} codes but {family.name} has only "
            f"{family.capacity} payloads: shorten the clip"
        )
    trajectory = _trajectory(scene)  # the event camera's motion, exactly
    screen = Slideshow(
        [family.draw(i) for i in range(refreshes)],
        scene.marker_size_m,
        blank_between,
        scene.display,
        scene.sensor.lux,
    )
    cam = FrameCamera(scene.camera)
    received: set[int] = set()
    for _, image in cam.frames(screen, trajectory, duration_s, seed):
        received |= family.read(image)
    shown = [k for k in range(refreshes) if screen.code_index(k) is not None]
    t_mid = (np.array(shown) + 0.5) * scene.display.period_us
    flow_px = marker_flow(scene, sensor, screen.corners(), t_mid)
    got = np.array([screen.code_index(k) in received for k in shown])
    name = f"{family.name}" + (" + blank" if blank_between else "")
    return Outcome(
        name, flow_px, got, float(got.sum() * family.bits / duration_s), time.perf_counter() - t0
    )


def run_event(profile: str, flow: float, seed: int, duration_s: float, sensor: Sensor) -> Outcome:
    """Our receiver: a data frame counts as received when its FEC and CRC pass (``robust``), as a
    code does when its own error correction decodes it and the paper counts decoding "with error
    correction"; the ``paper`` profile's frames carry no check of their own (its Reed-Solomon
    words span frames), so they count only when read bit-exact. From the clip's start like the
    codes (detection costs the frames before the lock); the throughput is the goodput after FEC
    of a message sized to the clip (``EventRun.goodput_bps``)."""
    motion = _motion(flow, seed, sensor)
    message = clip_message(profile, 16, motion.display.refresh_hz, duration_s, seed)
    enc = StreamEncoder(message, profile=profile, cells=16)
    scene = hand_held_scene(enc, flow, seed, sensor)
    run = run_event_receiver(scene, duration_s, HAND_HELD_TRACKER)
    period = scene.display.period_us
    shown = [k for k in range(int(duration_s * 1e6 / period)) if enc.is_data_frame(k)]

    def shown_and(read: set[int]) -> np.ndarray:
        # A read frame's time falls inside its refresh; allow one refresh of slack either way.
        return np.array([any(j in read for j in (k - 1, k, k + 1)) for k in shown], bool)

    exact = shown_and({round(t / period - 0.5) for t, e, _ in run.frames if e == 0})
    checked = shown_and({round(t / period - 0.5) for t, _, ok in run.frames if ok})
    got = checked if enc.profile.framed else exact
    flow_px = marker_flow(
        motion, sensor, motion.rig.corners, (np.array(shown, float) + 0.5) * period
    )
    goodput = run.goodput_bps(len(message) * 8, enc.profile.data_every * period / 1e6)
    tracking = {
        "first_lock_s": run.report["time_to_lock_s"],
        "losses": run.report["tracking_losses"],
        "tracked": run.tracked_s() / duration_s,
        "tracked_wrong": run.tracked_s(wrong=True) / duration_s,
    }
    name = f"ours (events, N=16, {profile})"
    return Outcome(name, flow_px, got, goodput, run.wall_s, exact, tracking)
