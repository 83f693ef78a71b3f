"""Calibration files: every layout round-trips; a bad field is named in the error."""

from __future__ import annotations

import numpy as np
import pytest

from eventocc.receiver.calibration import CalibrationError, load_calibration, save_calibration
from eventocc.receiver.camera import CameraModel

ROS_YAML = """image_width: 1280
image_height: 720
camera_name: prophesee
camera_matrix:
  rows: 3
  cols: 3
  data: [1033.689, 0, 624.771, 0, 1037.05, 321.822, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.032681, 0.06611, 0.001529, 0.00019, 0]
"""


def assert_same(a: CameraModel, b: CameraModel) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.K, b.K)
    np.testing.assert_allclose(a.dist, b.dist)


def test_ros_camera_info(tmp_path):
    (tmp_path / "ost.yaml").write_text(ROS_YAML)
    assert_same(load_calibration(tmp_path / "ost.yaml"), CameraModel.paper())


@pytest.mark.parametrize(
    ("name", "fmt"),
    [("c.yaml", "ros"), ("c.yaml", "opencv"), ("c.json", "opencv"), ("c.yaml", "eventocc")],
)
def test_round_trip(tmp_path, name, fmt):
    save_calibration(CameraModel.paper(), tmp_path / name, format=fmt)
    assert_same(load_calibration(tmp_path / name), CameraModel.paper())


def test_authors_camera_block(tmp_path):
    (tmp_path / "default.yaml").write_text(
        "sender: {frequency: 30}\ncamera:\n  width: 1280\n  height: 720\n  fx: 1033.689\n"
        "  fy: 1037.050\n  cx: 624.771\n  cy: 321.822\n  distortion_model: plumb_bob\n"
        "  distortion_coeffs: [-0.032681, 0.066110, 0.001529, 0.000190, 0.0]\n"
    )
    assert_same(load_calibration(tmp_path / "default.yaml"), CameraModel.paper())


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (("image_width: 1280\n", ""), "image_width"),
        (
            ("data: [1033.689, 0, 624.771, 0, 1037.05, 321.822, 0, 0, 1]", "data: [1, 2]"),
            "camera_matrix.data",
        ),
        (("plumb_bob", "equidistant"), "distortion_model"),
        (
            ("data: [-0.032681, 0.06611, 0.001529, 0.00019, 0]", "data: [a, b]"),
            "distortion_coefficients.data",
        ),
        (("image_height: 720", "image_height: -5"), "image_height"),
    ],
)
def test_bad_field_is_named(tmp_path, edit, field):
    (tmp_path / "bad.yaml").write_text(ROS_YAML.replace(*edit))
    with pytest.raises(CalibrationError, match=field.replace(".", r"\.")):
        load_calibration(tmp_path / "bad.yaml")


def test_opencv_missing_matrix(tmp_path):
    (tmp_path / "cv.yaml").write_text("%YAML:1.0\n---\nimage_width: 10\nimage_height: 10\n")
    with pytest.raises(CalibrationError, match="camera_matrix"):
        load_calibration(tmp_path / "cv.yaml")
