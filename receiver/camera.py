"""Pinhole camera with plumb_bob (radtan) distortion: projection and fast event undistortion."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

# The paper's receiver: Prophesee Gen4 1280x720 behind a Kowa LM5JCM (authors' default.yaml).
PAPER_K = np.array([[1033.689, 0.0, 624.771], [0.0, 1037.050, 321.822], [0.0, 0.0, 1.0]])
PAPER_DIST = np.array([-0.032681, 0.066110, 0.001529, 0.000190, 0.0])


@dataclass(frozen=True, eq=False)
class CameraModel:
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, dtype=np.float64).ravel()
        if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(
                f"K must be a 3x3 intrinsic matrix with positive focal lengths, got {K}"
            )
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"resolution must be positive, got {self.width}x{self.height}")
        if dist.size not in (4, 5, 8):
            raise ValueError(f"distortion must have 4, 5 or 8 coefficients, got {dist.size}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)

    @classmethod
    def paper(cls) -> CameraModel:
        return cls(1280, 720, PAPER_K, PAPER_DIST)

    def resized(self, width: int, height: int) -> CameraModel:
        """The same lens on a smaller or larger sensor of the same pixel pitch (centred crop)."""
        K = self.K.copy()
        K[0, 2] += (width - self.width) / 2
        K[1, 2] += (height - self.height) / 2
        return CameraModel(width, height, K, self.dist)

    def binned(self, width: int, height: int) -> CameraModel:
        """The whole field of view on ``width`` x ``height`` pixels, as if binned: the same
        angles on fewer pixels (``resized`` keeps the pixel pitch and crops the view)."""
        s = height / self.height
        if abs(width - self.width * s) > 1:
            raise ValueError(
                f"a binned sensor keeps the {self.width}x{self.height} aspect ratio; "
                f"{width}x{height} does not"
            )
        K = self.K.copy()
        K[:2, :2] *= s
        K[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5  # pixel centres at integer coordinates
        return CameraModel(width, height, K, self.dist)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist))

    def project(self, points_cam: np.ndarray, distort: bool = True) -> np.ndarray:
        """Pixel coordinates (..., 2) of camera-frame points (..., 3) with z > 0."""
        p = np.asarray(points_cam, dtype=np.float64)
        xy = p[..., :2] / p[..., 2:3]
        if distort and self.has_distortion:
            xy = self._distort_normalised(xy)
        return xy * self.K[[0, 1], [0, 1]] + self.K[:2, 2]

    def _distort_normalised(self, xy: np.ndarray) -> np.ndarray:
        k1, k2, p1, p2 = self.dist[:4]
        k3 = self.dist[4] if self.dist.size > 4 else 0.0
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], -1)

    def undistort_points(self, xy: np.ndarray) -> np.ndarray:
        """Ideal (undistorted) pixel coordinates of distorted pixel coordinates (..., 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        if not self.has_distortion:
            return xy.copy()
        out = cv2.undistortPoints(xy.reshape(-1, 1, 2), self.K, self.dist, P=self.K)
        return out.reshape(xy.shape)

    @cached_property
    def undistort_table(self) -> np.ndarray:
        """(height, width, 2) float32 lookup: ideal pixel coordinates of every sensor pixel, so
        per-event undistortion is one gather."""
        ys, xs = np.mgrid[0 : self.height, 0 : self.width]
        grid = np.stack([xs, ys], -1).astype(np.float64)
        return self.undistort_points(grid).astype(np.float32)

    def undistort_events(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n, 2) float32 ideal coordinates of integer event pixels."""
        return self.undistort_table[y, x]
