"""The experiments' command end to end at a tiny scale, and the virtual frame camera."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from bench.__main__ import main
from bench.experiments.baselines import code_families, run_frame_baseline
from bench.experiments.eventcam import EventRun, camera
from bench.experiments.streaming import FIT_SHARE, PAPER_CELL_PX, cell_px, paper_cell_px
from bench.framecam import FrameCamera, Slideshow
from bench.tracking import POSE_GAP_US
from eventocc.occ.marker import MarkerGeometry
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.sim.motion import Rig, StaticMotion

CAMERA = CameraModel.paper().resized(480, 360)


def _trajectory(screen: Slideshow, distance_m: float = 1.6):
    s = screen.size_m
    return StaticMotion(distance_m).trajectory(
        Rig(CAMERA, np.array([s / 2, s / 2, 0.0]), screen.corners())
    )


def test_tiny_run_writes_reports_and_plots(tmp_path):
    main(["--scale", "tiny", "--out", str(tmp_path), "--jobs", "2"])
    for png in ("streaming.png", "comparison.png"):
        image = cv2.imread(str(tmp_path / png))
        assert image is not None and image.shape[0] > 200 and image.std() > 0, png
    results = tmp_path / "RESULTS.md"
    text = results.read_text()
    assert text.startswith("# What we measured") and "Machine:" in text
    bench_md = (tmp_path / "BENCHMARKS.md").read_text()
    for name in ("streaming", "localization", "comparison"):
        assert f"<!-- bench:paper_{name} -->" in bench_md
        assert json.loads((tmp_path / "results" / f"{name}.json").read_text()) is not None
    compared = json.loads((tmp_path / "results" / "comparison.json").read_text())
    systems = {r["system"] for r in compared}
    assert {"QR v1-L", "QR v1-L + blank", "ours (events, N=16, paper)"} <= systems
    for row in compared:
        tracking = row["tracking"]
        if row["system"].startswith("ours"):  # why frames were missed: lock, losses, tracking
            assert 0 <= tracking["tracked_wrong"] <= tracking["tracked"] <= 1
            assert tracking["losses"] >= 0
            # A frame read bit-exact passes its FEC too; `paper` frames count only bit-exact.
            exact, got = np.array(row["exact"], bool), np.array(row["received"], bool)
            assert exact.shape == got.shape and not np.any(exact & ~got)
            if row["system"].endswith("paper)"):
                assert np.array_equal(exact, got)
        else:
            assert tracking is None
    # Rerunning one experiment keeps the others' sections; one job gives the same results.
    comparison = (tmp_path / "results" / "comparison.json").read_text()
    main(["--scale", "tiny", "--out", str(tmp_path), "--only", "comparison", "--jobs", "1"])
    assert (tmp_path / "results" / "comparison.json").read_text() == comparison
    assert "<!-- bench:paper_streaming -->" in results.read_text()


@pytest.mark.parametrize("family", code_families(), ids=lambda f: f.name)
def test_static_code_decodes(family):
    # One code on every refresh: with a new code per refresh, the progressive scan-out shows
    # the top of one code above the bottom of the previous one at any instant.
    screen = Slideshow([family.draw(7)])
    image = FrameCamera(CAMERA).capture(
        screen, _trajectory(screen), 4000.0, np.random.default_rng(0)
    )
    assert image.dtype == np.uint8 and image.shape == (CAMERA.height, CAMERA.width)
    assert family.read(image) == {7}


def test_heavy_blur_defeats_qr():
    qr = code_families()[0]
    screen = Slideshow([qr.draw(0)])  # one code, so only the blur can stop the decoder
    still = FrameCamera(CAMERA)
    blurred = FrameCamera(CAMERA, blur_px=12.0)
    rng = np.random.default_rng(0)
    assert qr.read(still.capture(screen, _trajectory(screen), 0.0, rng)) == {0}
    assert qr.read(blurred.capture(screen, _trajectory(screen), 0.0, rng)) == set()


def test_blank_refreshes_alternate_with_codes():
    screen = Slideshow([np.ones((5, 5), bool)] * 3, blank_between=True)
    assert [screen.code_index(k) for k in range(5)] == [0, None, 1, None, 2]


@pytest.mark.parametrize(
    "bad",
    [
        {"codes": []},
        {"codes": [np.ones((4, 5), bool)]},
        {"codes": [np.ones((5, 5), bool)], "size_m": 0.0},
    ],
)
def test_slideshow_rejects_bad_input(bad):
    with pytest.raises(ValueError):
        Slideshow(**bad)


def test_exposure_longer_than_frame_is_rejected():
    with pytest.raises(ValueError, match="does not fit"):
        FrameCamera(CAMERA, fps=120.0, exposure_ms=10.0)


def test_clip_longer_than_the_code_space_is_rejected():
    apriltag = code_families()[1]
    with pytest.raises(ValueError, match="shorten the clip"):
        run_frame_baseline(apriltag, False, 1.0, 0, 60.0, (320, 180))


@pytest.mark.parametrize("sensor", [None, (480, 270)])
def test_streaming_marker_fits_the_view_at_the_papers_cell_size_or_less(sensor):
    cam = camera(sensor)
    for cells in PAPER_CELL_PX:
        px = cell_px(cells, cam)
        assert px <= paper_cell_px(cells, cam)
        assert px * MarkerGeometry(cells).tracked_side <= FIT_SHARE * cam.height + 1e-9
    # N = 16's white ring fits at (almost) the paper's size; N = 96's needs smaller cells.
    assert cell_px(16, cam) > 0.95 * paper_cell_px(16, cam)
    assert cell_px(96, cam) < 0.8 * paper_cell_px(96, cam)


def _run(messages: list[dict], first_read_s: float | None) -> EventRun:
    none = np.empty((0, 4, 4))
    return EventRun(
        {"messages": messages}, np.empty(0), none, none, np.empty((0, 3)), first_read_s, 0
    )


def test_goodput_counts_the_frames_that_carried_the_message():
    done = {"verified": False, "check": "unchecked", "matches_sent": True, "t_s": 1.0}
    # 8000 bits over the frames from 0.2 s to 1.0 s plus the last frame's own 0.2 s.
    assert _run([done], 0.2).goodput_bps(8000, 0.2) == pytest.approx(8000)
    # A message other than the one sent counts for nothing, whatever its checks said.
    wrong = {**done, "verified": True, "matches_sent": False}
    assert _run([wrong], 0.2).goodput_bps(8000, 0.2) == 0.0
    assert _run([], None).goodput_bps(8000, 0.2) == 0.0


def test_tracked_time_counts_each_pose_until_the_next_but_not_across_a_loss():
    t = np.array([0, 1000, 2000, 12_000, 13_000])  # 10 ms without a pose: the lock was lost
    truth = np.repeat(np.eye(4)[None], len(t), axis=0)
    poses = truth.copy()
    poses[1, 0, 3] = 0.2  # one pose 20 cm off
    run = EventRun({}, t, poses, truth, np.empty((0, 3)), None, 0)
    assert run.tracked_s() == pytest.approx((1 + 1 + POSE_GAP_US / 1000 + 1) / 1000)
    assert run.tracked_s(wrong=True) == pytest.approx(0.001)


def test_pose_errors_match_evo():
    """ATE and RPE as the paper computes them with evo (optional: skipped where it is missing)."""
    pytest.importorskip("evo")
    from evo.core import metrics as evo_metrics
    from evo.core.trajectory import PoseTrajectory3D
    from scipy.spatial.transform import Rotation

    from bench.experiments.localization import RPE_DELTA_US
    from eventocc.receiver.pipeline.metrics import pose_errors

    rng = np.random.default_rng(0)
    n = 360
    t_us = np.arange(n) * RPE_DELTA_US
    truth = np.tile(np.eye(4), (n, 1, 1))
    truth[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(0, 3e-3, (n, 3)), 0)).as_matrix()
    truth[:, :3, 3] = np.cumsum(rng.normal(0, 1e-3, (n, 3)), 0) + np.array([0.1, 0.1, -0.6])
    estimate = truth.copy()
    estimate[:, :3, :3] = (
        truth[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 4e-3, (n, 3))).as_matrix()
    )
    estimate[:, :3, 3] += rng.normal(0, 5e-3, (n, 3))
    offset = np.eye(4)  # a rigid offset that the alignment must remove
    offset[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix()
    offset[:3, 3] = [0.3, -0.1, 0.2]
    estimate = offset @ estimate
    ours = pose_errors(t_us, estimate, truth, delta_us=RPE_DELTA_US)

    ref = PoseTrajectory3D(poses_se3=list(truth), timestamps=t_us / 1e6)
    est = PoseTrajectory3D(poses_se3=list(estimate), timestamps=t_us / 1e6)
    est.align(ref, correct_scale=False)
    relation, rmse = evo_metrics.PoseRelation, evo_metrics.StatisticsType.rmse
    ape = evo_metrics.APE(relation.translation_part)
    rpe_t = evo_metrics.RPE(relation.translation_part, 1, evo_metrics.Unit.frames)
    rpe_r = evo_metrics.RPE(relation.rotation_angle_deg, 1, evo_metrics.Unit.frames)
    for metric in (ape, rpe_t, rpe_r):
        metric.process_data((ref, est))
    assert ours.ate_rmse_m == pytest.approx(ape.get_statistic(rmse), rel=1e-6)
    assert ours.rpe_trans_rmse_m == pytest.approx(rpe_t.get_statistic(rmse), rel=1e-6)
    assert ours.rpe_rot_rmse_deg == pytest.approx(rpe_r.get_statistic(rmse), rel=1e-6)
