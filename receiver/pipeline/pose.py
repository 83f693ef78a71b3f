"""Camera pose from marker points: PnP for the first pose, and the compiled Levenberg-Marquardt
refinement against event clusters of the tracked edges (paper Sec. IV-C, Eq. 6-7).

Poses here are ``T_cam_world`` (marker frame -> camera frame); the receiver's outputs invert them.
Pixel coordinates are *ideal* (undistorted): events are undistorted through the camera's lookup
table before they reach the tracker, so the model is the pinhole ``K`` alone.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numba
import numpy as np

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.poses import make_pose


def pnp(corners_px: np.ndarray, world: np.ndarray, camera: CameraModel) -> np.ndarray:
    """T_cam_world from (k, 2) distorted pixel corners of (k, 3) planar marker points."""
    obj = np.ascontiguousarray(world, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(corners_px, np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if ok and not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
        # IPPE's closed form divides zero by zero for a square seen exactly head-on.
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("PnP failed on the detected corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
    return make_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())


def plane_homography(T_cam_world: np.ndarray, K: np.ndarray) -> np.ndarray:
    """3x3 H (or (n, 3, 3) for n poses) taking marker-plane points (X, Y, 1) in metres to ideal
    pixels."""
    return K @ T_cam_world[..., :3, [0, 1, 3]]


def project_ideal(T_cam_world: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Ideal pixels (..., 2) of marker points (..., 3); NaN behind the camera."""
    flat = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    T = np.ascontiguousarray(T_cam_world, np.float64)
    return _project(T, np.ascontiguousarray(K, np.float64), flat).reshape(*points.shape[:-1], 2)


@numba.njit(cache=True, nogil=True)
def _project(T, K, points):
    """``project_ideal`` of (n, 3) points, compiled: the receiver projects a few marker points
    several times per millisecond of events, where numpy's per-call overhead outweighs the
    arithmetic tenfold."""
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        P = points[i]
        X = T[0, 0] * P[0] + T[0, 1] * P[1] + T[0, 2] * P[2] + T[0, 3]
        Y = T[1, 0] * P[0] + T[1, 1] * P[1] + T[1, 2] * P[2] + T[1, 3]
        Z = T[2, 0] * P[0] + T[2, 1] * P[1] + T[2, 2] * P[2] + T[2, 3]
        if Z > 1e-6:
            out[i, 0], out[i, 1] = X / Z * K[0, 0] + K[0, 2], Y / Z * K[1, 1] + K[1, 2]
        else:
            out[i, 0] = out[i, 1] = np.nan
    return out


class PoseHistory:
    """Poses (T_cam_world) at increasing times, interpolated in between (``at``)."""

    def __init__(self) -> None:
        self._t = np.empty(0, np.int64)
        self._T = np.empty((0, 4, 4))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def restart(self, t_us: int, T_cam_world: np.ndarray) -> None:
        """Forget every pose; hold ``T_cam_world`` from ``t_us`` on."""
        self._n = 0
        self.append(t_us, T_cam_world)

    def append(self, t_us: int, T_cam_world: np.ndarray) -> None:
        """Add the pose at ``t_us``, not before the latest one."""
        if self._n == len(self._t):
            size = max(64, 2 * self._n)
            self._t = np.resize(self._t, size)
            self._T = np.resize(self._T, (size, 4, 4))
        self._t[self._n], self._T[self._n] = t_us, T_cam_world
        self._n += 1

    def forget_before(self, t_us: int) -> None:
        """Drop the poses before ``t_us`` but the latest of them (in batches: this runs for
        every few events the tracker takes)."""
        drop = int(np.searchsorted(self._t[: self._n], t_us, "right")) - 1
        if drop >= 32:
            self._n -= drop
            self._t[: self._n] = self._t[drop : drop + self._n]
            self._T[: self._n] = self._T[drop : drop + self._n]

    def at(self, times_us: np.ndarray | list[float]) -> np.ndarray:
        """(n, 4, 4) poses at ``times_us``: interpolated between the poses around each time, or
        the nearest one outside them."""
        if not self._n:
            raise ValueError("no pose to interpolate: the history is empty")
        times = np.atleast_1d(np.asarray(times_us, np.float64))
        return _interpolate(self._t[: self._n], self._T[: self._n], times)


@numba.njit(cache=True, nogil=True)
def _so3_log(R):
    """The rotation vector of rotation matrix ``R`` (axis times angle, the angle in [0, pi])."""
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])  # sin(theta)
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    theta = np.arctan2(s, c)  # accurate at any angle, unlike arccos(c) near 0
    if theta < 1e-6:
        return v  # sin(theta) / theta = 1 to within rounding
    if theta < np.pi - 1e-3:
        return theta / s * v
    # Near a half turn v vanishes: the axis a comes from the symmetric part of R,
    # c I + (1 - c) a a^T (its dominant column), signed as v leans.
    j = np.argmax(np.array([R[0, 0], R[1, 1], R[2, 2]]))
    a = (0.5 * (R[:, j] + R[j, :]) - c * np.eye(3)[:, j]) / (1.0 - c)
    a /= np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    if a[0] * v[0] + a[1] * v[1] + a[2] * v[2] < 0:
        a = -a
    return theta * a


@numba.njit(cache=True, nogil=True)
def _interpolate(t, T, at):
    """``PoseHistory.at``: each pose a share f of the way from the pose before to the one after,
    turned about their relative rotation's axis by f of its angle and moved along the line
    between them (compiled: the decoder asks for a pose every quarter millisecond of a frame)."""
    out = np.empty((at.shape[0], 4, 4))
    n = t.shape[0]
    for k in range(at.shape[0]):
        i = np.searchsorted(t, at[k], "right") - 1
        if i < 0 or i + 1 >= n:
            out[k] = T[max(i, 0)]
            continue
        f = (at[k] - t[i]) / (t[i + 1] - t[i])
        R0 = np.ascontiguousarray(T[i, :3, :3])
        w = _so3_log(R0.T @ np.ascontiguousarray(T[i + 1, :3, :3]))
        out[k] = np.eye(4)
        out[k, :3, :3] = R0 @ _so3_exp(f * w)
        out[k, :3, 3] = T[i, :3, 3] + f * (T[i + 1, :3, 3] - T[i, :3, 3])
    return out


# --- compiled LM --------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _so3_exp(w):
    theta = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + W
    return np.eye(3) + np.sin(theta) / theta * W + (1 - np.cos(theta)) / theta**2 * (W @ W)


@numba.njit(cache=True, nogil=True)
def _project_with_jacobian(P, R, t, k, uv, J):
    """Ideal pixel ``uv`` of world point P and its 2x6 Jacobian ``J`` for Pc' = exp(w) Pc + v,
    written into the given arrays (scalar code: small-array products allocate and call BLAS)."""
    X = R[0, 0] * P[0] + R[0, 1] * P[1] + R[0, 2] * P[2] + t[0]
    Y = R[1, 0] * P[0] + R[1, 1] * P[1] + R[1, 2] * P[2] + t[1]
    Z = R[2, 0] * P[0] + R[2, 1] * P[1] + R[2, 2] * P[2] + t[2]
    iz = 1.0 / Z
    uv[0], uv[1] = k[0] * X * iz + k[2], k[1] * Y * iz + k[3]
    fx, fy = k[0] * iz, k[1] * iz
    gx, gy = -k[0] * X * iz * iz, -k[1] * Y * iz * iz
    # d(u, v)/d(X, Y, Z) times dPc/d(w, v): rotation columns (0, Z, -Y), (-Z, 0, X), (Y, -X, 0).
    J[0, 0], J[0, 1], J[0, 2] = gx * Y, fx * Z - gx * X, -fx * Y
    J[1, 0], J[1, 1], J[1, 2] = -fy * Z + gy * Y, -gy * X, fy * X
    J[0, 3], J[0, 4], J[0, 5] = fx, 0.0, gx
    J[1, 3], J[1, 4], J[1, 5] = 0.0, fy, gy


DARK_SIDE = np.array([-1.0] * 4 + [1.0] * 4)
"""Which way each tracked edge's dark side lies, in the sign of ``_residuals``' distances (positive
to the right of an edge running clockwise, i.e. into the ring's inside): outside the outer
boundary of the white ring, inside its inner one (``MarkerGeometry.tracked_edges``' order)."""


@numba.njit(cache=True, nogil=True)
def _residuals(R, t, k, pts, edge, ends, huber, dark):
    """Robust cost of the points' signed distances to the lines of their projected edges, each
    moved ``dark`` px to its dark side, and the Huber-weighted normal equations (H, g) in the
    pose's six parameters and ``dark``.

    A log sensor fires where the log of the blurred edge's intensity is steepest, on the dark
    side of the edge, so the events of a moving edge lie a fraction of a pixel to a pixel off
    it, towards black: on both sides of the white ring the offsets point away from the ring
    (more with more blur and contrast). Fitted with the pose, the offset no longer tilts it when
    the edges firing are not balanced (a motion that fires only some of them).

    A point's Jacobian is linear in its offset q = (1, u, v) from its edge's projected start:
    J = M_e q. So the points only add up, per edge, the weighted moments S_e = sum w q q^T and
    h_e = sum w r q, and then H = sum_e M_e S_e M_e^T and g = sum_e M_e h_e: a few flops per
    point instead of the 27 products of J J^T (hand-held tracking solves a pose every ms)."""
    m = ends.shape[0]
    a_px = np.empty((m, 2))
    d = np.empty((m, 2))
    length = np.empty(m)
    M = np.empty((m, 6, 3))
    b_px, Ja, Jb = np.empty(2), np.empty((2, 6)), np.empty((2, 6))
    for e in range(m):
        _project_with_jacobian(ends[e, 0], R, t, k, a_px[e], Ja)
        _project_with_jacobian(ends[e, 1], R, t, k, b_px, Jb)
        dx, dy = b_px[0] - a_px[e, 0], b_px[1] - a_px[e, 1]
        d[e, 0], d[e, 1] = dx, dy
        L = np.sqrt(dx * dx + dy * dy) + 1e-12
        length[e] = L
        # d r / d (start, end) of the point at q, split into its parts along 1, u and v
        # (moving both ends alike moves the line: only the constant part sees it).
        i1, i3 = 1.0 / L, 1.0 / (L * L * L)
        for j in range(6):
            d0, d1 = Ja[0, j] - Jb[0, j], Ja[1, j] - Jb[1, j]
            M[e, j, 0] = dy * i1 * Ja[0, j] - dx * i1 * Ja[1, j]
            M[e, j, 1] = -dx * dy * i3 * d0 + (i1 - dy * dy * i3) * d1
            M[e, j, 2] = (dx * dx * i3 - i1) * d0 + dx * dy * i3 * d1
    S = np.zeros((m, 3, 3))
    h = np.zeros((m, 3))
    cost = 0.0
    # The moments add up in scalars while the points stay on one edge (the clusters come edge
    # by edge): sums in memory would chain every point's additions through a store.
    e = -1
    w0 = wu0 = wv0 = wuu = wuv = wvv = wr0 = wru = wrv = 0.0
    for i in range(pts.shape[0] + 1):
        if i == pts.shape[0] or edge[i] != e:
            if e >= 0:
                S[e, 0, 0] += w0
                S[e, 0, 1] += wu0
                S[e, 0, 2] += wv0
                S[e, 1, 1] += wuu
                S[e, 1, 2] += wuv
                S[e, 2, 2] += wvv
                h[e, 0] += wr0
                h[e, 1] += wru
                h[e, 2] += wrv
            if i == pts.shape[0]:
                break
            e = edge[i]
            w0 = wu0 = wv0 = wuu = wuv = wvv = wr0 = wru = wrv = 0.0
        u, v = pts[i, 0] - a_px[e, 0], pts[i, 1] - a_px[e, 1]
        r = (d[e, 0] * v - d[e, 1] * u) / length[e] - DARK_SIDE[e] * dark
        ar = abs(r)
        w = 1.0 if ar <= huber else huber / ar
        cost += 0.5 * r * r if ar <= huber else huber * (ar - 0.5 * huber)
        wu, wv, wr = w * u, w * v, w * r
        w0 += w
        wu0 += wu
        wv0 += wv
        wuu += wu * u
        wuv += wu * v
        wvv += wv * v
        wr0 += wr
        wru += wr * u
        wrv += wr * v
    H = np.zeros((7, 7))
    g = np.zeros(7)
    MS = np.empty(3)
    for e in range(m):
        S[e, 1, 0], S[e, 2, 0], S[e, 2, 1] = S[e, 0, 1], S[e, 0, 2], S[e, 1, 2]
        side = -DARK_SIDE[e]  # d r / d dark
        for j in range(6):
            for c in range(3):
                MS[c] = M[e, j, 0] * S[e, 0, c] + M[e, j, 1] * S[e, 1, c] + M[e, j, 2] * S[e, 2, c]
            for i in range(j, 6):
                H[j, i] += MS[0] * M[e, i, 0] + MS[1] * M[e, i, 1] + MS[2] * M[e, i, 2]
            H[j, 6] += side * MS[0]
            g[j] += M[e, j, 0] * h[e, 0] + M[e, j, 1] * h[e, 1] + M[e, j, 2] * h[e, 2]
        H[6, 6] += S[e, 0, 0]
        g[6] += side * h[e, 0]
    for j in range(7):  # the lower triangle mirrors the upper one
        for i in range(j):
            H[j, i] = H[i, j]
    return cost, H, g


@numba.njit(cache=True, nogil=True)
def _lm(R, t, k, pts, edge, ends, huber, iterations, dark, prior, fit_dark):
    """Levenberg-Marquardt on the pose and, with ``fit_dark``, the dark-side offset, which
    ``prior`` (a weight in points) pulls towards its starting value."""
    n = 7 if fit_dark else 6
    cost, H, g = _residuals(R, t, k, pts, edge, ends, huber, dark)
    start = dark  # the prior's cost, 0.5 * prior * (dark - start) ** 2, is 0 here
    lam = 1e-3
    for _ in range(iterations):
        A = H[:n, :n] + lam * np.diag(np.diag(H[:n, :n]) + 1e-9)
        b = g[:n].copy()
        if fit_dark:
            A[6, 6] += prior
            b[6] += prior * (dark - start)
        step = -np.linalg.solve(A, b)
        dR = _so3_exp(step[:3])
        R_new, t_new = dR @ R, dR @ t + step[3:6]
        dark_new = dark + step[6] if fit_dark else dark
        # One pass for the cost and the next normal equations: most steps are taken.
        new_cost, H_new, g_new = _residuals(R_new, t_new, k, pts, edge, ends, huber, dark_new)
        if fit_dark:
            new_cost += 0.5 * prior * (dark_new - start) ** 2
        if new_cost < cost:
            R, t, dark, cost, H, g = R_new, t_new, dark_new, new_cost, H_new, g_new
            lam = max(lam / 10, 1e-7)
            if np.abs(step).max() < 1e-7:
                break
        else:
            lam *= 10
            if lam > 1e6:
                break
    return R, t, dark, cost, H[6, 6] if fit_dark else 0.0


class PoseFit(NamedTuple):
    T_cam_world: np.ndarray
    cost: float
    """Robust cost per point, the offset's pull towards its prior included."""
    dark_px: float
    """The events' offset to their edges' dark side (``_residuals``)."""
    dark_weight: float
    """How many points (Huber-weighted) the offset was fitted to: 0 where it was not fitted."""


def refine_pose(
    T_cam_world: np.ndarray,
    K: np.ndarray,
    points_px: np.ndarray,
    edge: np.ndarray,
    edges_world: np.ndarray,
    huber_px: float,
    iterations: int,
    dark_px: float = 0.0,
    dark_prior: float = 0.0,
) -> PoseFit:
    """Levenberg-Marquardt with a Huber loss: the pose that puts the (n, 2) ideal event pixels on
    their edges' (8, 2, 3) projected lines, each moved to its dark side by an offset fitted
    with it from ``dark_px`` (``_residuals``), held there with the weight of ``dark_prior``
    points (infinite: not fitted). The offset is fitted only when points lie on both an outer
    and an inner edge: on one boundary alone it is the marker's distance."""
    k = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    edge = edge.astype(np.int64)
    sides = DARK_SIDE[edge]
    fit_dark = bool(np.any(sides < 0) and np.any(sides > 0) and np.isfinite(dark_prior))
    R, t, dark, cost, weight = _lm(
        np.ascontiguousarray(T_cam_world[:3, :3]),
        T_cam_world[:3, 3].copy(),
        k,
        np.ascontiguousarray(points_px, np.float64),
        edge,
        np.ascontiguousarray(edges_world, np.float64),
        huber_px,
        iterations,
        float(dark_px),
        float(dark_prior),
        fit_dark,
    )
    return PoseFit(make_pose(R, t), cost / max(1, len(edge)), dark, weight)
