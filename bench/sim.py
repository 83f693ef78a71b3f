"""Simulator speed at 1280x720 on one core: simulated seconds per wall second, events/s, memory.

Run: ``NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.sim``
"""

from __future__ import annotations

import resource
import time

from bench.report import write_section
from occ.stream import StreamEncoder
from receiver.sim import HandHeldMotion, Scene, SensorModel, StaticMotion, simulate

DURATION_S = 0.5
CASES = {
    "static, 80 cells, 1.25 m": {"cells": 80, "motion": StaticMotion(distance_m=1.25)},
    "hand-held 1 px/ms, 16 cells, 0.6 m": {
        "cells": 16, "motion": HandHeldMotion(distance_m=0.6, flow_px_per_ms=1.0)},
}


def main() -> None:
    rows = ["| scene | sim s / wall s | events/s (simulated) | peak RSS MB |", "|---|---|---|---|"]
    for name, case in CASES.items():
        scene = Scene(encoder=StreamEncoder(bytes(4096), profile="paper", cells=case["cells"]),
                      motion=case["motion"], sensor=SensorModel.preset("gen4-indoor"))
        list(simulate(scene, 0.02))  # compile and warm caches
        start = time.perf_counter()
        count = sum(len(c) for c in simulate(scene, DURATION_S))
        wall = time.perf_counter() - start
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        rows.append(f"| {name} | {DURATION_S / wall:.3f} | {count / DURATION_S:,.0f} | "
                    f"{rss:.0f} |")
        print(rows[-1], flush=True)
    write_section("sim", "Virtual event camera speed (1280x720, gen4-indoor, one core)",
                  "NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.sim",
                  f"{DURATION_S} s simulated per scene, after a warm-up.\n\n" + "\n".join(rows))


if __name__ == "__main__":
    main()
