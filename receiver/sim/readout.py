"""What a real camera does with more events than it can carry: the sensor's readout, its
event-rate controller and the link to the host, applied in that order to the packed events.

- **Sensor readout** (``SensorModel.readout_hz``): the arbiter reads events out one after the
  other at a fixed peak rate and timestamps them as it does; beyond that rate they wait, so a
  burst comes out with late timestamps (none is lost here).
- **Event-rate controller** (``erc_hz`` over ``erc_period_us``): the sensor's ERC keeps at most
  ``erc_hz * erc_period_us`` events of each period, dropping the excess evenly over the period.
- **Link** (``link_hz``, ``link_buffer``): the camera buffers what the link cannot send at once;
  while that buffer is full, arriving events are lost (as iniVation's cameras count "dropped DVS
  events on the device due to full USB buffers", libcaer's ``DVX_MUX_STATISTICS_DVS_DROPPED``).
  The link drains continuously, and the events that share a microsecond timestamp reach it
  spread over that microsecond in no order of their place on the sensor (drawn at random here),
  so a full buffer thins them evenly over the view. Draining in whole-microsecond steps would
  let each step's room go to the first events of the microsecond, which the packing orders by
  row: the top of the view would keep its events and the bottom lose nearly all of them. The
  link only delays delivery: the surviving events keep their sensor timestamps.

The stages see the events in time order, window after window, and carry their state across
windows; they draw from their own random stream, so a scene without them keeps its events bit
for bit.
"""

from __future__ import annotations

import numba
import numpy as np

from eventocc.receiver.sim.sensor import SensorModel


class Readout:
    """The readout stages of ``sensor`` that are switched on, with their state."""

    def __init__(self, sensor: SensorModel, rng: np.random.Generator) -> None:
        self.sensor = sensor
        self._rng = rng
        self._next_free_us = -np.inf
        """Sensor readout: when the arbiter can read its next event."""
        self._queued = 0.0
        self._queued_at_us = -np.inf
        """Link: events waiting in the camera's buffer, as of this time."""
        self.delayed = 0
        self.dropped_erc = 0
        self.dropped_link = 0

    @property
    def active(self) -> bool:
        s = self.sensor
        return s.readout_hz is not None or s.erc_hz is not None or s.link_hz is not None

    def apply(self, events: np.ndarray) -> np.ndarray:
        """The events (sorted by time) that leave the camera, with their timestamps."""
        s = self.sensor
        if not len(events):
            return events
        if s.readout_hz is not None:
            t, self._next_free_us = _arbiter(
                events["t"].astype(np.float64), 1e6 / s.readout_hz, self._next_free_us
            )
            t_us = np.rint(t).astype(events["t"].dtype)
            self.delayed += int(np.count_nonzero(t_us != events["t"]))
            events = events.copy()
            events["t"] = t_us
        if s.erc_hz is not None:
            keep = erc_keep(
                events["t"], s.erc_hz * s.erc_period_us * 1e-6, s.erc_period_us, self._rng
            )
            self.dropped_erc += int(len(keep) - np.count_nonzero(keep))
            events = events[keep]
        if s.link_hz is not None and len(events):
            keep, self._queued, self._queued_at_us = _link(
                events["t"].astype(np.float64),
                self._rng.random(len(events)),
                s.link_hz * 1e-6,
                float(s.link_buffer),
                self._queued,
                self._queued_at_us,
            )
            self.dropped_link += int(len(keep) - np.count_nonzero(keep))
            events = events[keep]
        return events


@numba.njit(cache=True)
def _arbiter(t, spacing_us, next_free):
    """Readout times of events arriving at ``t`` (sorted) at a reader that takes one event per
    ``spacing_us``: each leaves at its arrival or when the reader is free, whichever is later."""
    out = np.empty_like(t)
    for k in range(t.shape[0]):
        leave = max(t[k], next_free)
        out[k] = leave
        next_free = leave + spacing_us
    return out, next_free


def erc_keep(
    t_us: np.ndarray, per_period: float, period_us: int, rng: np.random.Generator
) -> np.ndarray:
    """Mask keeping at most ``per_period`` events in each ``period_us`` of the time-sorted
    ``t_us``, chosen evenly (a random subset) among that period's events."""
    budget = int(per_period)
    keep = np.ones(len(t_us), bool)
    period = t_us // period_us
    starts = np.flatnonzero(np.r_[True, period[1:] != period[:-1]])
    counts = np.diff(np.r_[starts, len(t_us)])
    for start, count in zip(starts[counts > budget], counts[counts > budget], strict=True):
        drop = rng.choice(count, count - budget, replace=False)
        keep[start + drop] = False
    return keep


@numba.njit(cache=True)
def _link(t, order_key, per_us, buffer, queued, queued_at):
    """Leaky bucket: the link drains ``per_us`` events per microsecond from a buffer of
    ``buffer`` events; an event arriving at a full buffer is lost. The ``n`` events stamped with
    one microsecond ``t`` (sorted) arrive at ``t + (j + 0.5) / n``, ``j`` their rank by
    ``order_key``."""
    keep = np.zeros(t.shape[0], np.bool_)
    start = 0
    while start < t.shape[0]:
        stop = start + 1
        while stop < t.shape[0] and t[stop] == t[start]:
            stop += 1
        n = stop - start
        ranked = np.argsort(order_key[start:stop]) + start if n > 1 else np.arange(start, stop)
        for j in range(n):
            k = ranked[j]
            arrival = t[start] + (j + 0.5) / n
            if arrival > queued_at:
                queued = max(queued - (arrival - queued_at) * per_us, 0.0)
                queued_at = arrival
            if queued + 1.0 <= buffer:
                queued += 1.0
                keep[k] = True
        start = stop
    return keep, queued, queued_at
