"""The paper's static set-up (Sec. V-A): marker filling the view at 1.25 m, 60 Hz, 250 lux.

For each payload size N the marker size is chosen so the image shows the paper's pixels per cell
(30, 18, 13, 10, 8, 7 px for N = 16 .. 96); the bench reports that size and the events per data
frame of the gen4-indoor sensor.

Run: ``NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.calibration``
"""

from __future__ import annotations

from bench.report import write_section
from occ.stream import StreamEncoder
from receiver.camera import CameraModel
from receiver.sim import Scene, SensorModel, StaticMotion, simulate
from receiver.sim.scene import marker_size_for_cell_px

DISTANCE_M = 1.25
PAPER_CELL_PX = {16: 30, 32: 18, 48: 13, 64: 10, 80: 8, 96: 7}
DATA_FRAMES = 4


def main() -> None:
    cam = CameraModel.paper()
    rows = [
        "| N | paper px/cell | marker size (m) | px/cell at the marker centre | "
        "events per data frame |",
        "|---|---|---|---|---|",
    ]
    sizes = []
    for cells, px in PAPER_CELL_PX.items():
        enc = StreamEncoder(bytes(8192), profile="paper", cells=cells)
        size = marker_size_for_cell_px(px, enc.geometry, DISTANCE_M, cam.K[0, 0])
        scene = Scene(
            encoder=enc,
            marker_size_m=size,
            camera=cam,
            motion=StaticMotion(distance_m=DISTANCE_M),
            sensor=SensorModel.preset("gen4-indoor", lux=250.0),
        )
        duration = DATA_FRAMES * 2 / scene.display.refresh_hz
        count = sum(len(c) for c in simulate(scene, duration))
        sizes.append(size)
        rows.append(
            f"| {cells} | {px} | {size:.3f} | {scene.cell_px():.1f} | {count / DATA_FRAMES:,.0f} |"
        )
        print(rows[-1], flush=True)
    write_section(
        "calibration",
        "Simulator calibration against the paper's static set-up",
        "NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.calibration",
        f"Marker at {DISTANCE_M} m, 60 Hz LCD, 250 lux, gen4-indoor sensor, 1280x720 paper lens, "
        f"{DATA_FRAMES} data frames (paper profile: data + blank) per N. The marker size (the "
        "white ring's outer side) is the one that gives the paper's pixels per cell at the "
        f"marker centre: {min(sizes):.2f}-{max(sizes):.2f} m across N, against the 0.272 m "
        "default.\n\n" + "\n".join(rows),
    )


if __name__ == "__main__":
    main()
