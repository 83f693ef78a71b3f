"""Live event cameras through optional vendor backends, each turned into our event chunks.

None of these packages is a dependency: a backend imports its package only when asked for, and
says which extra (or SDK) to install when it is missing.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventocc.occ.report import CameraReport
from eventocc.receiver.events import make_events
from eventocc.receiver.live.controls import CameraSettings, SensorReadings
from eventocc.receiver.live.sources import EventSource, SourceError, StayLive

log = logging.getLogger(__name__)

CHUNK_US = 10_000


@dataclass(frozen=True)
class Backend:
    module: str
    install: str
    opener: Callable[[str, CameraSettings], EventSource]


class LiveCamera:
    """A live sensor; ``chunks`` runs until the camera is unplugged or the daemon stops, and
    skips ahead whenever its consumer falls behind (``StayLive``). ``readings``: the camera's
    own (temperature, light), when its backend can ask."""

    def __init__(
        self,
        width: int,
        height: int,
        chunks: Iterator[np.ndarray],
        *,
        readings: SensorReadings | None = None,
        max_event_rate: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.width, self.height = width, height
        self._chunks = chunks
        self._live = StayLive(clock=clock)
        self.readings = readings
        self.max_event_rate = max_event_rate

    @property
    def speed(self) -> float | None:
        return self._live.speed

    def camera_report(self) -> CameraReport | None:
        if self.readings is None:
            return None
        self.readings.poll()
        return self.readings.report(max_event_rate=self.max_event_rate)

    def chunks(self) -> Iterator[np.ndarray]:
        return self._live(self._chunks)


def _open_neuromorphic_drivers(serial: str, settings: CameraSettings) -> EventSource:
    from eventocc.receiver.live.nd_camera import open_nd_camera

    return open_nd_camera(serial, settings)


def _open_nd_replay(path: str, settings: CameraSettings) -> EventSource:
    from eventocc.receiver.live.nd_camera import NdCamera
    from eventocc.receiver.live.nd_replay import RawReplay

    return NdCamera(RawReplay(Path(path)), settings)


METAVISION_FACILITIES: dict[str, tuple[str, ...]] = {
    "get_i_erc_module": ("enable", "set_cd_event_rate"),
    "get_i_ll_biases": ("get_all_biases", "set"),
    "get_i_monitoring": ("get_temperature", "get_illumination"),
}
"""The HAL facilities (device getter: methods) the metavision: backend calls, as OpenEB's
Python bindings name them. The SDK is not on PyPI: tests check these against metavision_hal
where it is installed, and drive the backend with a device of this shape."""


def _open_metavision(serial: str, settings: CameraSettings) -> LiveCamera:
    from metavision_core.event_io import EventsIterator
    from metavision_core.event_io.raw_reader import initiate_device

    device = initiate_device(path=serial)
    limit = _metavision_controls(device, settings)
    iterator = EventsIterator.from_device(device=device, delta_t=CHUNK_US)
    height, width = iterator.get_size()
    chunks = (make_events(ev["t"], ev["x"], ev["y"], ev["p"]) for ev in iterator if len(ev))
    monitoring = device.get_i_monitoring()
    readings = None
    if monitoring is not None:
        readings = SensorReadings(monitoring.get_temperature, monitoring.get_illumination, "lux")
    return LiveCamera(width, height, chunks, readings=readings, max_event_rate=limit)


def _metavision_controls(device, settings: CameraSettings) -> float | None:
    """The event rate controller (ERC) and the biases, through the HAL's facilities (the
    names ``METAVISION_FACILITIES`` lists); returns the limit in force."""
    limit = None
    erc = device.get_i_erc_module()
    if settings.max_event_rate is None or erc is None:
        if erc is not None:
            erc.enable(False)
        elif settings.max_event_rate is not None:
            log.info("this camera has no event rate controller: no limit set")
    else:
        limit = settings.rate_in_force
        erc.set_cd_event_rate(int(limit))
        erc.enable(True)
    if settings.biases:
        biases = device.get_i_ll_biases()
        if biases is None:
            raise SourceError("this camera's biases cannot be set")
        known = dict(biases.get_all_biases())
        for name, value in settings.biases.items():
            full = name if name.startswith("bias_") else f"bias_{name}"
            if full not in known:
                raise SourceError(f"the camera has no bias {name}; its biases: {', '.join(known)}")
            if not biases.set(full, value):
                raise SourceError(f"the camera refused bias {full}={value}")
    return limit


def _open_dv(serial: str, settings: CameraSettings) -> LiveCamera:
    import dv_processing as dv

    if settings.biases:
        raise SourceError(
            "the dv: backend sets no biases (iniVation's are per model): drop --bias, or set "
            "them with iniVation's DV software"
        )
    if settings.max_event_rate is not None:
        log.info("dv-processing's cameras have no event-rate limiter: no limit set")
    camera = dv.io.camera.open(serial) if serial else dv.io.camera.open()
    width, height = camera.getEventResolution()

    def chunks() -> Iterator[np.ndarray]:
        while camera.isRunning():
            batch = camera.getNextEventBatch()
            if batch is not None and len(batch):
                ev = batch.numpy()
                yield make_events(ev["timestamp"], ev["x"], ev["y"], ev["polarity"])

    return LiveCamera(width, height, chunks())


LIVE_BACKENDS: dict[str, Backend] = {
    "nd": Backend(
        "neuromorphic_drivers", "pip install 'eventocc[live-nd]'", _open_neuromorphic_drivers
    ),
    "metavision": Backend(
        "metavision_core",
        "install OpenEB or the Metavision SDK with its Python bindings (not on PyPI)",
        _open_metavision,
    ),
    "dv": Backend("dv_processing", "pip install 'eventocc[live-dv]'", _open_dv),
    "nd-replay": Backend(
        "neuromorphic_drivers", "pip install 'eventocc[live-nd]'", _open_nd_replay
    ),
}


def open_live_camera(
    backend: str, serial: str = "", settings: CameraSettings | None = None
) -> EventSource:
    """Open the first camera of ``backend`` (or the one with this serial number; for
    ``nd-replay``, the recording at this path) with ``settings`` (default: ``CameraSettings()``)."""
    spec = LIVE_BACKENDS[backend]
    try:
        importlib.import_module(spec.module)
    except ImportError:
        raise SourceError(
            f"live camera source {backend}: needs the {spec.module} package; {spec.install}"
        ) from None
    try:
        return spec.opener(serial, settings or CameraSettings())
    except SourceError:
        raise
    except Exception as error:  # vendor errors have no common base; keep their message
        raise SourceError(f"live camera source {backend}: no camera opened ({error})") from error
