"""A recording replayed as a Prophesee EVK4 behind neuromorphic-drivers: ``nd-replay:PATH``.

``RawReplay`` has the device shape the package declares (``PropheseeEvk4Device``: iteration
yielding its ``Status`` and ``Evt3Packet``, ``backlog``, ``clear_backlog``, ``overflow``,
``update_configuration``, ...), and the timing of a USB camera: the recording's events fill USB
buffers of ``buffer_us`` at the pace of its clock; a buffer goes into a ring of
``ring_length`` when complete, or is lost when the ring is full, and the next one kept marks
the loss in ``polarity_events_overflow_indices``, as the driver does. Each ``next`` decodes and
hands over up to ``packets_per_next`` buffers, or waits for one; ``clear_backlog`` drops
buffers undecoded. The sensor's rate limiter is applied when
configured; a recording's biases are what they were. So the whole live path
(``nd_camera.NdCamera``, the daemon, the pipeline) runs on any machine.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from eventocc.receiver.events import rechunk_by_time
from eventocc.receiver.live.nd_camera import POLARITY_DTYPE
from eventocc.receiver.live.sources import LiveClock, SourceError


class RawReplay:
    def __init__(
        self,
        path: Path,
        *,
        buffer_us: int = 1000,
        ring_length: int = 4096,
        packets_per_next: int = 64,
        clock: Callable[[], float] = time.time,
        sleep: Callable[[float], None] = time.sleep,
        readings: tuple[float, int] | None = None,
    ) -> None:
        """``readings``: the (temperature in Celsius, illuminance) to report, as a camera
        would; None: the device says it cannot (a recording has none)."""
        import neuromorphic_drivers as nd

        from eventocc.receiver.io import EventFileError, read_events

        self._nd = nd
        if not path.is_file():
            raise SourceError(f"no recording at {path}: give an event file's path")
        try:
            self._stream = read_events(path)
        except EventFileError as error:
            raise SourceError(str(error)) from None
        if self._stream.width is None or self._stream.height is None:
            raise SourceError(f"{path} does not state its sensor size; convert it first")
        self._properties = nd.prophesee_evk4.Properties(self._stream.width, self._stream.height)
        self.buffer_us, self.ring_length = buffer_us, ring_length
        self.packets_per_next = packets_per_next
        self.readings = readings
        self.configuration = nd.prophesee_evk4.Configuration()
        self.dropped_packets = 0
        """Buffers lost because the ring was full."""
        self.decoded = 0
        """Buffers handed over decoded (the rest were lost, or cleared from the backlog)."""
        self._clock = clock
        self._pace = LiveClock(clock=clock, sleep=sleep)
        self._buffers = self._cut()
        self._due: np.ndarray | None = None  # the next buffer, not complete yet
        self._ring: deque[tuple[float, bool, np.ndarray]] = deque()  # (arrived, after loss, events)
        self._lost = False  # buffers were lost since the last one kept
        self._overflowed = False

    # --- the device protocol ------------------------------------------------------------------
    def __enter__(self) -> RawReplay:
        return self

    def __exit__(self, *exc: object) -> bool:
        self.close()
        return False

    def close(self) -> None:
        self._stream.close()

    def __iter__(self) -> RawReplay:
        return self

    def __next__(self) -> tuple[Any, Any]:
        self._arrive()
        while not self._ring:
            if self._due is None:
                raise StopIteration
            self._pace.wait(int(self._due["t"][-1]))
            self._arrive()
        taken = [self._ring.popleft() for _ in range(min(self.packets_per_next, len(self._ring)))]
        starts = np.cumsum([0] + [len(events) for _, _, events in taken[:-1]])
        lost_at = [int(start) for start, (_, lost, _) in zip(starts, taken, strict=True) if lost]
        packet = self._nd.Evt3Packet()
        packet.polarity_events = _polarity_events(np.concatenate([ev for _, _, ev in taken]))
        self.decoded += len(taken)
        packet.polarity_events_overflow_indices = np.array(lost_at, np.uint64) if lost_at else None
        packet.trigger_events = packet.trigger_events_overflow_indices = None
        status = self._nd.status.Status(
            system_time=self._clock(),
            ring=self._nd.status.RingStatus(
                system_time=taken[0][0],
                backlog=len(self._ring),
                raw_packets=len(taken),
                clutch_engaged=False,
                current_t=int(packet.polarity_events["t"][-1]),
                dropped_packets=self.dropped_packets,
            ),
        )
        return status, packet

    def backlog(self) -> int:
        self._arrive()
        return len(self._ring)

    def clear_backlog(self, until: int) -> None:
        """Drop waiting buffers undecoded until fewer than ``until`` wait (0: all of them)."""
        self._arrive()
        while self._ring:
            self._ring.popleft()
            if len(self._ring) < until:
                return

    def overflow(self) -> bool:
        return self._overflowed

    def name(self) -> Any:
        return self._nd.Name.PROPHESEE_EVK4

    def properties(self) -> Any:
        return self._properties

    def serial(self) -> str:
        return f"replay:{self._stream.path.name}"

    def biases_bounds(self) -> Any:
        """Any value: ``update_configuration`` then says a recording keeps its biases."""
        evk4 = self._nd.prophesee_evk4
        wide = evk4.Bounds(-(1 << 15), (1 << 15) - 1)
        return evk4.BiasesBounds(**{f.name: wide for f in dataclasses.fields(evk4.BiasesBounds)})

    def connection(self) -> Any:
        return self._nd.Connection.USB_SUPER

    def update_configuration(self, configuration: Any) -> None:
        if configuration.biases != self.configuration.biases:
            raise SourceError("a recording keeps the biases it was recorded with: drop --bias")
        self.configuration = configuration

    def temperature_celsius(self) -> float:
        if self.readings is None:
            raise RuntimeError("a recording has no temperature")
        return self.readings[0]

    def illuminance(self) -> int:
        if self.readings is None:
            raise RuntimeError("a recording has no illuminance")
        return self.readings[1]

    # --- the USB link -------------------------------------------------------------------------
    def _arrive(self) -> None:
        """Move the buffers complete by now into the ring, or lose them if it is full."""
        if self._due is None:
            self._due = next(self._buffers, None)
            if self._due is None:
                return
            self._pace.start(int(self._due["t"][0]))
        now = self._clock()
        while self._due is not None and self._pace.due_s(int(self._due["t"][-1])) <= now:
            if len(self._ring) < self.ring_length:
                arrived = self._pace.due_s(int(self._due["t"][-1]))
                self._ring.append((arrived, self._lost, self._due))
                self._lost = False
            else:
                self.dropped_packets += 1
                self._lost = self._overflowed = True
            self._due = next(self._buffers, None)

    def _cut(self) -> Iterator[np.ndarray]:
        """The USB buffers: one per ``buffer_us`` (per limiter period, with a limiter, which
        counts within it); the configuration is read when the first one is asked for."""
        limiter = self.configuration.rate_limiter
        window = self.buffer_us if limiter is None else limiter.reference_period_us
        for chunk in rechunk_by_time(self._stream, window):
            limited = _limit(chunk, limiter)
            if len(limited):
                yield limited


def _polarity_events(events: np.ndarray) -> np.ndarray:
    """Our events as the driver's ``polarity_events``."""
    out = np.empty(len(events), POLARITY_DTYPE)
    out["t"], out["x"], out["y"], out["on"] = events["t"], events["x"], events["y"], events["p"] > 0
    return out


def _limit(events: np.ndarray, limiter: Any) -> np.ndarray:
    """What a sensor's rate limiter lets through: in each period of ``reference_period_us``
    at most ``maximum_events_per_period`` events, spread evenly over those it saw."""
    if limiter is None or not len(events):
        return events
    period = events["t"] // limiter.reference_period_us
    starts = np.flatnonzero(np.r_[True, period[1:] != period[:-1]])
    counts = np.diff(np.r_[starts, len(events)])
    rank = np.arange(len(events)) - np.repeat(starts, counts)
    n = np.repeat(counts, counts)
    most = limiter.maximum_events_per_period
    keep = (n <= most) | ((rank + 1) * most // n > rank * most // n)
    return events[keep]
