"""Output poses smoothed over centred windows of the tracker's updates.

The tracker re-fits the pose to the latest edge events about once a millisecond, and each fit is
noisy in one direction above all: a small marker's tilt against its sideways shift, which barely
moves its image. On a 240x180 camera 0.6 m from the 27.2 cm marker that noise is ~0.75 cm
sideways, and it is nearly independent from one millisecond to the next (correlation 0.5 at
1 ms, 0.2 at 2 ms), while the camera moves smoothly. Each output pose is therefore fitted to
the updates around it, a straight line evaluated at its time: a few milliseconds either side
average the noise out, while wider windows lag the hand's acceleration.

The pose is fitted in two parts, each over its own window: where the marker's centre lies in
the camera frame, which its image fixes well, over ``half_us`` either side; the camera's
orientation, which the image of a small or distant marker fixes poorly, over the wider
``orientation_half_us``, or over as much of it as the camera takes to turn by ``_TURN_RAD``.
The camera's position follows from the two. A far marker's tilt noise stays correlated over
more updates (the events of a slow edge serve several fits), and the wide window averages it
where the position's own window could not; the position keeps the narrow window, so the
camera's swings still show at once where they move the image. The price: a pose is published
once the updates the wider window after it have come.

The fit is done on the matrices' entries and the rotation is projected back onto the rotations
(the nearest in the Frobenius norm): within a few tens of milliseconds the rotations differ by a
few degrees, where this agrees with fitting their angles to a hundredth of a degree.
"""

from __future__ import annotations

import numba
import numpy as np

PoseSample = tuple[int, np.ndarray]
"""(t_us, 4x4 transform)"""

_TURN_RAD = np.radians(1.0)
"""The orientation's window spans at most this much of the camera's turn, and at least the
position's window: a straight line through a longer stretch of a turn carries the turn's
curvature into the pose. The rate is the widest fit's: a narrow fit's slope follows the slow
wander of a far marker's tilt noise as readily as a turn."""


@numba.njit(cache=True, nogil=True)
def _line_fit_at(t, rows, n, i, half_us):
    """The straight-line least-squares fit of the ``rows`` of the first ``n`` whose time ``t``
    lies within ``half_us`` of ``t[i]``: (its value at ``t[i]``, its slope per microsecond)."""
    lo, hi = i, i + 1
    while lo > 0 and t[i] - t[lo - 1] <= half_us:
        lo -= 1
    while hi < n and t[hi] - t[i] <= half_us:
        hi += 1
    k = hi - lo
    mean = 0.0
    for j in range(lo, hi):
        mean += t[j] - t[i]
    mean /= k
    sxx = 0.0
    for j in range(lo, hi):
        sxx += (t[j] - t[i] - mean) ** 2
    fit = np.zeros(rows.shape[1])
    slope = np.zeros(rows.shape[1])
    for j in range(lo, hi):
        w = 1.0 / k
        if sxx > 0:
            w -= (t[j] - t[i] - mean) * mean / sxx
            slope += (t[j] - t[i] - mean) / sxx * rows[j]
        fit += w * rows[j]
    return fit, slope


@numba.njit(cache=True, nogil=True)
def _pose_at(t, rows, n, i, half_us, orientation_half_us, pivot):
    """The 4x4 T_world_cam at ``t[i]`` from the ``rows`` (R_world_cam's 9 entries, then the
    pivot in the camera frame): the pivot fitted over ``half_us``, the rotation over
    ``orientation_half_us`` or a ``_TURN_RAD`` turn, whichever is shorter, re-orthonormalised."""
    R, dR = _line_fit_at(t, rows[:, :9], n, i, orientation_half_us)
    # |dR|_F = sqrt(2) x the turn rate (rad/us) for small turns
    turn_us = _TURN_RAD * np.sqrt(2.0) / max(np.sqrt(np.sum(dR * dR)), 1e-15)
    if turn_us < orientation_half_us:
        R = _line_fit_at(t, rows[:, :9], n, i, max(half_us, turn_us))[0]
    centre = _line_fit_at(t, rows[:, 9:], n, i, half_us)[0]
    u, _, vt = np.linalg.svd(R.reshape(3, 3))
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        u[:, 2] = -u[:, 2]
    R = u @ vt
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = pivot - R @ centre
    return out


class PoseSmoother:
    """Takes one track's poses (T_world_cam) in time order; gives each back fitted to its
    neighbours once the poses ``delay_us`` after it have come (``push``), or at the track's end
    (``flush``). ``pivot`` (world frame) is the point, the marker's centre, whose place in the
    camera frame is smoothed over ``half_us`` while the orientation is smoothed over
    ``orientation_half_us`` (at least ``half_us``)."""

    def __init__(
        self,
        half_us: int,
        orientation_half_us: int = 0,
        pivot: np.ndarray | None = None,
        capacity: int = 256,
    ) -> None:
        self.half_us = int(half_us)
        self.orientation_half_us = max(self.half_us, int(orientation_half_us)) if half_us else 0
        self.delay_us = self.orientation_half_us
        """How long after its time each pose is given back."""
        self._pivot = np.zeros(3) if pivot is None else np.asarray(pivot, float)
        self._t = np.empty(capacity, np.int64)
        self._rows = np.empty((capacity, 12))
        self._n = 0
        self._next = 0
        """Index of the oldest pose not yet given back."""

    def push(self, t_us: int, T: np.ndarray) -> list[PoseSample]:
        if not self.half_us:
            return [(t_us, T)]
        if self._n == len(self._t):
            self._make_room()
        R = T[:3, :3]
        self._t[self._n] = t_us
        self._rows[self._n, :9] = R.ravel()
        self._rows[self._n, 9:] = R.T @ (self._pivot - T[:3, 3])
        self._n += 1
        out = []
        while self._t[self._next] + self.delay_us < t_us:
            out.append(self._smoothed(self._next))
            self._next += 1
        return out

    def flush(self) -> list[PoseSample]:
        """Give back the poses still held, fitted to what came after them; start afresh."""
        out = [self._smoothed(i) for i in range(self._next, self._n)]
        self._n = self._next = 0
        return out

    def _smoothed(self, i: int) -> PoseSample:
        pose = _pose_at(
            self._t, self._rows, self._n, i, self.half_us, self.orientation_half_us, self._pivot
        )
        return int(self._t[i]), pose

    def _make_room(self) -> None:
        """Drop the poses no window still needs; grow if they all are (updates far denser than
        the tracker makes)."""
        drop = int(np.searchsorted(self._t[: self._n], self._t[self._next] - self.delay_us))
        if drop == 0:
            self._t = np.concatenate([self._t, np.empty_like(self._t)])
            self._rows = np.concatenate([self._rows, np.empty_like(self._rows)])
            return
        n = self._n - drop
        self._t[:n] = self._t[drop : self._n]
        self._rows[:n] = self._rows[drop : self._n]
        self._n, self._next = n, self._next - drop
