"""Detection and tracking while a hand-held camera moves: the motion-compensated locator search
(``locate``) on synthetic events, and the receiver on a small virtual event camera.

Detection under motion is a known gap: the receiver lock tests are expected failures (not strict)
and say what they require; the safety test (a wrong lock must not survive) holds today.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from occ.stream import StreamEncoder
from receiver.camera import CameraModel
from receiver.events import EVENT_DTYPE
from receiver.pipeline.config import ReceiverConfig, TrackerParams
from receiver.pipeline.locate import (
    MarkerNotFound,
    compensated_burst,
    locator_blob,
    motion_flow,
    quadrilateral,
)
from receiver.pipeline.receiver import TRACKING, PoseEstimate, Receiver, StateChange
from receiver.sim import Display, HandHeldMotion, Scene, SensorModel, simulate

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

# DAVIS240-sized sensor, intrinsics scaled from 346x260 (f = 300 px): the simulator's hand-held
# path costs tens of seconds of CPU per simulated second even at this size.
CAMERA = CameraModel(240, 180, np.array([[208.0, 0, 120], [0, 208.0, 90], [0, 0, 1]]))
MESSAGE = bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8))
LOCK_WITHIN_US = 300_000
"""A lock needs one detection window (70 ms) plus a few retries."""
FIRST_POSE_MAX_M = 0.05
"""Initial pose (after capture onto the ring edges) against ground truth."""
TRACKED_MAX_M = 0.03
WRONG_LOCK_M = 0.10
WRONG_LOCK_DROPPED_US = 50_000
"""A pose this far off must be dropped (fit ratio) within this time."""


SHAPE = (180, 240)
PERIOD_US = 1e6 / 30


def _events(t, x, y, p) -> np.ndarray:
    ev = np.zeros(len(t), EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, np.rint(x), np.rint(y), p
    return ev[np.argsort(ev["t"], kind="stable")]


def _outline(rng, n, t0, t1, corner, side, flow, polarity):
    """``n`` events on a square outline (top-left ``corner`` at t = 0) moving at ``flow``."""
    t = rng.integers(t0, t1, n)
    s, edge = rng.uniform(0, side, n), rng.integers(0, 4, n)
    x = corner[0] + np.choose(edge, [s, np.full(n, side), s, np.zeros(n)])
    y = corner[1] + np.choose(edge, [np.zeros(n), s, np.full(n, side), s])
    return _events(t, x + flow[0] * t / 1e3, y + flow[1] * t / 1e3, polarity(n))


def _moving_marker(flow, duration_us=70_000, seed=0):
    """A 60 px square that fires ON in the bursts (at whole periods) and OFF half a period
    later, moving at ``flow`` px/ms, framed by a 90 px outline (the static white ring) whose
    swept edges fire both polarities all the time."""
    rng = np.random.default_rng(seed)
    parts = []
    for k in range(int(duration_us // PERIOD_US) + 1):
        for centre, p in ((k * PERIOD_US, 1), ((k + 0.5) * PERIOD_US, -1)):
            t = rng.normal(centre, 0.05 * PERIOD_US, 4000).astype(np.int64)
            x, y = rng.uniform(90, 150, 4000), rng.uniform(60, 120, 4000)
            parts.append(_events(t, x + flow[0] * t / 1e3, y + flow[1] * t / 1e3, p))
    parts.append(
        _outline(
            rng,
            60_000,
            0,
            duration_us,
            (75, 45),
            90,
            flow,
            lambda n: rng.choice(np.array([-1, 1], np.int8), n),
        )
    )
    ev = np.concatenate(parts)
    ev = ev[(ev["t"] >= 0) & (ev["t"] < duration_us) & (ev["x"] < SHAPE[1]) & (ev["y"] < SHAPE[0])]
    return ev[np.argsort(ev["t"], kind="stable")]


@pytest.mark.parametrize("flow", [(0.5, -0.3), (-1.5, 1.0)])
def test_motion_flow_recovers_the_translation_of_an_outline(flow):
    rng = np.random.default_rng(1)
    ev = _outline(rng, 20_000, 0, 13_000, (60, 40), 80, flow, lambda n: -np.ones(n, np.int8))
    assert np.allclose(motion_flow(ev, 13_000, SHAPE), flow, atol=0.1)


def test_motion_flow_of_unstructured_noise_is_zero():
    rng = np.random.default_rng(2)
    n = 20_000
    ev = _events(
        np.sort(rng.integers(0, 13_000, n)),
        rng.uniform(0, 239, n),
        rng.uniform(0, 179, n),
        -np.ones(n, np.int8),
    )
    assert np.array_equal(motion_flow(ev, 13_000, SHAPE), [0.0, 0.0])


@pytest.mark.parametrize("flow", [(0.0, 0.0), (0.5, 0.3), (-1.0, 1.0)])
def test_compensated_burst_outlines_the_blinking_square_not_the_swept_ring(flow):
    ev = _moving_marker(np.array(flow))
    image, t_burst, found = compensated_burst([ev], 0.0, PERIOD_US, SHAPE)
    assert np.allclose(found, flow, atol=0.15)
    quad = quadrilateral(locator_blob(image, cell_px=60 / 18))
    move = np.array(flow) * t_burst / 1e3
    truth = np.array([[90, 60], [150, 60], [150, 120], [90, 120]]) + move
    nearest = np.linalg.norm(truth[:, None] - quad[None], axis=2).min(axis=1)
    assert nearest.max() < 4, quad.round(1)  # every corner found (orientation is not read here)


def test_an_image_without_a_blob_is_a_clear_miss():
    with pytest.raises(MarkerNotFound, match="spatial: nothing brightens"):
        locator_blob(np.zeros(SHAPE, bool), cell_px=4.0)


def _run(flow_px_per_ms: float, duration_s: float, seed: int = 0) -> dict:
    scene = Scene(
        encoder=StreamEncoder(MESSAGE, profile="robust", cells=16),
        marker_size_m=0.272,
        display=Display(refresh_hz=60.0),
        camera=CAMERA,
        motion=HandHeldMotion(distance_m=0.6, flow_px_per_ms=flow_px_per_ms, seed=seed),
        sensor=SensorModel.preset("gen4-indoor"),
        seed=seed,
    )
    # Under motion the fit-ratio loss check is on: it drops a pose that slid off the ring's
    # edges (off by default, because with a still camera it judges sensor noise).
    rx = Receiver(ReceiverConfig(CAMERA, tracker=TrackerParams(min_fit_ratio=0.5)))
    rec = simulate(scene, duration_s=duration_s, chunk_us=10_000)
    poses: list[PoseEstimate] = []
    changes: list[StateChange] = []
    for chunk in rec:
        for out in rx.push(chunk):
            if isinstance(out, PoseEstimate):
                poses.append(out)
            elif isinstance(out, StateChange):
                changes.append(out)
    t = np.array([p.t_us for p in poses], np.int64)
    err = np.array([])
    if len(t):
        truth = rec.pose_at(t)
        est = np.stack([p.T_world_cam for p in poses])
        err = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
    return {"t": t, "err": err, "changes": changes, "stats": rx.stats}


@pytest.fixture(scope="module")
def slow_hand() -> dict:
    return _run(0.5, 0.6)


def test_a_wrong_lock_under_motion_is_dropped_quickly(slow_hand):
    """Whatever detection does under motion, a pose far from the truth must not keep tracking:
    the tracker's fit ratio (events off the ring's edges) has to end it."""
    t, err, changes = slow_hand["t"], slow_hand["err"], slow_hand["changes"]
    for lock in (c for c in changes if c.state == TRACKING):
        end = next((c.t_us for c in changes if c.t_us > lock.t_us), 1 << 62)
        wrong = t[(t >= lock.t_us) & (t < end) & (err > WRONG_LOCK_M)]
        if len(wrong):
            assert end - wrong[0] <= WRONG_LOCK_DROPPED_US, (
                f"a pose {WRONG_LOCK_M * 100:.0f}+ cm off tracked from {wrong[0]} to {end} us"
            )


def _assert_locks_and_tracks(run: dict) -> None:
    locks = run["stats"].lock_times_us
    assert locks and locks[0] <= LOCK_WITHIN_US, (
        f"no lock within {LOCK_WITHIN_US / 1e3:.0f} ms: {dict(run['stats'].detection_failures)}"
    )
    assert run["err"][0] <= FIRST_POSE_MAX_M, f"first pose {run['err'][0] * 100:.1f} cm off"
    assert np.max(run["err"]) <= TRACKED_MAX_M, f"tracked pose up to {run['err'].max():.3f} m off"


@pytest.mark.xfail(reason="detection under hand-held motion is not solved yet", strict=False)
def test_detects_and_tracks_at_half_a_pixel_per_ms(slow_hand):
    _assert_locks_and_tracks(slow_hand)


@pytest.mark.slow
@pytest.mark.xfail(reason="detection under hand-held motion is not solved yet", strict=False)
@pytest.mark.parametrize("flow", [1.0, 2.0])
def test_detects_and_tracks_faster_motion(flow):
    _assert_locks_and_tracks(_run(flow, 1.0, seed=1))
