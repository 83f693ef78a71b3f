"""Where each sensor pixel looks: lens rays, pixel-area integration and lens blur.

A pixel's irradiance is the mean scene luminance over a small grid of sample rays around its
centre. The grid spacing is chosen so the grid's spatial variance equals that of the pixel's
square aperture (1/12 px² per axis) convolved with a Gaussian lens blur: the cheapest footprint
with the right width, evaluated identically for still and moving cameras.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from receiver.camera import CameraModel


@dataclass(frozen=True)
class Optics:
    blur_px: float = 0.5
    """Standard deviation of the lens point-spread function (an f/8 lens on 4.86 um Gen4 pixels
    is near the diffraction limit, about one pixel wide)."""
    supersample: int = 3
    """Sample rays per pixel along each axis."""

    def __post_init__(self) -> None:
        if self.blur_px < 0:
            raise ValueError(f"blur_px must be >= 0, got {self.blur_px}")
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample must be 1..8, got {self.supersample}")

    def offsets(self) -> np.ndarray:
        """(S, 2) sample offsets in pixels around a pixel centre."""
        n = self.supersample
        if n == 1:
            return np.zeros((1, 2))
        spacing = math.sqrt((1.0 + 12.0 * self.blur_px**2) / (n * n - 1))
        g = (np.arange(n) - (n - 1) / 2) * spacing
        gx, gy = np.meshgrid(g, g)
        return np.column_stack([gx.ravel(), gy.ravel()])

    def to_dict(self) -> dict:
        return asdict(self)


def centre_rays(camera: CameraModel, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, 2) normalised ray directions (x/z, y/z, camera frame) through pixel centres."""
    ideal = camera.undistort_table[y, x].astype(np.float64)
    return (ideal - camera.K[:2, 2]) / camera.K[[0, 1], [0, 1]]


def sample_offsets(camera: CameraModel, optics: Optics) -> np.ndarray:
    """(S, 2) footprint offsets in normalised ray units. They are applied in undistorted space:
    the lens is locally a similarity at the scale of a pixel."""
    return optics.offsets() / camera.K[[0, 1], [0, 1]]


def sample_rays(camera: CameraModel, optics: Optics, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n, S, 2) normalised ray directions of the footprint samples of pixels (x, y)."""
    return centre_rays(camera, x, y)[:, None, :] + sample_offsets(camera, optics)[None]


def rays_to_plane(rays: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(..., 2) marker-plane points (z = 0) hit by normalised rays (..., 2); NaN where a ray
    misses the plane (points behind the camera)."""
    R, C = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = rays[..., 0:1] * R[:, 0] + rays[..., 1:2] * R[:, 1] + R[:, 2]  # (..., 3) world
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -C[2] / d[..., 2]
    s = np.where(s > 0, s, np.nan)
    return C[:2] + s[..., None] * d[..., :2]
