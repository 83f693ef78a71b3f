"""Pre-processing (paper Sec. IV-A): a refractory filter, then a spatio-temporal neighbourhood
filter. Both keep per-pixel state across chunks, so a stream can be filtered chunk by chunk."""

from __future__ import annotations

import numba
import numpy as np

from eventocc.receiver.pipeline.config import FilterParams

_NEVER = np.iinfo(np.int64).min // 2


@numba.njit(cache=True, nogil=True)
def _filter_kernel(events, pixels, refractory_rule, neighbourhood_rule):
    """Which of the ``events`` = (t, x, y, p) pass, updating ``pixels`` = (last_pos, last_neg,
    last_kept) (each pixel's last event of each polarity, its last kept one);
    ``refractory_rule`` = (on, same_us, oppo_us), ``neighbourhood_rule`` = (on, radius,
    window_us, min_neighbours)."""
    t, x, y, p = events
    last_pos, last_neg, last_kept = pixels
    refractory, same_us, oppo_us = refractory_rule
    neighbourhood, radius, window_us, min_neighbours = neighbourhood_rule
    n = t.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    height, width = last_kept.shape
    for i in range(n):
        xi, yi, ti = x[i], y[i], t[i]
        same = last_pos if p[i] > 0 else last_neg
        oppo = last_neg if p[i] > 0 else last_pos
        passed = True
        if refractory:
            passed = ti - same[yi, xi] >= same_us and ti - oppo[yi, xi] >= oppo_us
        same[yi, xi] = ti  # every event restarts the refractory period, kept or not
        if not passed:
            continue
        if neighbourhood:
            count = 0
            for yy in range(max(0, yi - radius), min(height, yi + radius + 1)):
                for xx in range(max(0, xi - radius), min(width, xi + radius + 1)):
                    if (yy != yi or xx != xi) and ti - last_kept[yy, xx] <= window_us:
                        count += 1
            passed = count >= min_neighbours
        last_kept[yi, xi] = ti  # "recorded" events support their neighbours' checks
        keep[i] = passed
    return keep


class EventFilter:
    """Stateful refractory + neighbourhood filter over a stream of event chunks."""

    def __init__(self, params: FilterParams, width: int, height: int) -> None:
        if params.radius_px < 1 or params.min_neighbours < 0:
            raise ValueError("neighbourhood radius must be >= 1 px and min_neighbours >= 0")
        self.params = params
        self._last_pos = np.full((height, width), _NEVER, np.int64)
        self._last_neg = np.full((height, width), _NEVER, np.int64)
        self._last_kept = np.full((height, width), _NEVER, np.int64)

    @property
    def active(self) -> bool:
        return self.params.refractory or self.params.neighbourhood

    def __call__(self, events: np.ndarray) -> np.ndarray:
        if not self.active or not len(events):
            return events
        q = self.params
        keep = _filter_kernel(
            (events["t"], events["x"], events["y"], events["p"]),
            (self._last_pos, self._last_neg, self._last_kept),
            (q.refractory, q.same_polarity_us, q.opposite_polarity_us),
            (q.neighbourhood, q.radius_px, q.window_us, q.min_neighbours),
        )
        return events[keep]
