"""The paper's static set-up (Sec. V-A): marker filling the view at 1.25 m, 60 Hz, 250 lux.

For each payload size N the marker is sized as in the streaming experiment
(``bench.experiments.streaming.cell_px``): the paper's pixels per cell (30, 18, 13, 10, 8, 7 px
for N = 16 .. 96) where our marker's white ring then fits the view, fewer where it would not. The
bench reports that size, the pixels per cell it gives, and the events per data frame of the
gen4-indoor sensor.

Run: ``NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.calibration``
"""

from __future__ import annotations

from bench.experiments.streaming import (
    DISTANCE_M,
    FIT_SHARE,
    PAPER_CELL_PX,
    paper_cell_px,
    static_scene,
)
from bench.report import write_section
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.sim import SensorModel, simulate

DATA_FRAMES = 4


def main() -> None:
    cam = CameraModel.paper()
    rows = [
        "| N | paper px/cell | marker size (m) | px/cell at the marker centre | "
        "events per data frame |",
        "|---|---|---|---|---|",
    ]
    for cells in PAPER_CELL_PX:
        enc = StreamEncoder(bytes(8192), profile="paper", cells=cells)
        scene = static_scene(enc, cam, sensor=SensorModel.preset("gen4-indoor", lux=250.0))
        duration = DATA_FRAMES * 2 / scene.display.refresh_hz
        count = sum(len(c) for c in simulate(scene, duration))
        rows.append(
            f"| {cells} | {paper_cell_px(cells, cam):g} | {scene.marker_size_m:.3f} | "
            f"{scene.cell_px():.1f} | {count / DATA_FRAMES:,.0f} |"
        )
        print(rows[-1], flush=True)
    write_section(
        "calibration",
        "Simulator calibration against the paper's static set-up",
        "NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.calibration",
        f"Marker at {DISTANCE_M} m, 60 Hz LCD, 250 lux, gen4-indoor sensor, 1280x720 paper lens, "
        f"{DATA_FRAMES} data frames (paper profile: data + blank) per N. The marker size (the "
        "white ring's outer side) gives the paper's pixels per cell at the marker centre where "
        f"the white ring then spans at most {FIT_SHARE:.0%} of the 720 px view height, and "
        "smaller cells where it would not: our exterior rings are ceil(N / 16) cells wide "
        "against the paper's one cell, so our marker at the paper's pixels per cell would "
        "overflow the view from N = 32 on (N = 16 comes within 2% of the paper's 30 px). The "
        "white ring then spans the same share of the view for every N, so the marker sizes "
        "agree (against the 0.272 m default).\n\n" + "\n".join(rows),
    )


if __name__ == "__main__":
    main()
