"""Paper Fig. exp_a: BER before FEC and goodput after FEC of a static camera, per marker size N.

The camera stands 1.25 m in front of the screen and the marker fills its view: the marker is
sized so each cell covers as many pixels as in the paper (30 px at N = 16 down to 7 px at N = 96,
scaled with the sensor height on a cropped sensor) where that fits. The paper's marker has
one-cell exterior rings, so at those sizes it just fills 720 px; ours widens the rings with N
(``ceil(N / 16)`` cells), which at the paper's pixels per cell would overflow the view from
N = 32 on, so there the cells shrink until the white ring fits (``cell_px``). Each point streams
a fresh random message.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from bench.experiments.eventcam import Sensor, camera, clip_message, raw_bps, run_event_receiver
from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.sim import Display, Optics, Scene, SensorModel, StaticMotion
from eventocc.receiver.sim.scene import marker_size_for_cell_px

DISTANCE_M = 1.25
PAPER_CELL_PX = {16: 30, 32: 18, 48: 13, 64: 10, 80: 8, 96: 7}
"""Pixels per cell the paper reports for each N (its Section V-A), on its 720 px high sensor."""
FIT_SHARE = 0.9
"""The white ring (what detection and tracking need) spans at most this share of the sensor
height, leaving a margin for the blur and the detector's search."""
PAPER_PEAK_BPS = 114_000
SENSOR = "evk4"
"""The camera: the paper's (``ideal`` is the upper bound ``bench.realistic`` draws)."""


@dataclass(frozen=True)
class StreamingPoint:
    profile: str
    refresh_hz: float
    cells: int
    lux: float
    seed: int
    ber: float | None
    goodput_bps: float
    """Verified message bits per second of the frames that carried them (``EventRun.goodput_bps``:
    the paper's throughput after FEC); 0 when the message did not complete within the clip."""
    raw_bps: float
    """Physical limit: N^2 bits per data frame at the data frame rate."""
    cell_px: float
    """Pixels per cell at the marker centre (``cell_px``)."""
    paper_cell_px: float
    """The paper's pixels per cell, scaled to the sensor height."""
    locked: bool
    wall_s: float

    def to_dict(self) -> dict:
        return asdict(self)


def paper_cell_px(cells: int, cam: CameraModel) -> float:
    """The paper's pixels per cell for payload side ``cells``, scaled with the sensor height."""
    return PAPER_CELL_PX[cells] * cam.height / 720


def cell_px(cells: int, cam: CameraModel) -> float:
    """Pixels per cell to show payload side ``cells`` with: the paper's, capped so our marker's
    white ring fits within ``FIT_SHARE`` of the view."""
    fits = FIT_SHARE * cam.height / MarkerGeometry(cells).tracked_side
    return min(paper_cell_px(cells, cam), fits)


def static_scene(encoder: StreamEncoder, cam: CameraModel, **kwargs) -> Scene:
    """The paper's static set-up for ``encoder``: 1.25 m away, the marker filling the view
    (``cell_px``); ``kwargs`` go to ``Scene`` (display, sensor, seed)."""
    size = marker_size_for_cell_px(
        cell_px(encoder.geometry.cells, cam), encoder.geometry, DISTANCE_M, cam.K[0, 0]
    )
    return Scene(
        encoder=encoder,
        marker_size_m=size,
        camera=cam,
        motion=StaticMotion(DISTANCE_M),
        **kwargs,
    )


def run_point(
    profile: str,
    refresh_hz: float,
    cells: int,
    lux: float,
    seed: int,
    duration_s: float,
    sensor: Sensor,
) -> StreamingPoint:
    cam = camera(sensor)
    encoder = StreamEncoder(
        clip_message(profile, cells, refresh_hz, duration_s, seed), profile=profile, cells=cells
    )
    data_every = encoder.profile.data_every
    scene = static_scene(
        encoder,
        cam,
        display=Display(refresh_hz=refresh_hz),
        sensor=SensorModel.preset(SENSOR, lux=lux),
        optics=Optics.preset(SENSOR),
        seed=seed,
    )
    run = run_event_receiver(scene, duration_s)
    return StreamingPoint(
        profile,
        refresh_hz,
        cells,
        lux,
        seed,
        run.report["ber"],
        run.goodput_bps(len(encoder.message) * 8, data_every / refresh_hz),
        raw_bps(cells, refresh_hz, data_every),
        scene.cell_px(),
        paper_cell_px(cells, cam),
        run.report["locked"],
        run.wall_s,
    )
