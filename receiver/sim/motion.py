"""Camera motion relative to the marker: ground-truth ``T_world_cam`` at any time.

The world frame is the marker frame (origin at the white ring's top-left outer corner, x right,
y down, z into the screen). A motion is a recipe; ``trajectory(rig)`` binds it to the marker size
and camera and returns a function of time.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.poses import invert, make_pose, read_tum


@dataclass(frozen=True)
class Rig:
    """What a motion needs to know about the scene."""

    camera: CameraModel
    centre: np.ndarray
    """Marker centre, marker frame (metres)."""
    corners: np.ndarray
    """(4, 3) outer corners of the whole marker, marker frame."""


class Trajectory(Protocol):
    is_static: bool

    def pose_at(self, t_us: np.ndarray) -> np.ndarray:
        """(n, 4, 4) T_world_cam at times ``t_us`` (microseconds since the simulation start)."""
        ...


def look_at(centre: np.ndarray, distance_m, tilt_deg, elevation_deg, roll_deg) -> np.ndarray:
    """T_world_cam of a camera ``distance_m`` from ``centre`` looking at it, swung
    ``tilt_deg`` about the marker's vertical axis and ``elevation_deg`` about its horizontal
    one, rolled ``roll_deg`` about its optical axis. Scalars give (4, 4), arrays (n, 4, 4)."""
    args = np.broadcast_arrays(
        *(np.asarray(a, float) for a in (distance_m, tilt_deg, elevation_deg, roll_deg))
    )
    distance, tilt, elevation, roll = (a.ravel() for a in args)
    # Unrotated camera axes in the world: x right, y down, z into the screen.
    orbit = Rotation.from_euler("yx", np.column_stack([-tilt, elevation]), degrees=True)
    R = (orbit * Rotation.from_euler("z", roll[:, None], degrees=True)).as_matrix()
    position = np.asarray(centre, float) - distance[:, None] * R[:, :, 2]
    T = make_pose(R, position)
    return T[0] if args[0].ndim == 0 else T


class _FixedPose:
    is_static = True

    def __init__(self, T_world_cam: np.ndarray) -> None:
        self._T = T_world_cam

    def pose_at(self, t_us: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self._T, (np.size(t_us), 4, 4)).copy()


@dataclass(frozen=True)
class StaticMotion:
    """A camera on a tripod, ``distance_m`` from the marker centre, looking at it (``look_at``'s
    angles)."""

    distance_m: float = 1.25
    tilt_deg: float = 0.0
    roll_deg: float = 0.0
    elevation_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.distance_m <= 0:
            raise ValueError(f"distance must be positive, got {self.distance_m} m")
        _check_view(self.tilt_deg, self.elevation_deg)

    def trajectory(self, rig: Rig) -> Trajectory:
        return _FixedPose(
            look_at(rig.centre, self.distance_m, self.tilt_deg, self.elevation_deg, self.roll_deg)
        )

    def to_dict(self) -> dict:
        return {"kind": "static", **asdict(self)}


# Hand-held wander: each degree of freedom is a sum of three sinusoids. Frequencies are drawn
# in a band typical of arm motion and then scaled together so the marker's mean optical flow hits
# the requested value; amplitudes are set against the free room in the image so the marker stays
# in view.
_WANDER_TERMS = 3
_WANDER_BAND_HZ = (0.3, 1.2)
_ORBIT_DEG = 12.0
"""Amplitude of the viewing-angle swings about the marker centre."""
_ROLL_DEG = 8.0
_DEPTH_FRACTION = 0.08
"""Amplitude of the distance changes, as a fraction of the mean distance."""
_SHIFT_FRACTION = 0.7
"""Share of the free image margin the sideways wander may use."""
_FLOW_PROBE_S = 20.0


def _check_view(tilt_deg: float, elevation_deg: float) -> None:
    for name, angle in (("tilt", tilt_deg), ("elevation", elevation_deg)):
        if abs(angle) >= 80:
            raise ValueError(f"{name} must be within +-80 degrees, got {angle}")


@dataclass(frozen=True)
class HandHeldMotion:
    """Smooth 6-DoF wander around a view of the marker centre, at a set mean marker flow. The
    view it wanders around is square-on unless turned by ``look_at``'s angles."""

    distance_m: float = 0.6
    flow_px_per_ms: float = 1.0
    seed: int = 0
    start_s: float = 0.0
    """Where on its path the wander starts: a camera that resumes after a gap carries on."""
    tilt_deg: float = 0.0
    elevation_deg: float = 0.0
    roll_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.distance_m <= 0:
            raise ValueError(f"distance must be positive, got {self.distance_m} m")
        _check_view(self.tilt_deg, self.elevation_deg)
        if self.flow_px_per_ms <= 0:
            raise ValueError(
                f"flow must be positive, got {self.flow_px_per_ms} px/ms "
                "(use StaticMotion for a still camera)"
            )

    def trajectory(self, rig: Rig) -> Trajectory:
        return _Wander(self, rig)

    def to_dict(self) -> dict:
        return {"kind": "handheld", **asdict(self)}


class _Wander:
    is_static = False

    def __init__(self, motion: HandHeldMotion, rig: Rig) -> None:
        self.motion, self.rig = motion, rig
        rng = np.random.default_rng(motion.seed)
        # 6 DoF: orbit tilt, orbit elevation, roll, depth, shift x, shift y.
        self._freq = rng.uniform(*_WANDER_BAND_HZ, (6, _WANDER_TERMS))
        self._phase = rng.uniform(0, 2 * math.pi, (6, _WANDER_TERMS))
        weights = rng.uniform(0.5, 1.0, (6, _WANDER_TERMS))
        self._weight = weights / weights.sum(1, keepdims=True)
        self._speed = 1.0
        self._start_s = 0.0  # the flow is set on the path from its beginning
        self._shift_m = 0.0
        cam = rig.camera
        marker_px = self._marker_extent_px(self._base_poses(np.zeros(1))[0])
        free_px = (min(cam.width, cam.height) - marker_px) / 2
        if free_px <= 0:
            raise ValueError(
                f"the marker ({marker_px:.0f} px) does not fit in the "
                f"{cam.width}x{cam.height} image at {motion.distance_m} m; "
                "move the camera further away"
            )
        self._shift_m = _SHIFT_FRACTION * free_px * motion.distance_m / cam.K[0, 0]
        probe = np.linspace(0, _FLOW_PROBE_S * 1e6, 4001)
        self._speed = motion.flow_px_per_ms / self.mean_flow_px_per_ms(probe)
        self._start_s = motion.start_s

    def _signals(self, t_us: np.ndarray) -> np.ndarray:
        """(6, n) wander of each degree of freedom, in [-1, 1]."""
        t = (np.asarray(t_us, float).ravel() * 1e-6 + self._start_s) * self._speed
        arg = 2 * math.pi * self._freq[:, :, None] * t + self._phase[:, :, None]
        return np.einsum("dk,dkn->dn", self._weight, np.sin(arg))

    def _base_poses(self, t_us: np.ndarray) -> np.ndarray:
        s = self._signals(t_us)
        m = self.motion
        return look_at(
            self.rig.centre,
            m.distance_m * (1 + _DEPTH_FRACTION * s[3]),
            m.tilt_deg + _ORBIT_DEG * s[0],
            m.elevation_deg + _ORBIT_DEG * s[1],
            m.roll_deg + _ROLL_DEG * s[2],
        )

    def pose_at(self, t_us: np.ndarray) -> np.ndarray:
        T = self._base_poses(t_us)
        shift = self._signals(t_us)[4:6].T * self._shift_m
        T[:, :3, 3] += np.einsum("nij,nj->ni", T[:, :3, :2], shift)  # sideways in camera axes
        return T

    def _marker_extent_px(self, T_world_cam: np.ndarray) -> float:
        px = project_points(self.rig.camera, T_world_cam, self.rig.corners)
        return float(max(np.ptp(px[:, 0]), np.ptp(px[:, 1])))

    def mean_flow_px_per_ms(self, t_us: np.ndarray) -> float:
        """Mean image speed of the marker's corners and centre over the times ``t_us``."""
        pts = np.vstack([self.rig.corners, self.rig.centre])
        px = project_points(self.rig.camera, self.pose_at(t_us), pts)
        speed = np.linalg.norm(np.diff(px, axis=0), axis=2) / np.diff(t_us)[:, None] * 1e3
        return float(speed.mean())


@dataclass(frozen=True)
class TumMotion:
    """A recorded trajectory (TUM file of T_world_cam in the marker frame); its first row is
    t = 0, poses in between are interpolated (linear position, slerp rotation)."""

    path: str

    def trajectory(self, rig: Rig) -> Trajectory:
        return _TumTrajectory(Path(self.path))

    def to_dict(self) -> dict:
        return {"kind": "tum", "path": str(self.path)}


class _TumTrajectory:
    def __init__(self, path: Path) -> None:
        t_us, T = read_tum(path)
        if len(t_us) < 2:
            raise ValueError(f"{path}: a trajectory needs at least two poses, got {len(t_us)}")
        if np.any(np.diff(t_us) <= 0):
            raise ValueError(f"{path}: timestamps must increase strictly")
        self.t_us = t_us - t_us[0]
        self.T = T
        self.is_static = bool(np.allclose(T, T[0]))
        self._slerp = Slerp(self.t_us.astype(float), Rotation.from_matrix(T[:, :3, :3]))

    @property
    def duration_us(self) -> int:
        return int(self.t_us[-1])

    def pose_at(self, t_us: np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(t_us, float).ravel(), 0, self.t_us[-1])
        pos = np.column_stack([np.interp(t, self.t_us, self.T[:, i, 3]) for i in range(3)])
        return make_pose(self._slerp(t).as_matrix(), pos)


Motion = StaticMotion | HandHeldMotion | TumMotion


def motion_from_dict(d: dict) -> Motion:
    d = dict(d)
    kind = d.pop("kind", None)
    kinds = {"static": StaticMotion, "handheld": HandHeldMotion, "tum": TumMotion}
    if kind not in kinds:
        raise ValueError(f"unknown motion kind {kind!r}; valid kinds: {', '.join(kinds)}")
    return kinds[kind](**d)


def project_points(
    camera: CameraModel, T_world_cam: np.ndarray, points_world: np.ndarray
) -> np.ndarray:
    """Pixel coordinates (..., n, 2) of world points (n, 3) seen from T_world_cam (..., 4, 4)."""
    T = invert(np.asarray(T_world_cam))
    cam = np.einsum("...ij,nj->...ni", T[..., :3, :3], points_world) + T[..., None, :3, 3]
    return camera.project(cam)


def image_box(
    camera: CameraModel, T_world_cam: np.ndarray, points_world: np.ndarray, margin_px: float
) -> tuple[int, int, int, int]:
    """Pixel box ``(x0, x1, y0, y1)`` (clipped to the sensor, ends exclusive) around the images
    of world points seen from one or more poses; the whole sensor if a point is behind a camera
    (its projection would then be meaningless)."""
    T = invert(np.asarray(T_world_cam))
    cam = np.einsum("...ij,nj->...ni", T[..., :3, :3], points_world) + T[..., None, :3, 3]
    if np.any(cam[..., 2] <= 1e-6):
        return 0, camera.width, 0, camera.height
    px = camera.project(cam).reshape(-1, 2)
    lo = np.floor(px.min(axis=0) - margin_px)
    hi = np.ceil(px.max(axis=0) + margin_px)
    x0, x1 = (int(np.clip(v, 0, camera.width)) for v in (lo[0], hi[0]))
    y0, y1 = (int(np.clip(v, 0, camera.height)) for v in (lo[1], hi[1]))
    return x0, max(x0, x1), y0, max(y0, y1)
