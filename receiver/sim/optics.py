"""Where each sensor pixel looks: lens rays, pixel-area integration and lens blur.

A pixel's irradiance is the mean scene luminance over a small grid of sample rays around its
centre. The grid spacing is chosen so the grid's spatial variance equals that of the pixel's
square aperture (1/12 px² per axis) convolved with a Gaussian lens blur: the cheapest footprint
with the right width, evaluated identically for still and moving cameras.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numba
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
    rays = np.asarray(rays, dtype=np.float64)
    flat = np.ascontiguousarray(rays.reshape(-1, 2))
    T = np.ascontiguousarray(T_world_cam, dtype=np.float64)
    return _rays_to_plane(flat, T[:3, :3].copy(), T[:3, 3].copy()).reshape(rays.shape)


@numba.njit(cache=True, inline="always")
def plane_point(rx, ry, R, C):
    """Marker-plane point (x, y) hit by the normalised ray (rx, ry) of a camera with rotation
    ``R`` and centre ``C`` (world frame); NaN if the ray misses the plane."""
    dx = R[0, 0] * rx + R[0, 1] * ry + R[0, 2]
    dy = R[1, 0] * rx + R[1, 1] * ry + R[1, 2]
    dz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2]
    s = -C[2] / dz if dz != 0.0 else -1.0
    if s <= 0.0:
        return np.nan, np.nan
    return C[0] + s * dx, C[1] + s * dy


@numba.njit(cache=True)
def _rays_to_plane(rays, R, C):
    out = np.empty_like(rays)
    for j in range(rays.shape[0]):
        out[j, 0], out[j, 1] = plane_point(rays[j, 0], rays[j, 1], R, C)
    return out
