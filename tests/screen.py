"""A short recording of a screen sending a message, for the live chain's tests."""

from __future__ import annotations

from pathlib import Path

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.calibration import save_calibration
from eventocc.receiver.live.virtual_camera import default_camera, virtual_sensor
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.receiver import Receiver
from eventocc.receiver.sim import Scene, StaticMotion, simulate
from eventocc.receiver.sim.recording import write_recording

SCREEN_MESSAGE = b"through a replayed EVK4, the driver's packets and the daemon"


def write_screen_recording(out: Path) -> Path:
    """2.5 s of the demo's virtual camera (320x180) watching a robust stream of
    ``SCREEN_MESSAGE`` from 0.6 m, into ``out``: EVT 3.0 ``events.raw`` and ``camera.yaml``."""
    scene = Scene(
        encoder=StreamEncoder(SCREEN_MESSAGE, name="replayed.txt", profile="robust", cells=16),
        marker_size_m=0.272,
        camera=default_camera(),
        motion=StaticMotion(distance_m=0.6),
        sensor=virtual_sensor(),
        seed=0,
    )
    write_recording(simulate(scene, 2.5), out, progress=False)
    save_calibration(default_camera(), out / "camera.yaml")
    return out


def screen_receiver() -> Receiver:
    """A receiver for the recording: the link settings pinned, as for any recording."""
    return Receiver(ReceiverConfig(default_camera(), cells=16, profile="robust"))


class ReportSink:
    """The daemon's sink, keeping every report."""

    def __init__(self) -> None:
        self.reports: list = []

    def publish(self, report, *, durable: bool) -> None:
        self.reports.append(report)

    def of(self, kind: type) -> list:
        return [r for r in self.reports if isinstance(r, kind)]
