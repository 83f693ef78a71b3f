"""Evaluation against ground truth: BER with frame alignment, and ATE / RPE after Umeyama.

Trajectory alignment follows evo's ``--align`` without ``--correct_scale``: a rigid (SE(3))
Umeyama fit of the estimated positions to the ground truth at the same timestamps. The scale is
not estimated but held at exactly 1: metric scale comes from the marker's physical size (the
``marker_size_m`` both PnP and the edge model use), as in the paper, so a wrong marker size shows
up as ATE instead of being aligned away.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


def bit_errors(read: np.ndarray, truth: np.ndarray) -> int:
    return int(np.count_nonzero(np.asarray(read, bool) != np.asarray(truth, bool)))


def best_alignment(read: list[np.ndarray], candidates: list[np.ndarray]) -> tuple[int, int]:
    """(index into ``candidates``, bit errors) of the candidate frame closest to ``read``: the
    frame the receiver most likely saw when its own index may be off by a few."""
    errors = [bit_errors(read, c) for c in candidates]
    i = int(np.argmin(errors))
    return i, errors[i]


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising ||dst - (R src + t)|| (no scale)."""
    if len(src) < 3:
        raise ValueError(f"alignment needs at least 3 positions, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    return R, mu_d - R @ mu_s


def held_s(t_us: np.ndarray, max_gap_us: int, where: np.ndarray | None = None) -> float:
    """Seconds the poses at ``t_us`` stand for, each until the next one but at most
    ``max_gap_us`` (a longer gap is time without a lock); only the poses ``where`` is True."""
    held = np.minimum(np.diff(t_us, append=t_us[-1:]), max_gap_us)  # the last pose: 0
    return float(held.sum() if where is None else held[where].sum()) / 1e6


@dataclass(frozen=True)
class PoseErrors:
    ate_rmse_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    poses: int
    delta_us: int


def pose_errors(
    t_us: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray, delta_us: int = 100_000
) -> PoseErrors:
    """ATE (after alignment) and RPE over ``delta_us`` of matched (n, 4, 4) T_world_cam."""
    R, t = umeyama(T_est[:, :3, 3], T_gt[:, :3, 3])
    aligned = T_est.copy()
    aligned[:, :3, :3] = R @ T_est[:, :3, :3]
    aligned[:, :3, 3] = T_est[:, :3, 3] @ R.T + t
    ate = np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - T_gt[:, :3, 3]) ** 2, axis=1)))
    j = np.searchsorted(t_us, t_us + delta_us)
    i = np.nonzero(j < len(t_us))[0]
    if len(i) == 0:
        return PoseErrors(float(ate), float("nan"), float("nan"), len(t_us), delta_us)
    j = j[i]
    rel_est = np.linalg.inv(aligned[i]) @ aligned[j]
    rel_gt = np.linalg.inv(T_gt[i]) @ T_gt[j]
    err = np.linalg.inv(rel_gt) @ rel_est
    trans = np.sqrt(np.mean(np.sum(err[:, :3, 3] ** 2, axis=1)))
    angles = np.degrees(np.linalg.norm(Rotation.from_matrix(err[:, :3, :3]).as_rotvec(), axis=1))
    return PoseErrors(
        float(ate), float(trans), float(np.sqrt(np.mean(angles**2))), len(t_us), delta_us
    )
