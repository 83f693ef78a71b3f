"""Output poses smoothed over a centred window of the tracker's updates.

The tracker re-fits the pose to the latest edge events about once a millisecond, and each fit is
noisy in one direction above all: a small marker's tilt against its sideways shift, which barely
moves its image. On a 240x180 camera 0.6 m from the 27.2 cm marker that noise is ~0.75 cm
sideways, and it is nearly independent from one millisecond to the next (correlation 0.5 at
1 ms, 0.2 at 2 ms), while the camera moves smoothly. Each output pose is therefore a straight
line fitted to the updates within ``half_us`` of it, evaluated at its time: a few milliseconds
either side average the noise out, while wider windows lag the hand's acceleration. The
price: a pose is published once the updates ``half_us`` after it have come.

The fit is done on the 3x4 matrices and the rotation part is projected back onto the rotations
(the nearest in the Frobenius norm): within a few milliseconds the rotations differ by a degree
or two, where this agrees with fitting their angles to a thousandth of a degree.
"""

from __future__ import annotations

import numba
import numpy as np

PoseSample = tuple[int, np.ndarray]
"""(t_us, 4x4 transform)"""


@numba.njit(cache=True, nogil=True)
def _line_fit_at(t, rows, n, i, half_us):
    """The straight-line least-squares fit of the ``rows`` (flattened 3x4 poses) of the first
    ``n`` whose time ``t`` lies within ``half_us`` of ``t[i]``, evaluated at ``t[i]``, as a 4x4
    transform with its rotation re-orthonormalised."""
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
    fit = np.zeros(12)
    for j in range(lo, hi):
        w = 1.0 / k
        if sxx > 0:
            w -= (t[j] - t[i] - mean) * mean / sxx
        fit += w * rows[j]
    m = fit.reshape(3, 4)
    u, _, vt = np.linalg.svd(np.ascontiguousarray(m[:, :3]))
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        u[:, 2] = -u[:, 2]
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = m[:, 3]
    return out


class PoseSmoother:
    """Takes one track's poses in time order; gives each back fitted to its neighbours once the
    poses ``half_us`` after it have come (``push``), or at the track's end (``flush``)."""

    def __init__(self, half_us: int, capacity: int = 256) -> None:
        self.half_us = int(half_us)
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
        self._t[self._n] = t_us
        self._rows[self._n] = T[:3].ravel()
        self._n += 1
        out = []
        while self._t[self._next] + self.half_us < t_us:
            out.append(self._smoothed(self._next))
            self._next += 1
        return out

    def flush(self) -> list[PoseSample]:
        """Give back the poses still held, fitted to what came after them; start afresh."""
        out = [self._smoothed(i) for i in range(self._next, self._n)]
        self._n = self._next = 0
        return out

    def _smoothed(self, i: int) -> PoseSample:
        return int(self._t[i]), _line_fit_at(self._t, self._rows, self._n, i, self.half_us)

    def _make_room(self) -> None:
        """Drop the poses no window still needs; grow if they all are (updates far denser than
        the tracker makes)."""
        drop = int(np.searchsorted(self._t[: self._n], self._t[self._next] - self.half_us))
        if drop == 0:
            self._t = np.concatenate([self._t, np.empty_like(self._t)])
            self._rows = np.concatenate([self._rows, np.empty_like(self._rows)])
            return
        n = self._n - drop
        self._t[:n] = self._t[drop : self._n]
        self._rows[:n] = self._rows[drop : self._n]
        self._n, self._next = n, self._next - drop
