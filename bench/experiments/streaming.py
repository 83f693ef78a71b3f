"""Paper Fig. exp_a: BER before FEC and goodput after FEC of a static camera, per marker size N.

The camera stands 1.25 m in front of the screen and the marker fills its view: the marker is
sized so each cell covers as many pixels as in the paper (30 px at N = 16 down to 7 px at N = 96,
scaled with the sensor height on a cropped sensor). Each point streams a fresh random message.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from bench.experiments.eventcam import Sensor, camera, run_event_receiver
from occ.stream import StreamEncoder
from receiver.sim import Display, Scene, SensorModel, StaticMotion
from receiver.sim.scene import marker_size_for_cell_px

DISTANCE_M = 1.25
PAPER_CELL_PX = {16: 30, 32: 18, 48: 13, 64: 10, 80: 8, 96: 7}
"""Pixels per cell the paper reports for each N (its Section V-A)."""
PAPER_PEAK_BPS = 114_000
MESSAGE_SHARE = 0.2
"""The message takes this share of the clip's raw capacity, leaving room for detection, FEC
and a missed first pass; it still spans many frames, so the rate is a rate."""


@dataclass(frozen=True)
class StreamingPoint:
    profile: str
    refresh_hz: float
    cells: int
    lux: float
    seed: int
    ber: float | None
    goodput_bps: float
    """Verified message bits / time from lock to the message's completion (the looping
    transmitter's net rate after FEC); 0 when it did not complete within the clip."""
    raw_bps: float
    """Physical limit: N^2 bits per data frame at the data frame rate."""
    locked: bool
    wall_s: float

    def to_dict(self) -> dict:
        return asdict(self)


def raw_bps(cells: int, refresh_hz: float, data_every: int) -> float:
    return cells**2 * refresh_hz / data_every


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
    probe = StreamEncoder(b"\0", profile=profile, cells=cells)
    limit = raw_bps(cells, refresh_hz, probe.profile.data_every)
    size = max(16, int(limit * duration_s * MESSAGE_SHARE / 8))
    message = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    encoder = StreamEncoder(message, profile=profile, cells=cells)
    cell_px = PAPER_CELL_PX[cells] * cam.height / 720
    scene = Scene(
        encoder=encoder,
        marker_size_m=marker_size_for_cell_px(cell_px, encoder.geometry, DISTANCE_M, cam.K[0, 0]),
        display=Display(refresh_hz=refresh_hz),
        camera=cam,
        motion=StaticMotion(DISTANCE_M),
        sensor=SensorModel.preset("gen4-indoor", lux=lux),
        seed=seed,
    )
    run = run_event_receiver(scene, duration_s)
    rep = run.report
    done = [m for m in rep["messages"] if m["verified"]]
    lock_s = rep["time_to_lock_s"]
    goodput = size * 8 / (done[0]["t_s"] - lock_s) if done and lock_s is not None else 0.0
    return StreamingPoint(
        profile, refresh_hz, cells, lux, seed, rep["ber"], goodput, limit, rep["locked"], run.wall_s
    )
