"""Paper Table "Localization Accuracy": five hand-held sequences, pose and data together.

N = 16 on a 27.2 cm marker, office light (250 lux), the paper profile. Each sequence is a smooth
6-DoF wander with its own seed and mean marker flow. ATE and RPE as the paper computes them:
rigid Umeyama alignment (scale fixed by the marker's size), RPE over 100 ms.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from bench.experiments.eventcam import (
    EventRun,
    Sensor,
    camera,
    fitting_distance,
    run_event_receiver,
)
from occ.stream import StreamEncoder
from receiver.pipeline.metrics import pose_errors, umeyama
from receiver.sim import HandHeldMotion, Scene, SensorModel

SEQUENCES = ((1, 0.6), (2, 0.8), (3, 1.0), (4, 1.2), (5, 1.5))
"""(seed, mean marker flow in px/ms) of the five sequences."""
DISTANCE_M = 0.6
"""Mean hand-held distance on the full sensor (scaled up for crops so the marker fits)."""
MESSAGE_BYTES = 2048
MIN_POSES = 20
"""Fewer poses than this get no ATE/RPE: a rigid fit to a handful of points is near-perfect."""
PAPER_TABLE = (
    # time s, R_rpe deg, t_rpe cm, t_ate cm, BER
    (107, 0.29, 0.53, 1.55, 0.0078),
    (112, 0.32, 0.57, 1.40, 0.0118),
    (104, 0.23, 0.38, 1.43, 0.0072),
    (112, 0.28, 0.52, 1.63, 0.0104),
    (110, 0.33, 0.66, 1.96, 0.0113),
)


@dataclass(frozen=True)
class SequenceResult:
    seed: int
    flow_px_per_ms: float
    time_s: float
    rpe_rot_deg: float
    rpe_trans_cm: float
    ate_cm: float
    ber: float | None
    decodable: bool
    """At least one verified message completed (FEC recovered the data)."""
    poses: int
    wall_s: float

    def to_dict(self) -> dict:
        """JSON-ready: NaN (no poses to score) becomes None."""
        return {
            k: None if isinstance(v, float) and math.isnan(v) else v
            for k, v in asdict(self).items()
        }


def scene(seed: int, flow: float, sensor: Sensor) -> Scene:
    message = np.random.default_rng(seed).integers(0, 256, MESSAGE_BYTES, np.uint8).tobytes()
    return Scene(
        encoder=StreamEncoder(message, profile="paper", cells=16),
        marker_size_m=0.272,
        camera=camera(sensor),
        motion=HandHeldMotion(fitting_distance(sensor, DISTANCE_M), flow, seed=seed),
        sensor=SensorModel.preset("gen4-indoor", lux=250.0),
        seed=seed,
    )


def score(seed: int, flow: float, run: EventRun, duration_s: float) -> SequenceResult:
    nan = float("nan")
    rot = trans = ate = nan
    if len(run.pose_t_us) >= MIN_POSES:
        err = pose_errors(run.pose_t_us, run.poses, run.truth)
        rot, trans, ate = err.rpe_rot_rmse_deg, err.rpe_trans_rmse_m * 100, err.ate_rmse_m * 100
    rep = run.report
    decodable = any(m["verified"] for m in rep["messages"])
    return SequenceResult(
        seed,
        flow,
        duration_s,
        rot,
        trans,
        ate,
        rep["ber"],
        decodable,
        len(run.pose_t_us),
        run.wall_s,
    )


def run_sequence(
    seed: int, flow: float, duration_s: float, sensor: Sensor
) -> tuple[SequenceResult, EventRun]:
    run = run_event_receiver(scene(seed, flow, sensor), duration_s)
    return score(seed, flow, run, duration_s), run


def aligned_positions(run: EventRun) -> np.ndarray:
    """(n, 3) estimated positions after the rigid alignment the ATE uses."""
    R, t = umeyama(run.poses[:, :3, 3], run.truth[:, :3, 3])
    return run.poses[:, :3, 3] @ R.T + t
