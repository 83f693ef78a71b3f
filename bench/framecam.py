"""A virtual global-shutter frame camera watching a screen that plays a slideshow of 2D codes.

The baseline of the paper's comparison: a CMOS camera (120 Hz) filming QR codes, AprilTags or
ArUco markers shown one per refresh on a 60 Hz LCD. It shares the event simulator's physics where
it matters for fairness: the same camera model and motions, the same display (progressive
scan-out, exponential LCD response, panel reflection of ambient light).

An image is the mean of sub-exposure renders spread over the exposure, each the screen's current
luminance warped into the image by the plane's homography at the pose of that instant, so motion
blur and the screen changing mid-exposure both appear. Sub-steps are short enough that the code
moves at most ``max_step_px`` between them. Then lens blur, lens distortion (a remap through the
camera's undistortion table), shot and read noise, and 8-bit quantisation.

Scan-out is resolved per module row (a module row switches at its centre's screen height): a
row of modules spans a few scan lines of a real screen, far below the camera's time resolution.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.sim.display import LUX_TO_NITS_PER_REFLECTANCE, Display, settle
from eventocc.receiver.sim.motion import Trajectory, project_points

TEXTURE_PX_PER_MODULE = 8
"""Screen texture resolution: enough that warping (bilinear) keeps module edges sharp."""
WALL_REFLECTANCE = 0.5


@dataclass(frozen=True)
class Slideshow:
    """Codes shown one per display refresh, optionally with a black refresh between two codes.

    Each code is a square bool module matrix (True = white), quiet zone included; it is drawn
    ``size_m`` wide with its top-left corner at the origin of the marker frame (x right, y down),
    on a black screen ``display.margin`` x ``size_m`` wider on each side (as the event
    simulator's marker).
    """

    codes: Sequence[np.ndarray]
    size_m: float = 0.272
    blank_between: bool = False
    display: Display = field(default_factory=Display)
    lux: float = 250.0

    def __post_init__(self) -> None:
        if not len(self.codes):
            raise ValueError("a slideshow needs at least one code")
        shapes = {np.shape(c) for c in self.codes}
        first = np.shape(self.codes[0])
        if len(shapes) != 1 or len(first) != 2 or first[0] != first[1]:
            raise ValueError(f"codes must be square module matrices of one size, got {shapes}")
        if self.size_m <= 0 or self.lux < 0:
            raise ValueError(
                f"size_m must be positive and lux >= 0, got {self.size_m} m, {self.lux} lux"
            )

    @property
    def modules(self) -> int:
        return int(np.shape(self.codes[0])[0])

    def code_index(self, k: int) -> int | None:
        """Which code refresh ``k`` shows (None: a blank refresh)."""
        if self.blank_between:
            return None if k % 2 else (k // 2) % len(self.codes)
        return k % len(self.codes)

    def corners(self) -> np.ndarray:
        """(4, 3) marker-frame corners of the code: TL, TR, BR, BL."""
        s = self.size_m
        return np.array([[0, 0, 0], [s, 0, 0], [s, s, 0], [0, s, 0]], dtype=np.float64)

    @cached_property
    def _black(self) -> float:
        return self.display.black_nits + self.display.ambient_nits(self.lux)

    @property
    def wall_nits(self) -> float:
        return self.lux * WALL_REFLECTANCE * LUX_TO_NITS_PER_REFLECTANCE

    @property
    def white_nits(self) -> float:
        return self.display.peak_nits + self.display.ambient_nits(self.lux)

    def _target(self, k: int) -> np.ndarray:
        d, i = self.display, self.code_index(k)
        if i is None:
            return np.full((self.modules, self.modules), d.black_nits)
        return np.where(np.asarray(self.codes[i], bool), d.peak_nits, d.black_nits)

    def module_luminance(self, t_us: float) -> np.ndarray:
        """(modules, modules) luminance (cd/m², reflection included) at time ``t_us``; refresh 0
        starts scanning out at t = 0 after the screen settled on the last code."""
        d, n = self.display, self.modules
        m = d.margin
        v = (m + (np.arange(n) + 0.5) / n) / (1 + 2 * m)  # module rows' screen-height fraction
        k = np.floor((t_us - v * d.scan_us) / d.period_us).astype(int)
        out = np.empty((n, n))
        for row, (kr, vr) in enumerate(zip(k, v, strict=True)):
            # Two refreshes back is settled to within exp(-period / tau): negligible for LCDs.
            start = settle(self._target(kr - 2)[row], self._target(kr - 1)[row], d.period_us, d)
            out[row] = settle(
                start, self._target(kr)[row], t_us - kr * d.period_us - vr * d.scan_us, d
            )
        return out + d.ambient_nits(self.lux)

    @property
    def _margin_px(self) -> int:
        return round(self.display.margin * self.modules * TEXTURE_PX_PER_MODULE)

    def texture(self, t_us: float) -> np.ndarray:
        """float32 luminance image of the whole screen at ``t_us`` (code plus black margin)."""
        px, pad = TEXTURE_PX_PER_MODULE, self._margin_px
        code = np.kron(self.module_luminance(t_us), np.ones((px, px))).astype(np.float32)
        return cv2.copyMakeBorder(code, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=self._black)

    def texture_to_plane(self) -> np.ndarray:
        """3x3 map from texture pixel coordinates to marker-plane metres (homogeneous)."""
        scale = self.size_m / (self.modules * TEXTURE_PX_PER_MODULE)
        # Pixel centres: texture pixel i covers [i, i + 1) * scale, shifted by the margin.
        offset = (0.5 - self._margin_px) * scale
        return np.array([[scale, 0, offset], [0, scale, offset], [0, 0, 1.0]])


@dataclass(frozen=True)
class FrameCamera:
    """A global-shutter grayscale camera: same lens model as the event camera."""

    camera: CameraModel
    fps: float = 120.0
    exposure_ms: float = 4.0
    """Typical auto-exposure indoors at 120 Hz (must fit in the frame period)."""
    blur_px: float = 0.5
    """Lens point-spread standard deviation (as the event simulator's optics)."""
    full_well_e: float = 10_000.0
    read_noise_e: float = 3.0
    white_level: float = 0.8
    """Auto-exposure target: a white module fills this share of the full well."""
    max_step_px: float = 1.0
    """Longest image motion between two sub-exposure renders."""

    def __post_init__(self) -> None:
        if not 0 < self.fps <= 1000:
            raise ValueError(f"fps must be in (0, 1000], got {self.fps}")
        if not 0 < self.exposure_ms * 1e-3 * self.fps <= 1:
            raise ValueError(
                f"exposure {self.exposure_ms} ms does not fit a {self.fps} Hz "
                "frame period: lower one of them"
            )
        if self.full_well_e <= 0 or self.read_noise_e < 0 or not 0 < self.white_level <= 1:
            raise ValueError("need full_well_e > 0, read_noise_e >= 0, 0 < white_level <= 1")

    @cached_property
    def _distort_map(self) -> tuple[np.ndarray, np.ndarray] | None:
        if not self.camera.has_distortion:
            return None
        table = self.camera.undistort_table
        return table[..., 0].copy(), table[..., 1].copy()

    def _homography(self, screen: Slideshow, T_world_cam: np.ndarray) -> np.ndarray:
        T = np.linalg.inv(T_world_cam)
        plane_to_image = self.camera.K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
        return plane_to_image @ screen.texture_to_plane()

    def _substeps(self, screen: Slideshow, trajectory: Trajectory, t0: float, t1: float) -> int:
        ends = trajectory.pose_at(np.array([t0, t1]))
        moved = np.abs(
            np.diff([project_points(self.camera, T, screen.corners()) for T in ends], axis=0)
        ).max()
        # At least a few renders so screen switches inside the exposure are averaged too.
        return int(np.clip(math.ceil(moved / self.max_step_px), 4, 64))

    def capture(
        self, screen: Slideshow, trajectory: Trajectory, t_start_us: float, rng: np.random.Generator
    ) -> np.ndarray:
        """uint8 (height, width) image exposed from ``t_start_us`` for ``exposure_ms``."""
        cam = self.camera
        t_end = t_start_us + self.exposure_ms * 1e3
        n = self._substeps(screen, trajectory, t_start_us, t_end)
        times = t_start_us + (np.arange(n) + 0.5) / n * (t_end - t_start_us)
        poses = trajectory.pose_at(times)
        ideal = np.zeros((cam.height, cam.width), np.float32)
        for t, T in zip(times, poses, strict=True):
            ideal += cv2.warpPerspective(
                screen.texture(t),
                self._homography(screen, T),
                (cam.width, cam.height),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=screen.wall_nits,
            )
        ideal /= n
        if self.blur_px > 0:
            ideal = cv2.GaussianBlur(ideal, (0, 0), self.blur_px)
        if self._distort_map is not None:
            ideal = cv2.remap(ideal, *self._distort_map, cv2.INTER_LINEAR)
        electrons = ideal / screen.white_nits * self.white_level * self.full_well_e
        electrons = rng.poisson(np.maximum(electrons, 0)) + rng.normal(
            0, self.read_noise_e, electrons.shape
        )
        return np.clip(electrons / self.full_well_e * 255, 0, 255).astype(np.uint8)

    def frames(
        self, screen: Slideshow, trajectory: Trajectory, duration_s: float, seed: int = 0
    ) -> Iterator[tuple[float, np.ndarray]]:
        """(exposure start in us, image) of every frame in ``[0, duration_s)``; the camera's
        clock is not synchronised with the screen's (it starts a third of a frame in)."""
        rng = np.random.default_rng(seed)
        period = 1e6 / self.fps
        for i in range(int(duration_s * self.fps)):
            t = (i + 1 / 3) * period
            yield t, self.capture(screen, trajectory, t, rng)
