"""Where each sensor pixel looks: lens rays, pixel-area integration, lens blur and vignetting.

A pixel's irradiance is the mean scene luminance over a small grid of sample rays around its
centre. The grid spacing is chosen so the grid's spatial variance equals that of the pixel's
square aperture (1/12 px² per axis) convolved with a Gaussian lens blur: the cheapest footprint
with the right width, the same for still and moving cameras (a moving camera places the samples
with the ray-to-plane map linearised at the pixel centre, which moves them by ~1e-3 px).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numba
import numpy as np

from eventocc.receiver.camera import CameraModel


@dataclass(frozen=True)
class Optics:
    blur_px: float = 0.5
    """Standard deviation of the lens point-spread function (an f/8 lens on 4.86 um Gen4 pixels
    is near the diffraction limit, about one pixel wide)."""
    supersample: int = 3
    """Sample rays per pixel along each axis."""
    defocus_px: float = 0.0
    """Diameter of the defocus blur circle (a uniform disk), in pixels."""
    psf_step_px: float | None = None
    """A still camera samples the whole point-spread function (pixel aperture, Gaussian blur,
    defocus disk), tails included, on a grid of this pitch, each sample weighted by the light
    that lands there (``psf``). None: the footprint grid of ``supersample`` rays, spaced to the
    PSF's variance (a moving camera always takes that)."""
    vignetting: float = 0.0
    """Share of the scene's light lost at the image's corners: a pixel at distance r from the
    principal point gets ``1 - vignetting * (r / r_corner)^2`` of it (the farthest corner's
    r_corner). It dims the scene, not the sensor's dark floor, so a pixel's contrast between
    dark levels and its shot noise change while its events between bright ones barely do."""

    def __post_init__(self) -> None:
        if self.blur_px < 0:
            raise ValueError(f"blur_px must be >= 0, got {self.blur_px}")
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"supersample must be 1..8, got {self.supersample}")
        if self.defocus_px < 0:
            raise ValueError(f"defocus_px must be >= 0, got {self.defocus_px}")
        if self.psf_step_px is not None and not 0.2 <= self.psf_step_px <= 1.0:
            raise ValueError(f"psf_step_px must be 0.2 ... 1 px or None, got {self.psf_step_px}")
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")

    @classmethod
    def preset(cls, sensor_preset: str) -> Optics:
        """The lens that goes with a sensor preset (``SensorModel.preset``): the EVK4's for
        ``evk4`` and its variants, the default lens for every other."""
        return EVK4_LENS if sensor_preset.startswith("evk4") else cls()

    def offsets(self) -> np.ndarray:
        """(S, 2) sample offsets in pixels around a pixel centre."""
        n = self.supersample
        if n == 1:
            return np.zeros((1, 2))
        # A uniform disk of diameter D has variance D² / 16 along each axis.
        variance = self.blur_px**2 + self.defocus_px**2 / 16
        spacing = math.sqrt((1.0 + 12.0 * variance) / (n * n - 1))
        g = (np.arange(n) - (n - 1) / 2) * spacing
        gx, gy = np.meshgrid(g, g)
        return np.column_stack([gx.ravel(), gy.ravel()])

    @property
    def psf_reach_px(self) -> float:
        """How far from a pixel's centre its sampled PSF reaches."""
        return 0.5 + 4.0 * self.blur_px + self.defocus_px / 2

    def psf(self) -> tuple[np.ndarray, np.ndarray]:
        """(S, 2) sample offsets in pixels and (S,) weights summing to 1: the light of a point
        spread over the pixel's square aperture, the Gaussian blur and the defocus disk,
        binned on a ``psf_step_px`` grid out to 4 sigma of the blur (samples that receive no
        light are left out; the light beyond the grid goes to its border). The bins are filled by
        a pseudo-random draw of fixed seed, so the same optics always give the same weights."""
        if self.psf_step_px is None:
            offsets = self.offsets()
            return offsets, np.full(len(offsets), 1.0 / len(offsets))
        step = self.psf_step_px
        half = math.ceil(self.psf_reach_px / step - 0.5)
        draws = 1 << 18
        rng = np.random.default_rng(0)
        points = rng.uniform(-0.5, 0.5, (draws, 2)) + self.blur_px * rng.standard_normal((draws, 2))
        if self.defocus_px > 0:
            r = self.defocus_px / 2 * np.sqrt(rng.random(draws))
            a = 2 * np.pi * rng.random(draws)
            points += np.column_stack([r * np.cos(a), r * np.sin(a)])
        bins = np.clip(np.rint(points / step).astype(int), -half, half) + half
        side = 2 * half + 1
        counts = np.bincount(bins[:, 1] * side + bins[:, 0], minlength=side * side)
        g = (np.arange(side) - half) * step
        gx, gy = np.meshgrid(g, g)
        lit = counts > 0
        return np.column_stack([gx.ravel(), gy.ravel()])[lit], counts[lit] / draws

    def gain(self, camera: CameraModel) -> np.ndarray:
        """(height * width,) share of the scene's light each pixel gets (row-major)."""
        ys, xs = np.divmod(np.arange(camera.width * camera.height), camera.width)
        r2 = (xs - camera.K[0, 2]) ** 2 + (ys - camera.K[1, 2]) ** 2
        return 1.0 - self.vignetting * r2 / r2.max()

    def to_dict(self) -> dict:
        return asdict(self)


EVK4_LENS = Optics(
    # The paper's lens: f = 1034 px (the authors' calibration) x 4.86 um = 5.0 mm. Our
    # assumptions, no datasheet: a machine-vision lens at f/1.6 whose aberrations and the
    # pixels' crosstalk blur like a Gaussian of 0.7 px (MTF50 near 55 lp/mm, half the
    # sensor's Nyquist frequency), focused at 1 m: at 1.25 m the thin-lens blur circle is
    # f² |s - s0| / (N s (s0 - f)) = 3.1 um = 0.65 px across.
    blur_px=0.7,
    defocus_px=0.65,
    psf_step_px=0.5,
)


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


POSE_R, POSE_C = 0, 9
"""Columns of a flat pose (``flat_poses``): R row-major from ``POSE_R``, C from ``POSE_C``."""


def flat_poses(T_world_cam: np.ndarray) -> np.ndarray:
    """(n, 12) rows ``[R row-major, C]`` of poses T_world_cam (n, 4, 4) or (4, 4): the layout
    ``plane_point`` reads (one array, which numba passes cheaply)."""
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    return np.ascontiguousarray(np.column_stack([T[:, :3, :3].reshape(-1, 9), T[:, :3, 3]]))


def rays_to_plane(rays: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(..., 2) marker-plane points (z = 0) hit by normalised rays (..., 2); NaN where a ray
    misses the plane (points behind the camera)."""
    rays = np.asarray(rays, dtype=np.float64)
    flat = np.ascontiguousarray(rays.reshape(-1, 2))
    return _rays_to_plane(flat, flat_poses(T_world_cam)).reshape(rays.shape)


@numba.njit(cache=True, inline="always")
def plane_point(rx, ry, poses, s):
    """Marker-plane point (x, y) hit by the normalised ray (rx, ry) of the camera at row ``s``
    of ``poses`` (``flat_poses``, or any array whose first columns are laid out so); NaN if the
    ray misses the plane."""
    r, c = POSE_R, POSE_C
    dx = poses[s, r] * rx + poses[s, r + 1] * ry + poses[s, r + 2]
    dy = poses[s, r + 3] * rx + poses[s, r + 4] * ry + poses[s, r + 5]
    dz = poses[s, r + 6] * rx + poses[s, r + 7] * ry + poses[s, r + 8]
    d = -poses[s, c + 2] / dz if dz != 0.0 else -1.0
    if d <= 0.0:
        return np.nan, np.nan
    return poses[s, c] + d * dx, poses[s, c + 1] + d * dy


@numba.njit(cache=True)
def _rays_to_plane(rays, poses):
    out = np.empty_like(rays)
    for j in range(rays.shape[0]):
        out[j, 0], out[j, 1] = plane_point(rays[j, 0], rays[j, 1], poses, 0)
    return out
