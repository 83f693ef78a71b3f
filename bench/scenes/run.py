"""Running the receiver on a drawn scene and scoring it against the simulator's truth.

The receiver is told only what a user tells it: the link settings (profile, N, refresh rate, and
for ``paper``, which has no header, the message size), the camera's calibration and the
marker's size; it runs with its defaults, as ``eventocc-receiver decode`` builds it.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.scenes.draw import SceneDraw, draw
from eventocc.occ.profiles import get_profile
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.receiver import Receiver
from eventocc.receiver.pipeline.report import DecodeLog
from eventocc.receiver.sim import simulate
from eventocc.receiver.sim.truth import SceneTruth

OFF_M, OFF_DEG = 0.02, 2.0
"""A pose this far from the truth (either) counts as off."""
WRONG_M = 0.05
"""A pose this far from the truth counts as wrong."""
LOCK_MS = 150.0
"""The lock the issue asks for: within this long of the marker appearing."""
FIRST_LOCK_MS = 50.0
"""The poses of a lock's first this-many ms tell whether it locked right."""
BURST_GAP_US = 3000
"""ON events of one pixel further apart than this (or than a third of a refresh period) belong
to separate transitions (``on_per_transition``)."""
BURST_GRID = 3
"""``on_per_transition`` reads every this-many-th pixel of every this-many-th row."""


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (degrees) errors of poses (n, 4, 4) against the truth."""
    position = np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)
    R = np.einsum("nji,njk->nik", T_true[:, :3, :3], T_est[:, :3, :3])
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return position, np.degrees(np.arccos(cos))


@dataclass(frozen=True)
class PoseScore:
    poses: int
    off_share: float | None
    """Share of the poses more than ``OFF_M`` or ``OFF_DEG`` off (None: no pose)."""
    wrong_share: float | None
    """Share more than ``WRONG_M`` off."""
    wrong: int
    max_error_cm: float | None
    median_error_cm: float | None
    median_error_deg: float | None


def score_poses(position_m: np.ndarray, rotation_deg: np.ndarray) -> PoseScore:
    if not len(position_m):
        return PoseScore(0, None, None, 0, None, None, None)
    off = (position_m > OFF_M) | (rotation_deg > OFF_DEG)
    wrong = position_m > WRONG_M
    return PoseScore(
        len(position_m),
        float(off.mean()),
        float(wrong.mean()),
        int(wrong.sum()),
        float(100 * position_m.max()),
        float(100 * np.median(position_m)),
        float(np.median(rotation_deg)),
    )


def reason_kind(reason: str) -> str:
    """A detection failure's reason without its numbers, so that like ones add up."""
    return re.sub(r"[-+]?\d+(\.\d+)?%?", "#", reason)


def on_per_transition(t: np.ndarray, pixel: np.ndarray, gap_us: float) -> tuple[float, float]:
    """Median and 90th percentile of the ON events a pixel fires per transition, over the
    pixels that saw at least three transitions (noise fires alone, and seldom)."""
    if len(t) < 10:
        return float("nan"), float("nan")
    order = np.lexsort((t, pixel))
    t, pixel = t[order], pixel[order]
    start = np.ones(len(t), bool)
    start[1:] = (pixel[1:] != pixel[:-1]) | (np.diff(t) > gap_us)
    starts = np.flatnonzero(start)
    sizes = np.diff(np.append(starts, len(t)))
    bursts = np.bincount(np.unique(pixel[starts], return_inverse=True)[1])
    busy = np.repeat(bursts >= 3, bursts)
    if not busy.any():
        return float("nan"), float("nan")
    return float(np.median(sizes[busy])), float(np.percentile(sizes[busy], 90))


def lock_rightness(
    lock_times_us: list[int], t: np.ndarray, position: np.ndarray
) -> list[bool | None]:
    """Per lock, whether it locked right: its poses of its first ``FIRST_LOCK_MS`` (before the
    next lock) all lie within ``WRONG_M`` of the truth (None: it published no pose then)."""
    out: list[bool | None] = []
    for k, start in enumerate(lock_times_us):
        end = start + FIRST_LOCK_MS * 1e3
        if k + 1 < len(lock_times_us):
            end = min(end, lock_times_us[k + 1])
        early = (t >= start) & (t < end)
        out.append(bool(position[early].max() <= WRONG_M) if early.any() else None)
    return out


def receiver_config(draw: SceneDraw, camera: CameraModel) -> ReceiverConfig:
    """What a user tells the receiver of ``draw``: the link settings, the calibration and the
    marker's size; everything else at its defaults."""
    return ReceiverConfig(
        camera,
        cells=draw.cells,
        profile=draw.profile,
        refresh_hz=draw.refresh_hz,
        marker_size_m=draw.marker_size_m,
    )


def run_scene(draw: SceneDraw) -> dict:
    """Simulate ``draw`` and decode it with the streaming receiver; its scores, flat."""
    wall0 = time.perf_counter()
    scene = draw.scene()
    rec = simulate(scene, draw.duration_s)
    config = receiver_config(draw, scene.camera)
    framed = get_profile(draw.profile).framed
    receiver = Receiver(config, message_size=None if framed else draw.message_bytes)
    log = DecodeLog(receiver, SceneTruth(scene))
    appears = scene.marker_appears_us
    on_t, on_pixel = [], []
    sim_cpu = 0.0

    def chunks() -> Iterator[np.ndarray]:
        nonlocal sim_cpu
        it = iter(rec)
        while True:
            t0 = time.process_time()
            chunk = next(it, None)
            sim_cpu += time.process_time() - t0
            if chunk is None:
                return
            yield chunk

    for chunk in chunks():
        log.add(receiver.push(chunk))
        on = chunk[
            (chunk["p"] > 0) & (chunk["x"] % BURST_GRID == 0) & (chunk["y"] % BURST_GRID == 0)
        ]
        on = on[on["t"] >= appears]
        on_t.append(on["t"])
        on_pixel.append(on["y"].astype(np.int64) * scene.camera.width + on["x"])
    log.add(receiver.finish())
    sent = scene.encoder.message
    right = [m.t_us for m in log.messages if m.message.data == sent]
    delivered_us = right[0] if right else None
    wrong_messages = len(log.messages) - len(right)
    report = log.report()
    st = receiver.stats
    t = np.array(log.pose_t, np.int64)
    est = np.array(log.poses).reshape(-1, 4, 4)
    verified = np.array(log.pose_verified, bool)
    position, rotation = pose_errors(est, rec.pose_at(t)) if len(t) else (np.empty(0),) * 2
    tentative = score_poses(position[~verified], rotation[~verified])
    locks_ms = [(u - appears) / 1e3 for u in st.lock_times_us]
    first = locks_ms[0] if locks_ms else None
    right = lock_rightness(st.lock_times_us, t, position)
    right_ms = next((ms for ms, ok in zip(locks_ms, right, strict=True) if ok and ms >= 0), None)
    period = 1e6 / draw.refresh_hz
    on_median, on_p90 = on_per_transition(
        np.concatenate(on_t), np.concatenate(on_pixel), min(BURST_GAP_US, period / 3)
    )
    rx_cpu = sum(report["cpu_s"].values())
    return {
        "draw": draw.to_dict(),
        "cell_px_scene": scene.cell_px(),
        "events": st.events,
        "on_per_transition": None if math.isnan(on_median) else on_median,
        "on_per_transition_p90": None if math.isnan(on_p90) else on_p90,
        "first_lock_ms": first,
        "locked_before_marker": bool(locks_ms and locks_ms[0] < 0),
        "right_lock_ms": right_ms,
        "lock_ok": right_ms is not None and right_ms <= LOCK_MS,
        "first_lock_wrong": bool(right and right[0] is False),
        "wrong_locks": sum(ok is False for ok in right),
        "locks": len(locks_ms),
        "losses": st.losses,
        **{
            f"pose_{k}": v
            for k, v in asdict(score_poses(position[verified], rotation[verified])).items()
        },
        "tentative_poses": tentative.poses,
        "tentative_off_share": tentative.off_share,
        "tentative_wrong": tentative.wrong,
        "verified_ms": (t[verified][0] - appears) / 1e3 if verified.any() else None,
        "delivered": delivered_us is not None,
        "delivered_ms": None if delivered_us is None else (delivered_us - appears) / 1e3,
        "wrong_messages": wrong_messages,
        "ber": report["ber"],
        "bits_scored": report["bits_scored"],
        "frames_read": st.frames_read,
        "frames_seen": st.frames_seen,
        "detection_failures": report["detection_failures"],
        "realtime_factor": report["realtime_factor"],
        "receiver_cpu_s": rx_cpu,
        "sim_cpu_s": sim_cpu,
        "wall_s": time.perf_counter() - wall0,
    }


def earlier_results(path: Path, seed: int) -> dict[int, dict]:
    """Results printed by an earlier run (its output, one JSON line per scene) whose scene is
    still drawn the same, by index: the simulator and the receiver give such a scene the same
    outputs again."""
    found = {}
    for line in path.read_text().splitlines():
        if line.startswith("{"):
            r = json.loads(line)
            d = r["draw"]
            if d["seed"] == seed and draw(seed, d["index"]).to_dict() == d:
                found[d["index"]] = r
    return found
