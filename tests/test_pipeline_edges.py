"""Sub-pixel locator corners (``edges``) on hand-made images of in-phase pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from eventocc.occ.marker import MarkerGeometry
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.edges import refine_corners
from eventocc.receiver.pipeline.locate import outline, quadrilateral

CAMERA = CameraModel(
    640,
    480,
    np.array([[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]]),
    np.array([-0.2, 0.05, 0, 0, 0]),
)
_SUPER = 4
"""Sub-pixel samples per pixel side when the lit cells are rendered."""


def _lit_image(
    geometry: MarkerGeometry,
    corners: np.ndarray,
    spread_px: float,
    fill: float,
    seed: int,
    ring: np.ndarray | None = None,
) -> np.ndarray:
    """What fires with the bursts: the locator and a random payload seen through ``corners``
    (ideal pixels, TL, TR, BR, BL), the lit area grown by about ``spread_px`` on every side
    (blur seen through a log response), a share ``fill`` of its pixels firing; ``ring``, the
    cells shown in place of the locator's ring."""
    rng = np.random.default_rng(seed)
    cells = geometry.inner_locator.copy() if ring is None else ring.copy()
    n = geometry.cells
    cells[1:-1, 1:-1] = rng.random((n, n)) < 0.5
    side = geometry.locator_side
    square = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
    H = cv2.getPerspectiveTransform(square, corners.astype(np.float32))
    h, w = CAMERA.height * _SUPER, CAMERA.width * _SUPER
    ys, xs = np.mgrid[0:h, 0:w]
    ideal = np.stack([xs, ys], -1).reshape(-1, 1, 2).astype(np.float64) / _SUPER + (
        0.5 / _SUPER - 0.5
    )
    # Each sensor sub-sample sees the ideal point that the lens maps onto it.
    ideal = CAMERA.undistort_points(ideal.reshape(-1, 2))
    uv = cv2.perspectiveTransform(ideal.reshape(-1, 1, 2), np.linalg.inv(H)).reshape(h, w, 2)
    inside = (uv >= 0).all(-1) & (uv < side).all(-1)
    col = np.clip(uv[..., 0].astype(int), 0, side - 1)
    row = np.clip(uv[..., 1].astype(int), 0, side - 1)
    light = (inside & cells[row, col]).astype(np.float32)
    light = light.reshape(CAMERA.height, _SUPER, CAMERA.width, _SUPER).mean(axis=(1, 3))
    # A Gaussian edge blurred by sigma reaches 5% of the light at 1.64 sigma out.
    blurred = cv2.GaussianBlur(light, (0, 0), spread_px / 1.64)
    lit = blurred >= 0.05
    return (lit & (rng.random(lit.shape) < fill)).astype(np.float32)


IDEAL = np.array([[210.0, 130.0], [395.0, 152.0], [380.0, 335.0], [196.0, 318.0]])
"""A locator of about 10 px per cell, turned and seen at a slant (ideal pixels)."""


def _corners(lit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outline's corners, the refined ones and the truth (distorted pixels, TL first)."""
    xy = (IDEAL - CAMERA.K[:2, 2]) / CAMERA.K[0, 0]
    truth = CAMERA.project(np.c_[xy, np.ones(4)])
    outlined = quadrilateral(outline(lit > 0))
    outlined = np.roll(outlined, -int(np.argmin(np.linalg.norm(outlined - truth[0], axis=1))), 0)
    return outlined, refine_corners(outlined, lit, MarkerGeometry(16), CAMERA), truth


@pytest.mark.parametrize("spread_px", [0.3, 1.2, 2.0])
def test_corners_come_back_to_the_true_edges_whatever_the_spread(spread_px):
    outlined, refined, truth = _corners(_lit_image(MarkerGeometry(16), IDEAL, spread_px, 1.0, 3))
    rough, fine = (np.abs(q - truth).max() for q in (outlined, refined))
    assert fine < 0.3, (rough, fine)
    if spread_px >= 1.0:
        assert fine < rough / 3, (rough, fine)


def test_sparse_firing_leaves_the_corners_nearer_the_truth_than_the_outline():
    # A pixel that fires now and then leaves holes: each cell's edge is noisy, not biased.
    rough, fine = [], []
    for seed in range(4):
        outlined, refined, truth = _corners(_lit_image(MarkerGeometry(16), IDEAL, 1.5, 0.7, seed))
        rough.append(np.linalg.norm(outlined - truth, axis=1).mean())
        fine.append(np.linalg.norm(refined - truth, axis=1).mean())
    assert np.mean(fine) < 0.6 and np.mean(fine) < 0.6 * np.mean(rough), (rough, fine)


def test_an_image_that_cannot_say_leaves_the_corners_as_they_were():
    geometry = MarkerGeometry(16)
    corners = IDEAL.copy()
    empty = np.zeros((CAMERA.height, CAMERA.width), np.float32)
    assert refine_corners(corners, empty, geometry, CAMERA) is corners


def test_a_border_that_is_not_the_locators_leaves_the_corners_as_they_were():
    # What frames mixed in a window look like: the border cells lit at random, not as the
    # locator's dashes and 'L'.
    geometry = MarkerGeometry(16)
    ring = np.random.default_rng(5).random((18, 18)) < 0.5
    lit = _lit_image(geometry, IDEAL, 1.2, 1.0, 3, ring=ring)
    corners = quadrilateral(outline(lit > 0))
    assert refine_corners(corners, lit, geometry, CAMERA) is corners
