"""Camera pose from marker points: PnP for the first pose, and the compiled Levenberg-Marquardt
refinement against event clusters of the tracked edges (paper Sec. IV-C, Eq. 6-7).

Poses here are ``T_cam_world`` (marker frame -> camera frame); the receiver's outputs invert them.
Pixel coordinates are *ideal* (undistorted): events are undistorted through the camera's lookup
table before they reach the tracker, so the model is the pinhole ``K`` alone.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from receiver.camera import CameraModel
from receiver.poses import make_pose


def pnp(corners_px: np.ndarray, world: np.ndarray, camera: CameraModel) -> np.ndarray:
    """T_cam_world from (k, 2) distorted pixel corners of (k, 3) planar marker points."""
    obj = np.ascontiguousarray(world, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(corners_px, np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("PnP failed on the detected corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
    return make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())


def plane_homography(T_cam_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """3x3 H taking marker-plane points (X, Y, 1) in metres to ideal pixels."""
    return K @ T_cam_world[:3, [0, 1, 3]]


def project_ideal(T_cam_world: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Ideal pixels (..., 2) of marker points (..., 3); NaN behind the camera."""
    pc = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = np.where(pc[..., 2:3] > 1e-6, pc[..., 2:3], np.nan)
    return pc[..., :2] / z * K[[0, 1], [0, 1]] + K[:2, 2]


# --- compiled LM --------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _so3_exp(w):
    theta = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + W
    return np.eye(3) + np.sin(theta) / theta * W + (1 - np.cos(theta)) / theta**2 * (W @ W)


@numba.njit(cache=True, nogil=True)
def _project_with_jacobian(P, R, t, k):
    """Ideal pixel of world point P and its 2x6 Jacobian for Pc' = exp(w) Pc + v."""
    pc = R @ P + t
    X, Y, Z = pc[0], pc[1], pc[2]
    iz = 1.0 / Z
    uv = np.array([k[0] * X * iz + k[2], k[1] * Y * iz + k[3]])
    duv = np.array([[k[0] * iz, 0.0, -k[0] * X * iz * iz], [0.0, k[1] * iz, -k[1] * Y * iz * iz]])
    dpc = np.zeros((3, 6))
    dpc[0, 1], dpc[0, 2], dpc[1, 0], dpc[1, 2], dpc[2, 0], dpc[2, 1] = Z, -Y, -Z, X, Y, -X
    dpc[0, 3] = dpc[1, 4] = dpc[2, 5] = 1.0
    return uv, duv @ dpc


@numba.njit(cache=True, nogil=True)
def _residuals(R, t, k, pts, edge, ends, huber, want_jac):
    """Signed distances of points to the lines of their projected edges; Huber-weighted normal
    equations when ``want_jac``."""
    n = pts.shape[0]
    H = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    a_px = np.empty((ends.shape[0], 2))
    b_px = np.empty((ends.shape[0], 2))
    Ja = np.empty((ends.shape[0], 2, 6))
    Jb = np.empty((ends.shape[0], 2, 6))
    length, length3 = np.empty(ends.shape[0]), np.empty(ends.shape[0])  # per edge, not point
    J = np.empty(6)
    for e in range(ends.shape[0]):
        a_px[e], Ja[e] = _project_with_jacobian(ends[e, 0], R, t, k)
        b_px[e], Jb[e] = _project_with_jacobian(ends[e, 1], R, t, k)
        dx, dy = b_px[e, 0] - a_px[e, 0], b_px[e, 1] - a_px[e, 1]
        length[e] = np.sqrt(dx * dx + dy * dy) + 1e-12
        length3[e] = length[e] * length[e] * length[e]
    for i in range(n):
        e = edge[i]
        ax, ay, bx, by = a_px[e, 0], a_px[e, 1], b_px[e, 0], b_px[e, 1]
        px, py = pts[i, 0], pts[i, 1]
        dx, dy = bx - ax, by - ay
        L = length[e]
        c = dx * (py - ay) - dy * (px - ax)
        r = c / L
        ar = abs(r)
        w = 1.0 if ar <= huber else huber / ar
        cost += 0.5 * r * r if ar <= huber else huber * (ar - 0.5 * huber)
        if want_jac:
            # Scalar loops, not small-array expressions: those allocate per point.
            s = c / length3[e]
            dra0, dra1 = (by - py) / L + s * dx, (px - bx) / L + s * dy
            drb0, drb1 = (py - ay) / L - s * dx, -(px - ax) / L - s * dy
            for j in range(6):
                J[j] = (dra0 * Ja[e, 0, j] + dra1 * Ja[e, 1, j]) + (
                    drb0 * Jb[e, 0, j] + drb1 * Jb[e, 1, j]
                )
            for j in range(6):
                g[j] += w * r * J[j]
                for m in range(j, 6):
                    H[j, m] += w * (J[j] * J[m])
    for j in range(6):  # the lower triangle mirrors the upper one
        for m in range(j):
            H[j, m] = H[m, j]
    return cost, H, g


@numba.njit(cache=True, nogil=True)
def _lm(R, t, k, pts, edge, ends, huber, iterations):
    cost, H, g = _residuals(R, t, k, pts, edge, ends, huber, True)
    lam = 1e-3
    for _ in range(iterations):
        A = H + lam * np.diag(np.diag(H) + 1e-9)
        step = -np.linalg.solve(A, g)
        dR = _so3_exp(step[:3])
        R_new, t_new = dR @ R, dR @ t + step[3:]
        # One pass for the cost and the next normal equations: most steps are taken.
        new_cost, H_new, g_new = _residuals(R_new, t_new, k, pts, edge, ends, huber, True)
        if new_cost < cost:
            R, t, cost, H, g = R_new, t_new, new_cost, H_new, g_new
            lam = max(lam / 10, 1e-7)
            if np.abs(step).max() < 1e-7:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    return R, t, cost


def refine_pose(
    T_cam_world: np.ndarray,
    K: np.ndarray,
    points_px: np.ndarray,
    edge: np.ndarray,
    edges_world: np.ndarray,
    huber_px: float,
    iterations: int,
) -> tuple[np.ndarray, float]:
    """Levenberg-Marquardt with a Huber loss: the pose that puts the (n, 2) ideal event pixels on
    their edges' (8, 2, 3) projected lines; returns (T_cam_world, robust cost per point)."""
    k = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    R, t, cost = _lm(
        np.ascontiguousarray(T_cam_world[:3, :3]),
        T_cam_world[:3, 3].copy(),
        k,
        np.ascontiguousarray(points_px, np.float64),
        edge.astype(np.int64),
        np.ascontiguousarray(edges_world, np.float64),
        huber_px,
        iterations,
    )
    return make_pose(R, t), cost / max(1, len(edge))
