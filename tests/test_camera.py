import numpy as np
import pytest

from eventocc.receiver.camera import CameraModel


def test_projection_and_lookup_undistortion_agree():
    cam = CameraModel.paper()
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.3, 0.3, 50), np.ones(50)])
    distorted = cam.project(pts)
    ideal = cam.project(pts, distort=False)
    assert np.abs(distorted - ideal).max() > 1.0  # the lens model matters at the edges
    assert np.allclose(cam.undistort_points(distorted), ideal, atol=1e-3)
    px = np.round(distorted).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    table = cam.undistort_events(px[inside, 0], px[inside, 1])
    assert np.allclose(table, cam.undistort_points(px[inside].astype(float)), atol=1e-3)


def test_resized_keeps_the_optical_axis_in_the_centre():
    cam = CameraModel(640, 480, np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1.0]]))
    small = cam.resized(320, 240)
    assert small.K[0, 2] == 160 and small.K[1, 2] == 120
    assert np.allclose(small.project(np.array([0.0, 0.0, 1.0])), [160, 120])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"K": np.eye(2)}, "3x3"),
        ({"K": np.diag([0.0, 1.0, 1.0])}, "positive focal"),
        ({"width": 0}, "resolution"),
        ({"dist": np.zeros(3)}, "4, 5 or 8"),
    ],
)
def test_bad_calibration_is_refused(kwargs, message):
    args = {"width": 64, "height": 48, "K": np.diag([50.0, 50.0, 1.0]), "dist": np.zeros(5)}
    with pytest.raises(ValueError, match=message):
        CameraModel(**(args | kwargs))


def test_a_binned_camera_sees_the_whole_view_with_fewer_pixels():
    full = CameraModel.paper()
    binned = full.binned(320, 180)
    point = np.array([[0.1, -0.05, 0.6]])  # camera frame, metres
    # Pixel centres map as (u + 0.5) * scale - 0.5: the same ray lands on the same spot.
    assert np.allclose((full.project(point) + 0.5) / 4 - 0.5, binned.project(point))


def test_a_binned_camera_keeps_the_aspect_ratio():
    with pytest.raises(ValueError, match="aspect ratio"):
        CameraModel.paper().binned(320, 240)
