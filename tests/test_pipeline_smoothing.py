"""The output pose smoother: every pose comes back once, in order, fitted to its neighbours."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.smoothing import PoseSmoother
from eventocc.receiver.poses import make_pose

HALF_US = 5000


def _path(t_us: np.ndarray) -> np.ndarray:
    """A camera moving at a steady 1 m/s while turning at 90 deg/s: a straight line in time."""
    s = t_us / 1e6
    R = Rotation.from_rotvec(np.outer(s, np.radians([30.0, 80.0, 20.0]))).as_matrix()
    return make_pose(R, np.outer(s, [0.6, 0.8, 0.0]) + np.array([0.1, 0.1, -0.6]))


def _smooth(smoother: PoseSmoother, t_us: np.ndarray, T: np.ndarray) -> list:
    out = [p for t, pose in zip(t_us, T, strict=True) for p in smoother.push(int(t), pose)]
    return out + smoother.flush()


def test_every_pose_comes_back_once_in_order_after_its_windows_have_passed():
    t_us = np.cumsum(np.random.default_rng(0).integers(300, 1500, 400))
    wide = 3 * HALF_US
    smoother = PoseSmoother(HALF_US, wide, capacity=8)  # small: it must drop and grow as it goes
    given = []
    for t, pose in zip(t_us, _path(t_us), strict=True):
        back = smoother.push(int(t), pose)
        assert all(tb + wide < t for tb, _ in back), "a pose came back before its window closed"
        given += back
    held = smoother.flush()
    assert held and all(tb + wide >= t_us[-1] for tb, _ in held)
    assert [t for t, _ in given + held] == t_us.tolist()
    assert smoother.flush() == []


def test_a_steady_motion_comes_back_unchanged_even_at_the_ends_of_a_track():
    t_us = np.arange(0, 60_000, 800)
    truth = _path(t_us)
    out = _smooth(PoseSmoother(HALF_US), t_us, truth)
    T = np.array([pose for _, pose in out])
    # to 0.1 mm: the pivot's place in the frame of a camera turning at 90 deg/s bends
    assert np.abs(T[:, :3, 3] - truth[:, :3, 3]).max() < 1e-4
    angle = Rotation.from_matrix(np.swapaxes(T[:, :3, :3], 1, 2) @ truth[:, :3, :3]).magnitude()
    assert np.degrees(angle).max() < 1e-3  # the chordal fit of a 0.9 deg span
    assert np.allclose(T[:, 3], [0, 0, 0, 1])


def test_independent_pose_noise_shrinks_threefold():
    """~11 updates in the window: noise independent from pose to pose falls by ~sqrt(11)."""
    rng = np.random.default_rng(1)
    t_us = np.arange(0, 500_000, 1000)
    truth = _path(t_us)
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (len(t_us), 3))
    turn = Rotation.from_rotvec(rng.normal(0, np.radians(1.0), (len(t_us), 3))).as_matrix()
    noisy[:, :3, :3] = noisy[:, :3, :3] @ turn
    T = np.array([pose for _, pose in _smooth(PoseSmoother(HALF_US), t_us, noisy)])

    def rms_cm_deg(est):
        cm = 100 * np.sqrt(np.mean(np.sum((est[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1)))
        rel = np.swapaxes(est[:, :3, :3], 1, 2) @ truth[:, :3, :3]
        return cm, np.degrees(np.sqrt(np.mean(Rotation.from_matrix(rel).magnitude() ** 2)))

    (raw_cm, raw_deg), (cm, deg) = rms_cm_deg(noisy), rms_cm_deg(T)
    assert cm < raw_cm / 2.5 and deg < raw_deg / 2.5
    assert np.allclose(np.linalg.det(T[:, :3, :3]), 1.0)


def test_orientation_noise_that_keeps_the_pivot_in_place_is_averaged_over_its_own_window():
    """Noise that swings the camera about the marker's centre (which its image barely shows),
    held for 4 ms at a time as a slow edge's events hold it: the orientation's wider window
    averages it where the position's could not, and the pivot stays where the camera saw it."""
    rng = np.random.default_rng(2)
    t_us = np.arange(0, 400_000, 1000)
    truth = _path(t_us)
    pivot = np.array([0.2, 0.15, 0.0])
    centre = np.einsum("nji,nj->ni", truth[:, :3, :3], pivot - truth[:, :3, 3])
    swing = np.repeat(rng.normal(0, np.radians(0.5), (len(t_us) // 4, 3)), 4, axis=0)
    noisy = truth.copy()
    noisy[:, :3, :3] = truth[:, :3, :3] @ Rotation.from_rotvec(swing).as_matrix()
    noisy[:, :3, 3] = pivot - np.einsum("nij,nj->ni", noisy[:, :3, :3], centre)

    def smoothed(half_us, orientation_half_us):
        smoother = PoseSmoother(half_us, orientation_half_us, pivot=pivot)
        return np.array([pose for _, pose in _smooth(smoother, t_us, noisy)])

    def rms_cm(T):
        return 100 * np.sqrt(np.mean(np.sum((T[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1)))

    wide = smoothed(HALF_US, 3 * HALF_US)
    assert rms_cm(wide) < rms_cm(smoothed(HALF_US, HALF_US)) / 1.4
    seen = np.einsum("nji,nj->ni", wide[:, :3, :3], pivot - wide[:, :3, 3])
    assert np.abs(seen - centre).max() < 1e-4


def test_a_fast_turn_narrows_the_orientation_window():
    """A camera panning at 300 deg/s with a 1 deg, 10 Hz wobble: a line fitted over +-15 ms
    would cut the wobble's peaks by ~0.15 deg; over the time of a degree's turn it follows."""
    t_us = np.arange(0, 300_000, 1000)
    s = t_us / 1e6
    turn = np.radians(300.0 * s + np.sin(2 * np.pi * 10 * s))
    R = Rotation.from_rotvec(np.outer(turn, [0.0, 1.0, 0.0])).as_matrix()
    truth = make_pose(R, np.tile([0.1, 0.1, -0.6], (len(t_us), 1)))
    out = _smooth(PoseSmoother(HALF_US, 3 * HALF_US), t_us, truth)
    T = np.array([pose for _, pose in out])
    angle = Rotation.from_matrix(np.swapaxes(T[:, :3, :3], 1, 2) @ truth[:, :3, :3]).magnitude()
    assert np.degrees(angle).max() < 0.05


def test_no_window_gives_each_pose_back_at_once():
    pose = _path(np.array([0]))[0]
    assert PoseSmoother(0).push(7, pose) == [(7, pose)]


def test_a_negative_window_is_refused():
    with pytest.raises(ValueError, match="pose smoothing"):
        ReceiverConfig(CameraModel(240, 180, np.diag([208.0, 208.0, 1.0])), pose_smoothing_us=-1)
