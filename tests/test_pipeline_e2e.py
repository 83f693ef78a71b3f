"""End to end on the virtual event camera: detect, track, decode, recover the message."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.cli import main as cli_main
from eventocc.receiver.events import make_events
from eventocc.receiver.pipeline.config import DecoderParams, ReceiverConfig
from eventocc.receiver.pipeline.metrics import pose_errors
from eventocc.receiver.pipeline.receiver import Receiver
from eventocc.receiver.pipeline.report import FrameTruth, decode_events
from eventocc.receiver.sim import (
    Display,
    HandHeldMotion,
    Scene,
    SensorModel,
    StaticMotion,
    simulate,
)

# A small sensor whose focal length makes the 0.272 m marker fill it from 0.6 m.
CAMERA = CameraModel(346, 260, np.array([[300.0, 0, 173], [0, 300.0, 130], [0, 0, 1]]))
MESSAGE = bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8))


def _run(
    scene: Scene,
    duration_s: float,
    message_size: int | None = None,
    drop_us: tuple[int, int] | None = None,
    **told,
):
    """Decode ``scene``, less its events in ``drop_us`` (a gap in the stream); ``told``
    overrides what the receiver is told (cells, profile, ...)."""
    enc = scene.encoder
    link = {
        "cells": enc.geometry.cells,
        "profile": enc.profile.name,
        "refresh_hz": scene.display.refresh_hz,
    }
    config = ReceiverConfig(scene.camera, **{**link, **told})
    rec = simulate(scene, duration_s=duration_s, chunk_us=10_000)
    chunks = iter(rec)
    if drop_us is not None:
        chunks = (c[(c["t"] < drop_us[0]) | (c["t"] >= drop_us[1])] for c in chunks)
    truth = FrameTruth(enc, scene.display.refresh_hz, scene.start_refresh)
    return decode_events(Receiver(config, message_size=message_size), chunks, truth), rec


def _scene(
    profile: str,
    motion,
    sensor: str = "ideal",
    start_refresh: int = 0,
    cells: int = 16,
    display: Display | None = None,
    camera: CameraModel = CAMERA,
    **encoder,
) -> Scene:
    return Scene(
        encoder=StreamEncoder(MESSAGE, profile=profile, cells=cells, **encoder),
        marker_size_m=0.272,
        display=display or Display(refresh_hz=60.0),
        camera=camera,
        motion=motion,
        sensor=SensorModel.preset(sensor),
        start_refresh=start_refresh,
        seed=0,
    )


STATIC = StaticMotion(distance_m=0.6, tilt_deg=0.0, roll_deg=0.0)


def test_static_robust_locks_fast_and_recovers_the_message_with_zero_ber():
    log, rec = _run(_scene("robust", STATIC, "gen4-indoor"), 1.6)
    assert log.receiver.stats.lock_times_us[0] <= 100_000  # a few blink periods, not 0.5 s
    assert [m.message.data for m in log.messages] == [MESSAGE]
    assert log.bits > 0 and log.bit_errors == 0
    assert log.receiver.stats.losses == 0
    t = np.array(log.pose_t)
    err = np.linalg.norm(np.array(log.poses)[:, :3, 3] - rec.pose_at(t)[:, :3, 3], axis=1)
    assert err.max() < 0.01  # 1 cm from PnP on the detected locator corners at 0.6 m


def test_a_framed_frame_that_passes_its_check_counts_whatever_its_locator_reads():
    # No inner locator reads this clearly: only the frames' code and CRC can vouch for them.
    told = DecoderParams(min_locator_score=1.01)
    log, _ = _run(_scene("robust", STATIC, "gen4-indoor"), 1.6, decoder=told)
    assert [m.message.data for m in log.messages] == [MESSAGE]
    assert log.receiver.stats.losses == 0


def test_a_gap_in_the_event_stream_is_not_a_tracking_loss():
    # A camera that dropped 0.3 s of packets: its frames show nothing, not a vanished marker.
    log, _ = _run(_scene("robust", STATIC, "gen4-indoor"), 1.6, drop_us=(400_000, 700_000))
    assert log.receiver.stats.losses == 0
    assert [m.message.data for m in log.messages] == [MESSAGE]


def test_static_paper_profile_locks_in_the_preamble_and_decodes_in_order():
    # Join 1 s before the end of the blink preamble: the paper's receiver needs frames in order.
    scene = _scene("paper", STATIC, start_refresh=300, preamble=True)
    log, _ = _run(scene, 2.0, message_size=len(MESSAGE))
    assert [m.message.data for m in log.messages] == [MESSAGE]


def test_static_fast_profile_reads_toggles_of_both_polarities_byte_exact():
    log, _ = _run(_scene("fast", STATIC, "gen4-indoor"), 1.0)
    assert [m.message.data for m in log.messages] == [MESSAGE]
    assert log.bits > 0 and log.bit_errors == 0
    assert log.receiver.stats.losses == 0
    assert log.frames > 45  # one symbol per refresh since the lock, the buffered ones included


# An LCD faster than our default (rise 0.9 ms, fall 1.4 ms, scan-out over 85% of the refresh)
# and a sensor with a high threshold, so each pixel fires only a few events per switch and its
# settling towards black trails a lone OFF event into the next refreshes; the marker rolled
# and tilted, ~6 px per cell.
QUICK_LCD = Display(refresh_hz=60.0, rise_ms=0.9, fall_ms=1.4, scanout_fraction=0.85)
SPARSE = replace(
    SensorModel.preset("gen4-indoor"),
    threshold_on=1.2,
    threshold_off=1.2,
    threshold_sigma=0.04,
    refractory_us=500.0,
    shot_hz=0.15,
)
WIDE = CameraModel(480, 360, np.array([[420.0, 0, 240], [0, 420.0, 180], [0, 0, 1]]))


@pytest.mark.parametrize("profile", ["robust", "fast"])
def test_a_quick_lcd_and_a_sparse_sensor_lock_and_read_exactly(profile):
    scene = replace(
        _scene(profile, StaticMotion(0.45, tilt_deg=15, roll_deg=20), cells=32),
        display=QUICK_LCD,
        camera=WIDE,
        sensor=SPARSE,
    )
    log, _ = _run(scene, 0.5)
    stats = log.receiver.stats
    assert stats.lock_times_us and stats.lock_times_us[0] <= 100_000, stats.detection_failures
    assert log.ber is not None and log.ber < 0.01  # far below what Reed-Solomon corrects
    assert [m.message.data for m in log.messages] == [MESSAGE]


# A lens that makes 32 cells about 6 px wide on the small sensor: the paper's cell size.
CLOSE = StaticMotion(distance_m=0.35, tilt_deg=0.0, roll_deg=0.0)


def test_static_robust_at_120_hz_with_32_cells_is_error_free():
    scene = _scene("robust", CLOSE, "gen4-indoor", cells=32, display=Display(refresh_hz=120.0))
    log, _ = _run(scene, 1.0)
    assert log.ber is not None and log.ber < 0.01
    assert [m.message.data for m in log.messages] == [MESSAGE]


@pytest.mark.parametrize("profile", ["robust", "fast"])
def test_cells_twice_as_wide_as_needed_are_read_from_every_other_pixel(profile):
    # About 12 px per cell: told that 5 are enough, the receiver keeps one pixel in four.
    told = DecoderParams(read_px_per_cell=5.0)
    log, _ = _run(_scene(profile, CLOSE, "gen4-indoor"), 1.0, decoder=told)
    assert log.receiver._triage.stride == 2
    assert log.ber is not None and log.ber < 0.01
    assert [m.message.data for m in log.messages] == [MESSAGE]
    assert log.receiver.stats.losses == 0


@pytest.mark.parametrize(
    ("told", "why"),
    [
        ({"cells": 24}, "check --cells"),  # the inner locator's dashes do not fit 24 cells
        ({"refresh_hz": 50.0}, "check --refresh-hz"),  # nothing blinks at 25 Hz
    ],
)
def test_wrong_link_settings_are_reported_not_raised(told, why):
    log, _ = _run(_scene("robust", STATIC, "gen4-indoor"), 1.1, **told)
    report = log.report()
    assert not report["locked"] and not report["messages"]
    assert any(why in reason for reason in report["detection_failures"])


def test_a_dimmed_screen_is_reported_with_its_brightness_to_check():
    # A 1 kHz PWM backlight at half duty: the lit pixels fire with every PWM period, and the
    # data frames' blink never shows.
    log, _ = _run(_scene("robust", STATIC, "gen4-indoor", display=Display(pwm_hz=1000.0)), 1.1)
    report = log.report()
    assert not report["locked"] and not report["messages"]
    assert any("full brightness" in reason for reason in report["detection_failures"])


def test_wrong_profile_locks_but_never_delivers_a_wrong_message():
    log, _ = _run(_scene("fast", STATIC, "gen4-indoor"), 1.0, profile="robust")
    assert log.report()["messages"] == []  # frames fail their CRC: nothing unverified comes out


def test_the_smallest_grid_decodes():
    # 8 x 8 cells carry 8 bytes a frame: the paper's codes only (robust and fast need 12 for
    # their header and parity, and say so).
    log, _ = _run(_scene("paper", STATIC, cells=8), 2.5, message_size=len(MESSAGE))
    assert log.ber == 0.0
    assert [m.message.data for m in log.messages] == [MESSAGE]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("profile", "cells", "refresh_hz"),
    [("paper", 80, 60.0), ("robust", 64, 120.0), ("fast", 32, 240.0), ("robust", 128, 120.0)],
)
def test_full_size_sensor_decodes(profile, cells, refresh_hz):
    # The paper's setup: 1280x720 behind its lens, the marker filling the view.
    display = Display(refresh_hz=refresh_hz, rise_ms=0.5, fall_ms=0.3)  # a gaming LCD's response
    scene = _scene(
        profile,
        StaticMotion(distance_m=0.48),
        "gen4-indoor",
        cells=cells,
        display=display,
        camera=CameraModel.paper(),
        start_refresh=300 if profile == "paper" else 0,  # joins the paper's blink preamble
        preamble=profile == "paper",
    )
    log, _ = _run(scene, 1.5, message_size=len(MESSAGE))
    assert log.ber is not None and log.ber < 0.01
    assert [m.message.data for m in log.messages] == [MESSAGE]


@pytest.mark.slow
def test_hand_held_tracking_keeps_pose_error_small_and_decodes():
    log, rec = _run(
        _scene("robust", HandHeldMotion(distance_m=0.6, flow_px_per_ms=0.3, seed=0)), 2.0
    )
    t = np.array(log.pose_t)
    errors = pose_errors(t, np.array(log.poses), rec.pose_at(t))
    assert errors.ate_rmse_m < 0.02  # the paper reports 1.4-2.0 cm on real hand-held sequences
    assert [m.message.data for m in log.messages] == [MESSAGE]


@pytest.mark.slow
def test_full_size_sensor_under_hand_held_motion_locks_on_the_right_cells():
    """The paper's 1280x720 camera 0.6 m from the marker (23 px per cell) at 1 px/ms: a lock
    search sized for small cells put the pose two cells sideways, 2.6 cm off."""
    scene = _scene(
        "robust",
        HandHeldMotion(distance_m=0.6, flow_px_per_ms=1.0, seed=0),
        "gen4-indoor",
        camera=CameraModel.paper(),
    )
    log, rec = _run(scene, 1.2)
    stats = log.receiver.stats
    assert stats.lock_times_us[0] <= 100_000 and stats.losses == 0
    t = np.array(log.pose_t)
    err = np.linalg.norm(np.array(log.poses)[:, :3, 3] - rec.pose_at(t)[:, :3, 3], axis=1)
    assert err.max() < 0.01
    assert [m.message.data for m in log.messages] == [MESSAGE]


def test_noise_without_marker_reports_why_nothing_locked():
    rng = np.random.default_rng(3)
    config = ReceiverConfig(CAMERA)
    rx = Receiver(config)
    for k in range(150):
        n = 2000
        t = np.sort(rng.integers(k * 10_000, (k + 1) * 10_000, n))
        rx.push(
            make_events(t, rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n))
        )
    assert not rx.stats.lock_times_us
    assert rx.stats.detection_failures  # each reason says which stage gave up, and why


def test_decode_cli_writes_message_trajectory_and_report(tmp_path, capsys):
    from eventocc.receiver.io import write_events

    scene = _scene("robust", STATIC, cells=20)  # the link settings come from the scene
    rec = simulate(scene, duration_s=1.6, chunk_us=10_000)
    path = tmp_path / "rec.dat"
    write_events(path, rec, width=CAMERA.width, height=CAMERA.height)
    (tmp_path / "scene.json").write_text(json.dumps(scene.describe()))
    code = cli_main(
        [
            "decode",
            str(path),
            "--scene",
            str(tmp_path / "scene.json"),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert code == 0 and report["locked"]
    (message,) = report["messages"]  # checked in-band, and against the scene's message
    assert message["verified"] and message["check"] == "sender's sha256" and message["matches_sent"]
    assert report["ber"] < 0.005  # N = 20 on this small sensor misreads a few bits (0.23%)
    assert report["link"] == {
        "profile": "robust",
        "cells": 20,
        "refresh_hz": 60.0,
        "marker_size_m": 0.272,
    }
    files = list((tmp_path / "out" / "messages").iterdir())
    assert [f.read_bytes() for f in files] == [MESSAGE]
    smoothed = np.loadtxt(tmp_path / "out" / "trajectory_all.tum")
    verified = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    assert 10 < len(verified) <= len(smoothed)  # the verified ones: a still lock proves at once
    assert np.isin(verified[:, 0], smoothed[:, 0]).all()
    # The tracker's own poses (a still camera's hardly move): at the same times.
    args = ["decode", str(path), "--scene", str(tmp_path / "scene.json"), "--cells", "20"]
    assert cli_main([*args, "--pose-smoothing-ms", "0", "--out", str(tmp_path / "raw")]) == 0
    raw = np.loadtxt(tmp_path / "raw" / "trajectory_all.tum")
    assert np.array_equal(raw[:, 0], smoothed[:, 0])
    assert np.abs(raw[:, 1:4] - smoothed[:, 1:4]).max() < 1e-3
    code = cli_main([*args, "--pose-smoothing-ms", "-1", "--out", str(tmp_path / "bad")])
    assert code == 2 and "pose smoothing must be >= 0" in capsys.readouterr().err
    # An option overrides the scene: told N = 16, the receiver finds no marker of that size.
    wrong = ["decode", str(path), "--scene", str(tmp_path / "scene.json"), "--cells", "16"]
    assert cli_main([*wrong, "--out", str(tmp_path / "wrong")]) == 1
    report = json.loads((tmp_path / "wrong" / "report.json").read_text())
    assert report["link"]["cells"] == 16 and not report["messages"]


def test_decode_cli_reports_a_calibration_that_does_not_fit(tmp_path, capsys):
    path = tmp_path / "rec.dat"
    from eventocc.receiver.io import write_events

    write_events(path, [make_events([0, 10], [400, 5], [5, 5], [1, -1])], width=640, height=480)
    (tmp_path / "scene.json").write_text(json.dumps(_scene("robust", STATIC).describe()))
    code = cli_main(
        [
            "decode",
            str(path),
            "--scene",
            str(tmp_path / "scene.json"),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    assert code == 2 and "calibration" in capsys.readouterr().err


def test_poses_are_tentative_until_a_frame_proves_the_lock():
    # Unsmoothed, the lock's own pose comes out before the buffered frames are read.
    log, _ = _run(_scene("robust", STATIC, "gen4-indoor"), 0.6, pose_smoothing_us=0)
    rx = log.receiver
    verified = log.pose_verified
    assert verified[0] is False and verified[-1] is True
    assert verified == sorted(verified), "once proven, a lock's poses stay verified"
    first_verified = log.pose_t[verified.index(True)]
    assert first_verified - rx.stats.lock_times_us[0] <= 40_000  # a still lock proves at once


def test_a_lock_whose_frames_never_pass_their_check_is_dropped_within_100_ms():
    # Told robust while the screen sends fast: the marker is found, no frame ever verifies.
    log, _ = _run(_scene("fast", STATIC, "gen4-indoor"), 1.0, profile="robust")
    locks, drops = (
        log.receiver.stats.lock_times_us,
        [s.t_us for s in log.states if s.reason == "no frame passed its check since the lock"],
    )
    assert locks and drops
    assert all(0 < drop - lock <= 110_000 for lock, drop in zip(locks, drops, strict=False))
    assert not any(log.pose_verified), "no pose of an unproven lock is published as verified"


def test_a_proven_lock_whose_frames_stop_passing_goes_tentative_and_is_dropped():
    # The screen switches from robust to fast under a still camera: the ring and the 'L' stay
    # where they were, so the track holds and keeps seeing the locator, but no frame passes.
    switch_us = 400_000
    config = ReceiverConfig(CAMERA, cells=16, profile="robust", refresh_hz=60.0)
    robust, fast = (
        simulate(_scene(profile, STATIC, "gen4-indoor"), duration_s=0.8, chunk_us=10_000)
        for profile in ("robust", "fast")
    )
    chunks = [c[c["t"] < switch_us] for c in robust] + [c[c["t"] >= switch_us] for c in fast]
    log = decode_events(Receiver(config), [c for c in chunks if len(c)], None)
    t, verified = np.array(log.pose_t), np.array(log.pose_verified)
    assert verified[t < switch_us].sum() > 100, "the robust frames proved the lock"
    lapse = config.decoder.proof_lapse_us + config.frame_us
    assert not verified[t > switch_us + lapse].any()
    drops = [s.t_us for s in log.states if s.reason == "no frame passed its check lately"]
    assert drops and switch_us < drops[0] <= switch_us + lapse + config.frame_us


@pytest.mark.parametrize(("cells", "locks"), [(16, True), (64, False)])
def test_the_receiver_says_how_many_pixels_a_cell_spans_locked_or_not(cells, locks):
    """The demo's 320x180 camera 0.6 m from the marker: 16 cells read at ~5 px per cell; 64
    cells, at ~1.4, never lock, and the receiver says how small they look and why it fails."""
    from eventocc.receiver.live.virtual_camera import default_camera, virtual_sensor
    from eventocc.receiver.pipeline.decoder import cell_side_px
    from eventocc.receiver.poses import invert

    scene = _scene("robust", STATIC, cells=cells, camera=default_camera())
    scene = replace(scene, sensor=virtual_sensor())
    log, rec = _run(scene, 0.6)
    rx = log.receiver
    seen = cell_side_px(rx.config, invert(rec.pose_at(np.array([300_000]))[0]))
    assert bool(rx.stats.lock_times_us) is locks
    assert rx.cell_px == pytest.approx(seen, rel=0.1)
    if locks:
        assert rx.detection_failure is None
    else:
        assert rx.detection_failure in rx.stats.detection_failures
        assert rx.detection_failure.startswith("spatial:"), (
            "the marker blinks; its cells are unread"
        )
