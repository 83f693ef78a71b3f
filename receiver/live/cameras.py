"""Live event cameras through optional vendor backends, each turned into our event chunks.

None of these packages is a dependency: a backend imports its package only when asked for, and
says which extra (or SDK) to install when it is missing.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from eventocc.receiver.events import make_events
from eventocc.receiver.live.sources import SourceError, StayLive

CHUNK_US = 10_000


@dataclass(frozen=True)
class Backend:
    module: str
    install: str
    opener: Callable[[str], LiveCamera]


class LiveCamera:
    """A live sensor; ``chunks`` runs until the camera is unplugged or the daemon stops, and
    skips ahead whenever its consumer falls behind (``StayLive``)."""

    def __init__(
        self,
        width: int,
        height: int,
        chunks: Iterator[np.ndarray],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.width, self.height = width, height
        self._chunks = chunks
        self._live = StayLive(clock=clock)

    @property
    def speed(self) -> float | None:
        return self._live.speed

    def chunks(self) -> Iterator[np.ndarray]:
        return self._live(self._chunks)


def _open_neuromorphic_drivers(serial: str) -> LiveCamera:
    import neuromorphic_drivers as nd

    device = nd.open(serial=serial) if serial else nd.open()
    width, height = device.properties().width, device.properties().height

    def chunks() -> Iterator[np.ndarray]:
        with device:
            for _status, packet in device:
                events = packet.get("dvs_events") if isinstance(packet, dict) else None
                if events is not None and len(events):
                    yield make_events(
                        events["t"].astype(np.int64), events["x"], events["y"], events["on"]
                    )

    return LiveCamera(width, height, chunks())


def _open_metavision(serial: str) -> LiveCamera:
    from metavision_core.event_io import EventsIterator

    iterator = EventsIterator(input_path=serial, mode="delta_t", delta_t=CHUNK_US)
    height, width = iterator.get_size()
    chunks = (make_events(ev["t"], ev["x"], ev["y"], ev["p"]) for ev in iterator if len(ev))
    return LiveCamera(width, height, chunks)


def _open_dv(serial: str) -> LiveCamera:
    import dv_processing as dv

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
}


def open_live_camera(backend: str, serial: str = "") -> LiveCamera:
    """Open the first camera of ``backend`` (or the one with this serial number)."""
    spec = LIVE_BACKENDS[backend]
    try:
        importlib.import_module(spec.module)
    except ImportError:
        raise SourceError(
            f"live camera source {backend}: needs the {spec.module} package; {spec.install}"
        ) from None
    try:
        return spec.opener(serial)
    except Exception as error:  # vendor errors have no common base; keep their message
        raise SourceError(f"live camera source {backend}: no camera opened ({error})") from error
