"""Rigid transforms and TUM trajectory files (``t tx ty tz qx qy qz qw``, t in seconds)."""

from __future__ import annotations

from decimal import Decimal
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 (or (n,4,4)) homogeneous transform from rotation matrices and translations."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(R, -(R @ T[..., :3, 3:4])[..., 0])


def pose_to_tum_row(T: np.ndarray) -> np.ndarray:
    """(..., 7) tx ty tz qx qy qz qw of transforms (..., 4, 4)."""
    flat = T.reshape(-1, 4, 4)
    q = Rotation.from_matrix(flat[:, :3, :3]).as_quat()  # x, y, z, w
    return np.concatenate([flat[:, :3, 3], q], 1).reshape((*T.shape[:-2], 7))


def tum_row_to_pose(rows: np.ndarray) -> np.ndarray:
    rows = np.asarray(rows, float)
    flat = rows.reshape(-1, 7)
    T = make_pose(Rotation.from_quat(flat[:, 3:]).as_matrix(), flat[:, :3])
    return T.reshape((*rows.shape[:-1], 4, 4))


def format_seconds(t_us: int) -> str:
    """Exact decimal seconds of an integer microsecond time (no float rounding)."""
    sign = "-" if t_us < 0 else ""
    whole, frac = divmod(abs(int(t_us)), 1_000_000)
    return f"{sign}{whole}.{frac:06d}"


TUM_HEADER = "# t tx ty tz qx qy qz qw (T_world_cam, marker frame, metres)\n"
_TUM_VALUES = " %.9f" * 7 + "\n"


def tum_lines(t_us: np.ndarray | list[int], T_world_cam: np.ndarray) -> str:
    """TUM rows of poses at integer microsecond times (the times printed exactly)."""
    rows = pose_to_tum_row(np.asarray(T_world_cam).reshape(-1, 4, 4)).tolist()
    times = np.asarray(t_us).ravel().tolist()
    return "".join(
        format_seconds(t) + _TUM_VALUES % tuple(row) for t, row in zip(times, rows, strict=True)
    )


def write_tum(path: str | Path, t_us: np.ndarray, T_world_cam: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write(TUM_HEADER + tum_lines(t_us, T_world_cam))


class TrajectoryFileError(ValueError):
    pass


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_us int64 (n,), T_world_cam (n, 4, 4)) from a TUM file."""
    t_us, rows = [], []
    for lineno, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise TrajectoryFileError(
                f"{path}:{lineno}: a TUM row has 8 numbers (t tx ty tz qx qy qz qw), "
                f"got {len(parts)}"
            )
        try:
            t_us.append(int(Decimal(parts[0]).scaleb(6).to_integral_value()))
            rows.append([float(v) for v in parts[1:]])
        except (ValueError, ArithmeticError) as exc:
            raise TrajectoryFileError(f"{path}:{lineno}: not a number: {exc}") from None
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    return np.array(t_us, np.int64), tum_row_to_pose(np.array(rows))
