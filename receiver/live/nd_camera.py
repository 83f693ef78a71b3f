"""Cameras through neuromorphic-drivers (Prophesee EVK4 and EVK3 HD, iniVation DAVIS346 and
DVXplorer, ...), as an event source.

Its device yields ``(status, packet)``: ``packet.polarity_events`` is a structured array
(``POLARITY_DTYPE``), ``packet.polarity_events_overflow_indices`` the index of the first event
after each run of USB packets the driver lost because its ring was full. ``status.delay()`` says
how long ago the oldest USB packet in ``packet`` arrived: further behind than ``MAX_LAG_S``, the
camera skips the backlog in the driver (``clear_backlog``), which never decodes it, where a
generic live source (``sources.StayLive``) has to decode what it then drops.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time
import typing
from collections.abc import Callable, Iterator
from typing import Any, Protocol

import numpy as np

from eventocc.occ.report import CameraReport
from eventocc.receiver.events import make_events
from eventocc.receiver.live.controls import CameraSettings, SensorReadings
from eventocc.receiver.live.sources import BEHIND_NOTE_S, MAX_LAG_S, BehindNote, SourceError

log = logging.getLogger(__name__)

POLARITY_DTYPE = np.dtype([("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")])
"""``packet.polarity_events``' records: the driver builds them in Rust (its stubs say only
``numpy.ndarray``); microseconds, origin at the top-left pixel."""


class NdDevice(Protocol):
    """The part of neuromorphic-drivers' device protocols (``GenericDevice``,
    ``PropheseeEvk4Device``) this source uses; ``temperature_celsius`` and ``illuminance`` only
    where the device has them."""

    def __enter__(self) -> NdDevice: ...
    def __exit__(self, *exc: object) -> bool | None: ...
    def __iter__(self) -> NdDevice: ...
    def __next__(self) -> tuple[Any, Any]: ...
    def backlog(self) -> int: ...
    def clear_backlog(self, until: int) -> None: ...
    def name(self) -> Any: ...
    def properties(self) -> Any: ...
    def biases_bounds(self) -> Any: ...
    def update_configuration(self, configuration: Any) -> None: ...


class OverflowNote:
    """Counts the runs of USB packets the driver lost, and the event time they took; says so in
    the log at most every ``BEHIND_NOTE_S``."""

    def __init__(self) -> None:
        self.overflows = 0
        self.lost_us = 0
        self._unsaid = 0
        self._next_note = 0.0

    def packet(self, t: np.ndarray, indices: np.ndarray | None, previous_us: int | None) -> None:
        """``t``: the packet's event times; ``indices``: its overflow indices (each the first
        event after a loss); ``previous_us``: the last event time before the packet."""
        if indices is None or not len(indices):
            return
        indices = np.asarray(indices, np.int64)
        before = t[np.maximum(indices - 1, 0)]
        if previous_us is not None:
            before = np.where(indices == 0, previous_us, before)
        else:
            before = np.where(indices == 0, t[0], before)
        self.overflows += len(indices)
        self._unsaid += len(indices)
        self.lost_us += int(np.maximum(t[indices] - before, 0).sum())
        if time.monotonic() >= self._next_note:
            self._next_note = time.monotonic() + BEHIND_NOTE_S
            log.warning(
                "the camera's USB ring overflowed %d time(s), %.0f ms of events lost in all: "
                "lower --max-event-rate or the biases' sensitivity",
                self._unsaid,
                self.lost_us / 1e3,
            )
            self._unsaid = 0


class NdCamera:
    """An event source over a neuromorphic-drivers device (or anything of its shape)."""

    def __init__(
        self,
        device: NdDevice,
        settings: CameraSettings | None = None,
        *,
        max_lag_s: float = MAX_LAG_S,
        window_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        properties = device.properties()
        self.width, self.height = int(properties.width), int(properties.height)
        self.device = device
        self.max_event_rate = configure(device, settings or CameraSettings())
        self.max_lag_s, self.window_us = max_lag_s, window_s * 1e6
        self.speed: float | None = None
        """Share of the camera's event time kept over the last ``window_s`` of it."""
        self.skips = 0
        """Times the receiver fell ``max_lag_s`` behind and the driver's backlog was skipped."""
        self.overflow = OverflowNote()
        self.readings = SensorReadings(
            getattr(device, "temperature_celsius", None),
            getattr(device, "illuminance", None),
            "count",
            clock=clock,
        )
        self._note = BehindNote("receiver", "it cannot process the events as fast as they come")

    def camera_report(self) -> CameraReport:
        return self.readings.report(
            max_event_rate=self.max_event_rate,
            usb_overflows=self.overflow.overflows,
            usb_lost_s=self.overflow.lost_us / 1e6,
        )

    def chunks(self) -> Iterator[np.ndarray]:
        last_us: int | None = None  # the last event kept
        arrived_us = kept_us = 0
        skipped = False
        tie: tuple[float, int] | None = None  # (driver's wall clock, event time) since a skip
        with self.device as device:
            for status, packet in _until_stopped(device):
                self.readings.poll()
                events = None if packet is None else packet.polarity_events
                if events is None or not len(events):
                    continue
                t = events["t"].astype(np.int64)
                overflows = packet.polarity_events_overflow_indices
                self.overflow.packet(t, overflows, None if skipped else last_us)
                start_us, end_us = int(t[0]), int(t[-1])
                delay, now = status.delay(), status.system_time
                if delay is not None and delay > self.max_lag_s:
                    device.clear_backlog(until=0)
                    self.skips += 1
                    if tie is not None and now > tie[0]:
                        self._note.skipped((end_us - tie[1]) / 1e6 / (now - tie[0]))
                    skipped, tie = True, None
                    continue
                if tie is None:
                    tie = (now, end_us)
                span = end_us - (start_us if last_us is None else last_us)
                arrived_us += span
                kept_us += end_us - start_us if skipped else span
                skipped, last_us = False, end_us
                if arrived_us >= self.window_us:
                    self.speed = kept_us / arrived_us
                    self._note.measured(self.speed)
                    arrived_us = kept_us = 0
                yield make_events(t, events["x"], events["y"], events["on"])


def _until_stopped(device: NdDevice) -> Iterator[tuple[Any, Any]]:
    """The device's packets; a driver error (unplugged, USB failure) ends them with a
    ``SourceError`` saying so."""
    try:
        yield from device
    except RuntimeError as error:
        raise SourceError(f"the camera stopped: {error}") from error


def configure(device: NdDevice, settings: CameraSettings) -> float | None:
    """Set the device's event-rate limiter and biases; returns the limit in force (events/s).
    Starts from the configuration the package declares for the device: a field not set here
    keeps its default."""
    name = device.name()
    default = _configuration_type(name)()
    changes: dict[str, Any] = {}
    limit = None
    if settings.max_event_rate is not None:
        if hasattr(default, "rate_limiter"):
            limiter = vars(sys.modules[type(default).__module__])["RateLimiter"]
            changes["rate_limiter"] = limiter(settings.rate_period_us, settings.events_per_period)
            limit = settings.rate_in_force
        else:
            log.info("the %s has no event-rate limiter: none set", getattr(name, "value", name))
    if settings.biases:
        changes["biases"] = _biases(device, default.biases, settings.biases)
    if changes:
        device.update_configuration(dataclasses.replace(default, **changes))
    return limit


def _configuration_type(name: Any) -> type:
    """The package's ``Configuration`` class for the device called ``name`` (a ``nd.Name``)."""
    from neuromorphic_drivers.generated import unions

    for cls in typing.get_args(unions.Configuration):
        if cls.type() == name.name.lower():
            return cls
    raise SourceError(f"neuromorphic-drivers has no configuration for the {name.value}")


def _biases(device: NdDevice, default: Any, wanted: dict[str, int]) -> Any:
    names = [f.name for f in dataclasses.fields(default)]
    if unknown := sorted(set(wanted) - set(names)):
        raise SourceError(
            f"the camera has no bias {', '.join(unknown)}; its biases: {', '.join(names)}"
        )
    bounds = device.biases_bounds()
    for bias, value in wanted.items():
        low, high = getattr(bounds, bias).minimum, getattr(bounds, bias).maximum
        if not low <= value <= high:
            raise SourceError(f"bias {bias}={value} is outside the camera's {low} ... {high}")
    return dataclasses.replace(default, **wanted)


def open_nd_camera(serial: str, settings: CameraSettings) -> NdCamera:
    import neuromorphic_drivers as nd

    return NdCamera(nd.open(serial=serial or None), settings)
