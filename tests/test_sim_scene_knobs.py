"""The simulator's knobs for the randomized scene suite: a lead-in before the marker appears, a
camera clock that starts anywhere, oblique views and lens vignetting."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.events import concat
from eventocc.receiver.pipeline.report import FrameTruth
from eventocc.receiver.poses import make_pose, write_tum
from eventocc.receiver.sim import (
    Display,
    HandHeldMotion,
    Optics,
    Scene,
    SensorModel,
    StaticMotion,
    TumMotion,
    simulate,
)
from eventocc.receiver.sim.display import LeadIn
from eventocc.receiver.sim.motion import look_at, project_points
from eventocc.receiver.sim.truth import SceneTruth

SMALL = CameraModel.paper().resized(240, 180)
QUIET = replace(SensorModel.preset("gen4-indoor"), leak_hz=0.0, shot_hz=0.0)


def small_scene(**kw) -> Scene:
    base = {
        "encoder": StreamEncoder(b"knobs" * 40, profile="robust", cells=16),
        "camera": SMALL,
        "motion": StaticMotion(distance_m=3.0),
        "sensor": QUIET,
    }
    return Scene(**(base | kw))


def test_a_black_lead_in_keeps_the_screen_silent_until_the_marker_appears():
    lead = LeadIn(refreshes=6)
    scene = small_scene(lead_in=lead, start_refresh=3)
    ev = concat(simulate(scene, 0.2))
    appears = scene.marker_appears_us
    assert appears == pytest.approx(6 * 1e6 / 60)
    assert scene.first_refresh == -3
    assert len(ev) > 1000
    # The marker's first refresh switches its rings and cells on: nothing fires before it.
    assert ev["t"].min() >= appears
    assert (ev["p"][ev["t"] < appears + 1e6 / 60] > 0).all()
    # Afterwards the stream is the one without a lead-in, shifted by the lead-in.
    plain = concat(simulate(small_scene(start_refresh=3), 0.2 - appears / 1e6))
    shifted = ev.copy()
    shifted["t"] -= round(appears)
    late = shifted["t"] >= 0.05e6  # once the first transitions have settled in both
    ref = plain[plain["t"] >= 0.05e6]
    assert abs(late.sum() - len(ref)) < 0.02 * len(ref)


def test_bars_in_the_lead_in_toggle_cells_far_from_the_marker_blink():
    display = Display(rise_ms=0.0, fall_ms=0.0)
    scene = small_scene(
        lead_in=LeadIn(refreshes=30, content="bars"),
        display=display,
        sensor=SensorModel.preset("ideal"),
    )
    ev = concat(simulate(scene, 0.4))
    assert ev["t"].max() < scene.marker_appears_us + 1  # only the lead-in fits in 0.4 s...
    before = ev[ev["t"] < 0.4e6]
    assert len(before) > 1000  # ...and it moves
    # A pixel toggles every 4 refreshes: its ON bursts come 8 refreshes apart, never 2.
    pix = before["y"].astype(np.int64) * SMALL.width + before["x"]
    on = before[before["p"] > 0]
    busiest = np.bincount(pix[before["p"] > 0]).argmax()
    t_on = on["t"][(on["y"].astype(np.int64) * SMALL.width + on["x"]) == busiest]
    starts = t_on[np.diff(t_on, prepend=-1e9) > 1e6 / 60 / 2]
    gaps = np.diff(starts) / (1e6 / 60)
    assert len(gaps) >= 2
    assert np.allclose(gaps, 8, atol=0.5)


def test_the_time_base_shifts_events_and_ground_truth_alike():
    motion = HandHeldMotion(distance_m=3.0, flow_px_per_ms=0.5, seed=1)
    base = small_scene(motion=motion, sensor=SensorModel.preset("gen4-indoor"))
    late = replace(base, time_base_us=1_000_000_007)
    a, b = simulate(base, 0.03), simulate(late, 0.03)
    ea, eb = concat(a), concat(b)
    assert np.array_equal(ea["t"] + 1_000_000_007, eb["t"])
    assert np.array_equal(ea[["x", "y", "p"]], eb[["x", "y", "p"]])
    t = np.array([0, 12_345, 29_000])
    assert np.allclose(a.pose_at(t), b.pose_at(t + 1_000_000_007))
    assert np.allclose(a.refresh_times_us(0, 3) + 1_000_000_007, b.refresh_times_us(0, 3))
    d = late.describe()
    assert Scene.from_dict(d).time_base_us == 1_000_000_007
    with pytest.raises(ValueError, match="time_base_us must be >= 0"):
        replace(base, time_base_us=-1)


def test_old_scene_descriptions_load_without_the_new_fields():
    d = small_scene().describe()
    del d["lead_in"], d["time_base_us"]
    s = Scene.from_dict(d)
    assert s.lead_in == LeadIn() and s.time_base_us == 0


def test_an_elevated_view_looks_at_the_marker_from_above_or_below():
    scene = small_scene(motion=StaticMotion(distance_m=2.0, elevation_deg=30.0, tilt_deg=10.0))
    T = scene.motion.trajectory(scene.rig).pose_at(np.zeros(1))[0]
    assert np.allclose(T, look_at(scene.rig.centre, 2.0, 10.0, 30.0, 0.0))
    centre = project_points(SMALL, T, scene.rig.centre[None])[0]
    assert np.allclose(centre, SMALL.K[:2, 2], atol=1e-6)  # it still looks at the centre
    # Seen from 30 degrees up, the marker's vertical side shortens by about cos(30).
    c = project_points(SMALL, T, scene.rig.corners)
    ratio = np.linalg.norm(c[3] - c[0]) / np.linalg.norm(c[1] - c[0])
    assert ratio == pytest.approx(math.cos(math.radians(30)), abs=0.06)
    with pytest.raises(ValueError, match="elevation must be within"):
        StaticMotion(elevation_deg=85.0)


def test_a_hand_held_wander_turns_around_its_base_view():
    rig = small_scene().rig
    level = HandHeldMotion(distance_m=3.0, flow_px_per_ms=0.5, seed=4).trajectory(rig)
    rolled = HandHeldMotion(distance_m=3.0, flow_px_per_ms=0.5, seed=4, roll_deg=40.0)
    R_level = level.pose_at(np.zeros(1))[0, :3, :3]
    R_rolled = rolled.trajectory(rig).pose_at(np.zeros(1))[0, :3, :3]
    # The extra roll turns about the optical axis: the camera's z axis stays, x turns 40 deg.
    assert np.allclose(R_level[:, 2], R_rolled[:, 2], atol=1e-9)
    assert R_level[:, 0] @ R_rolled[:, 0] == pytest.approx(math.cos(math.radians(40.0)))


def test_vignetting_dims_the_corners_by_the_set_share():
    g = Optics(vignetting=0.4).gain(SMALL).reshape(SMALL.height, SMALL.width)
    cx, cy = SMALL.K[0, 2], SMALL.K[1, 2]
    assert g.max() == pytest.approx(1.0, abs=1e-4)
    assert g.min() == pytest.approx(0.6)
    assert g[round(cy), round(cx)] == pytest.approx(1.0, abs=1e-4)
    assert np.all(Optics().gain(SMALL) == 1.0)
    with pytest.raises(ValueError, match="vignetting must be in"):
        Optics(vignetting=1.0)


def test_vignetted_corners_see_less_light_and_so_more_shot_noise(tmp_path):
    # Camera turned away from the screen: a uniform wall, shot noise only.
    away = make_pose(np.diag([-1.0, 1.0, -1.0]), [0.1, 0.1, -1.0])
    write_tum(tmp_path / "away.tum", np.array([0, 2_000_000]), np.stack([away, away]))
    sensor = replace(SensorModel.preset("ideal", lux=2000.0), shot_hz=5.0)
    motion = TumMotion(str(tmp_path / "away.tum"))

    def corner_share(vignetting: float) -> float:
        ev = concat(
            simulate(
                small_scene(motion=motion, sensor=sensor, optics=Optics(vignetting=vignetting)), 0.5
            )
        )
        r = np.hypot(ev["x"] - SMALL.K[0, 2], ev["y"] - SMALL.K[1, 2])
        return float(np.mean(r > 0.8 * r.max()))

    # A sunlit wall is as bright as the screen's white: darker pixels fire more shot noise (v2e,
    # up to 4x the bright rate).
    assert corner_share(0.9) > 1.5 * corner_share(0.0)


def test_vignetting_costs_a_dark_view_events_where_the_light_falls_off():
    # At night a pixel's log contrast between the screen's black and white shrinks as the
    # vignetting brings both towards the dark floor; near the principal point nothing changes.
    night = SensorModel(lux=0.0, dark_nits=0.2)  # no refractory period to cap the events
    display = Display(black_nits=0.05, peak_nits=2.0)
    near = StaticMotion(distance_m=1.3)  # the marker fills the view

    def per_pixel(vignetting: float) -> np.ndarray:
        scene = small_scene(
            sensor=night, display=display, motion=near, optics=Optics(vignetting=vignetting)
        )
        ev = concat(simulate(scene, 0.1))
        pix = ev["y"].astype(np.int64) * SMALL.width + ev["x"]
        return np.bincount(pix, minlength=SMALL.width * SMALL.height)

    plain, dim = per_pixel(0.0), per_pixel(0.9)
    g = Optics(vignetting=0.9).gain(SMALL)
    edge, centre = (g < 0.7) & (plain > 0), (g > 0.98) & (plain > 0)
    assert edge.sum() > 100 and centre.sum() > 100
    assert dim[edge].sum() < 0.9 * plain[edge].sum()
    assert dim[centre].sum() == pytest.approx(plain[centre].sum(), rel=0.02)


def test_the_scene_truth_scores_frames_on_the_recordings_clock():
    scene = small_scene(lead_in=LeadIn(refreshes=9), start_refresh=4, time_base_us=3_000_000_011)
    truth, enc = SceneTruth(scene), scene.encoder
    rec = simulate(scene, 0.5)
    k = next(k for k in range(4, 20) if enc.is_data_frame(k))
    t = int(rec.refresh_times_us(k, k + 1)[0] + 0.5e6 / 60)  # mid-way through its refresh
    shown = enc.geometry.payload_of(enc.frame(k))
    assert truth.errors(shown, t) == 0
    # Scored from the stream's first refresh at event time 0, it matches another frame.
    assert FrameTruth(enc, 60.0, scene.start_refresh).errors(shown, t) > 0
