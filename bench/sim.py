"""Simulator speed on one core: simulated seconds per wall (and CPU) second, events/s, memory.

Run: ``NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.sim``
"""

from __future__ import annotations

import resource
import time

import numpy as np

from bench.report import write_section
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.live.virtual_camera import (
    DISTANCE_M,
    HANDHELD_FLOW_PX_PER_MS,
    default_camera,
    virtual_sensor,
)
from eventocc.receiver.sim import HandHeldMotion, Scene, SensorModel, StaticMotion, simulate
from eventocc.receiver.sim.scene import marker_size_for_cell_px

DURATION_S = 0.5
RUNS = 3
"""Runs per scene; the median is reported (the machine is shared and noisy)."""
PAPER = CameraModel.paper()
VGA = PAPER.resized(640, 480)


def _paper_marker(cells: int, cell_px: float) -> float:
    geometry = StreamEncoder(b"x", profile="paper", cells=cells).geometry
    return marker_size_for_cell_px(cell_px, geometry, 1.25, PAPER.K[0, 0])


def _paper_scene(cells: int, camera: CameraModel, motion, **kw) -> Scene:
    """The paper's link on the gen4-indoor sensor."""
    return Scene(
        encoder=StreamEncoder(bytes(4096), profile="paper", cells=cells),
        camera=camera,
        motion=motion,
        sensor=SensorModel.preset("gen4-indoor"),
        **kw,
    )


def _demo_scene(motion) -> Scene:
    """What the live demo's virtual camera simulates: quarter-size sensor, robust link."""
    return Scene(
        encoder=StreamEncoder(bytes(4096), profile="robust", cells=16),
        camera=default_camera(),
        motion=motion,
        sensor=virtual_sensor(),
    )


CASES = {
    "static, 80 cells, 1.25 m, 0.272 m marker, 1280x720": lambda: _paper_scene(
        80, PAPER, StaticMotion(distance_m=1.25)
    ),
    "static, 80 cells, 1.25 m, 8 px/cell (paper), 1280x720": lambda: _paper_scene(
        80, PAPER, StaticMotion(distance_m=1.25), marker_size_m=_paper_marker(80, 8.0)
    ),
    "hand-held 0.5 px/ms, 16 cells, 1.2 m, 640x480": lambda: _paper_scene(
        16, VGA, HandHeldMotion(distance_m=1.2, flow_px_per_ms=0.5)
    ),
    "hand-held 1 px/ms, 16 cells, 0.6 m, 1280x720": lambda: _paper_scene(
        16, PAPER, HandHeldMotion(distance_m=0.6, flow_px_per_ms=1.0)
    ),
    f"demo: static, 16 cells robust, {DISTANCE_M} m, 320x180 binned": lambda: _demo_scene(
        StaticMotion(distance_m=DISTANCE_M)
    ),
    f"demo: hand-held {HANDHELD_FLOW_PX_PER_MS} px/ms, 16 cells robust, {DISTANCE_M} m, "
    "320x180 binned": lambda: _demo_scene(
        HandHeldMotion(distance_m=DISTANCE_M, flow_px_per_ms=HANDHELD_FLOW_PX_PER_MS)
    ),
    f"demo: hand-held 0.2 px/ms, 16 cells robust, {DISTANCE_M} m, 320x180 binned": lambda: (
        _demo_scene(HandHeldMotion(distance_m=DISTANCE_M, flow_px_per_ms=0.2))
    ),
    f"demo: hand-held 0.5 px/ms, 16 cells robust, {DISTANCE_M} m, 320x180 binned": lambda: (
        _demo_scene(HandHeldMotion(distance_m=DISTANCE_M, flow_px_per_ms=0.5))
    ),
}


def main() -> None:
    rows = [
        "| scene | px/cell | sim s / wall s | sim s / CPU s | events/s (simulated) | "
        "CPU ns per event | ns per event at 0.5x | peak RSS MB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, make in CASES.items():
        scene = make()
        list(simulate(scene, 0.02))  # compile and warm caches
        walls, cpus = [], []
        for _ in range(RUNS):
            start, cpu = time.perf_counter(), time.process_time()
            count = sum(len(c) for c in simulate(scene, DURATION_S))
            walls.append(time.perf_counter() - start)
            cpus.append(time.process_time() - cpu)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        rate = count / DURATION_S
        rows.append(
            f"| {name} | {scene.cell_px():.1f} | {DURATION_S / np.median(walls):.3f} | "
            f"{DURATION_S / np.median(cpus):.3f} | {rate:,.0f} | "
            f"{np.median(cpus) / count * 1e9:.0f} | {1e9 / (0.5 * rate):.0f} | {rss:.0f} |"
        )
        print(rows[-1], flush=True)
    write_section(
        "sim",
        "Virtual event camera speed (one core)",
        "NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.sim",
        f"{DURATION_S} s simulated per scene (set-up included), median of {RUNS} runs after a "
        "warm-up run; 60 Hz "
        "display, 250 lux. The paper rows use the paper link profile and the gen4-indoor "
        "sensor; the demo rows are what the live demo's virtual camera simulates (robust "
        "profile, its coarse-threshold sensor). The machine is shared, so CPU time is given "
        "next to wall time, and its speed drifts between days: compare rows of one run. "
        "'ns per event at 0.5x': the CPU time per event that simulating at half real time on "
        "one core would leave, against the 'CPU ns per event' it takes.\n\n" + "\n".join(rows),
    )


if __name__ == "__main__":
    main()
