"""The simulator's fast paths against their slow equivalents: same events, other shortcuts."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.events import EVENT_DTYPE, concat
from eventocc.receiver.poses import make_pose
from eventocc.receiver.sim import (
    Display,
    HandHeldMotion,
    Scene,
    SensorModel,
    StaticMotion,
    moving,
    render,
    simulate,
)
from eventocc.receiver.sim.motion import image_box
from eventocc.receiver.sim.sensor import BackgroundNoise, _readout_cap, to_events

CAM = CameraModel.paper().resized(160, 120)
MESSAGE = bytes(range(256))


def _scene(**kw) -> Scene:
    base = {
        "encoder": StreamEncoder(MESSAGE, profile="paper", cells=16),
        "camera": CAM,
        "motion": StaticMotion(distance_m=4.0),
        "sensor": SensorModel.preset("ideal"),
    }
    return Scene(**(base | kw))


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0, 5000), st.integers(0, 99), st.sampled_from([-1, 1])), max_size=200
    ),
    st.integers(0, 40),
)
def test_events_come_out_sorted_by_time_and_stable_with_the_held_back_ones(raw, n_pending):
    t = np.array([r[0] for r in raw], float)
    idx = np.array([r[1] for r in raw], np.int64)
    p = np.array([r[2] for r in raw], np.int8)
    pending = np.zeros(n_pending, EVENT_DTYPE)
    pending["t"] = np.sort(np.random.default_rng(n_pending).integers(0, 6000, n_pending))
    pending["x"], pending["p"] = np.arange(n_pending) % 10, 1
    ev = to_events(t, idx, p, 10, SensorModel(), np.random.default_rng(0), pending)
    # Reference: a stable comparison sort of the same events, the held-back ones first.
    t_all = np.concatenate([pending["t"], np.rint(t).astype(np.int64)])
    i_all = np.concatenate([pending["y"].astype(np.int64) * 10 + pending["x"], idx])
    order = np.argsort(t_all, kind="stable")
    assert np.array_equal(ev["t"], t_all[order])
    assert np.array_equal(ev["y"].astype(np.int64) * 10 + ev["x"], i_all[order])


def test_background_noise_follows_each_pixels_rate():
    rates = np.where(np.arange(2000) < 1000, 1.0, 3.0)
    t, idx, p = BackgroundNoise(rates, np.zeros(2000)).events(0, 10e6, np.random.default_rng(1))
    low, high = (idx < 1000).sum(), (idx >= 1000).sum()
    assert low == pytest.approx(10_000, rel=0.05)
    assert high == pytest.approx(30_000, rel=0.05)
    assert np.all(p == 1) and t.min() >= 0 and t.max() < 10e6


def test_a_still_camera_gives_the_same_events_whatever_the_chunk_size():
    # Whole refreshes are rendered ahead of the window and held back: chunking must not show.
    scene = _scene(display=Display(rise_ms=2.5, fall_ms=1.5))
    a = concat(simulate(scene, 0.05, chunk_us=10_000))
    b = concat(simulate(scene, 0.05, chunk_us=1_300))
    assert len(a) > 1000
    assert np.array_equal(
        np.sort(a, order=["t", "y", "x", "p"]), np.sort(b, order=["t", "y", "x", "p"])
    )


def test_closed_form_runs_match_sampling_every_pixel_at_every_sub_step(monkeypatch):
    scene = _scene(motion=HandHeldMotion(distance_m=3.0, flow_px_per_ms=0.5, seed=1))
    fast = concat(simulate(scene, 0.03))
    monkeypatch.setattr(moving.MovingRenderer, "closed_form_runs", False)  # sample every step
    sampled = concat(simulate(scene, 0.03))
    assert len(fast) > 5000
    assert len(fast) == pytest.approx(len(sampled), rel=0.02)
    per_pixel = [
        np.bincount(e["y"].astype(int) * CAM.width + e["x"], minlength=CAM.width * CAM.height)
        for e in (fast, sampled)
    ]
    assert np.mean(np.abs(per_pixel[0] - per_pixel[1]) <= 1) > 0.97


def test_the_pixel_box_is_the_whole_sensor_when_the_screen_is_behind_the_camera():
    corners = _scene().rig.corners
    behind = make_pose(np.eye(3), [0.1, 0.1, 1.0])  # camera past the screen, looking away
    assert image_box(CAM, behind, corners, 4) == (0, CAM.width, 0, CAM.height)
    front = _scene().motion.trajectory(_scene().rig).pose_at([0])[0]
    x0, x1, y0, y1 = image_box(CAM, front, corners, 4)
    assert x0 < x1 and y0 < y1 and (x1 - x0) * (y1 - y0) < CAM.width * CAM.height / 2


def test_noise_free_sensors_stay_silent_off_the_screen():
    sensor = replace(SensorModel.preset("ideal"), leak_hz=0.0, shot_hz=0.0)
    scene = _scene(sensor=sensor)
    ev = concat(simulate(scene, 0.02))
    pose = scene.motion.trajectory(scene.rig).pose_at([0])[0]
    x0, x1, y0, y1 = image_box(CAM, pose, scene.layout.screen_corners(), 2)
    assert len(ev) > 100
    assert x0 <= ev["x"].min() and ev["x"].max() < x1 and y0 <= ev["y"].min() and ev["y"].max() < y1


def test_a_pwm_backlight_makes_the_lit_cells_blink_at_its_edges():
    pwm = Display(rise_ms=0.0, fall_ms=0.0, pwm_hz=600.0, pwm_duty=0.25)
    period, on = pwm.backlight_us()
    ev = concat(simulate(_scene(display=pwm), 0.03))
    steady = concat(simulate(_scene(display=replace(pwm, pwm_hz=None)), 0.03))
    assert len(ev) > 3 * len(steady)  # 18 blinks against 2 refreshes
    phase = ev["t"] % period
    rising = np.minimum(phase, period - phase) <= 1.0
    falling = np.abs(phase - on) <= 1.0
    assert np.mean(rising[ev["p"] > 0]) > 0.9
    assert np.mean(falling[ev["p"] < 0]) > 0.9


def test_pwm_with_a_moving_camera_is_refused_with_a_clear_message():
    scene = _scene(display=Display(pwm_hz=240.0), motion=HandHeldMotion(distance_m=3.0))
    with pytest.raises(ValueError, match="still cameras only"):
        list(simulate(scene, 0.01))


def test_still_pixels_skip_resting_refreshes_with_the_events_of_rendering_every_one(monkeypatch):
    """Thresholds of exactly 1 ln unit (clipped) land a transition's tail exactly on a threshold:
    its event must still fire as when every refresh is rendered."""
    coarse = replace(SensorModel.preset("ideal"), threshold_on=1.0, threshold_off=1.0)
    scene = _scene(encoder=StreamEncoder(MESSAGE, profile="robust", cells=16), sensor=coarse)
    skipping = concat(simulate(scene, 0.2))
    monkeypatch.setattr(render.StaticRenderer, "skip_resting", False)
    every = concat(simulate(scene, 0.2))
    assert len(skipping) > 1000
    assert np.array_equal(skipping, every)


def _readout_cap_by_sorting(t_us: np.ndarray, per_ms: float, rng) -> np.ndarray:
    """The readout cap's definition: sort each millisecond's events by a uniform random key and
    keep the first ``per_ms`` (ranks below it)."""
    ms = t_us // 1000
    order = np.lexsort((rng.random(len(ms)), ms))
    first = np.searchsorted(ms[order], ms[order], side="left")
    keep = np.zeros(len(ms), bool)
    keep[order[np.arange(len(ms)) - first < per_ms]] = True
    return keep


@pytest.mark.parametrize(("n", "per_ms"), [(1000, 3.5), (200_000, 1000.0), (50, 1e6), (1, 1.0)])
def test_the_readout_cap_keeps_the_events_that_sorting_by_random_keys_keeps(n, per_ms):
    t = np.random.default_rng(n).integers(5_000_000, 5_020_000, n)
    kept = _readout_cap(t, per_ms, np.random.default_rng(7))
    assert np.array_equal(kept, _readout_cap_by_sorting(t, per_ms, np.random.default_rng(7)))
    assert np.bincount(t[kept] // 1000).max() <= np.ceil(per_ms)
