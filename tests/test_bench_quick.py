"""The experiments' command end to end at a tiny scale, and the virtual frame camera."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from bench.__main__ import main
from bench.experiments.baselines import code_families, run_frame_baseline
from bench.framecam import FrameCamera, Slideshow
from receiver.camera import CameraModel
from receiver.sim.motion import Rig, StaticMotion

CAMERA = CameraModel.paper().resized(480, 360)


def _trajectory(screen: Slideshow, distance_m: float = 1.6):
    s = screen.size_m
    return StaticMotion(distance_m).trajectory(
        Rig(CAMERA, np.array([s / 2, s / 2, 0.0]), screen.corners())
    )


def test_tiny_run_writes_reports_and_plots(tmp_path):
    main(["--scale", "tiny", "--out", str(tmp_path)])
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
    systems = {
        r["system"] for r in json.loads((tmp_path / "results" / "comparison.json").read_text())
    }
    assert {"QR v1-L", "QR v1-L + blank", "ours (events, N=16)"} <= systems
    # Rerunning one experiment keeps the others' sections.
    main(["--scale", "tiny", "--out", str(tmp_path), "--only", "streaming"])
    assert "<!-- bench:paper_comparison -->" in results.read_text()


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
