"""Receiver on the virtual event camera: BER before FEC, goodput, time to lock, real-time factor.

Run: ``python -m bench.receiver [--quick]``. Static camera, ``robust`` profile, a 346x260 sensor
whose lens makes the marker fill the view from 0.6 m (cells per pixel as in the paper's setup
at small N). The real-time factor is seconds of events per CPU second of the receiver alone
(simulation excluded), one core.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.report import write_section
from occ.stream import StreamEncoder
from receiver.camera import CameraModel
from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.receiver import Receiver
from receiver.pipeline.report import DecodeLog, FrameTruth
from receiver.sim import Display, Scene, SensorModel, StaticMotion, simulate

CAMERA = CameraModel(346, 260, np.array([[300.0, 0, 173], [0, 300.0, 130], [0, 0, 1]]))


def run_case(cells: int, profile: str, duration_s: float) -> dict:
    message = bytes(np.random.default_rng(cells).integers(0, 256, 2000, dtype=np.uint8))
    enc = StreamEncoder(message, profile=profile, cells=cells)
    scene = Scene(
        encoder=enc,
        marker_size_m=0.272,
        display=Display(refresh_hz=60.0),
        camera=CAMERA,
        motion=StaticMotion(distance_m=0.6, tilt_deg=0.0, roll_deg=0.0),
        sensor=SensorModel.preset("gen4-indoor"),
        start_refresh=0,
        seed=0,
    )
    chunks = list(simulate(scene, duration_s=duration_s, chunk_us=10_000))
    rx = Receiver(ReceiverConfig(CAMERA, cells=cells, profile=profile))
    log = DecodeLog(rx, FrameTruth(enc, 60.0, 0))
    cpu0 = time.process_time()
    for chunk in chunks:
        log.add(rx.push(chunk))
    cpu = time.process_time() - cpu0
    report = log.report()
    report["cpu_total_s"] = cpu
    report["realtime_factor"] = report["duration_s"] / cpu
    return report


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="N = 16 only, 1.5 s clips")
    args = parser.parse_args(argv)
    cells = (16,) if args.quick else (16, 32)
    duration = 1.5 if args.quick else 3.0
    rows = []
    for n in cells:
        r = run_case(n, "robust", duration)
        stages = ", ".join(f"{k} {v:.2f}" for k, v in sorted(r["cpu_s"].items()))
        ber = "n/a" if r["ber"] is None else f"{r['ber']:.2e}"
        lock = "n/a" if r["time_to_lock_s"] is None else f"{r['time_to_lock_s']:.2f}"
        rows.append(
            f"| {n} | {ber} | {r['goodput_bps']:.0f} | {lock} | "
            f"{r['frames_seen']}/{r['frames_read']} | {r['realtime_factor']:.2f} | "
            f"{stages} |"
        )
        print(rows[-1])
    body = (
        f"Static camera at 0.6 m, 346x260 sensor (f = 300 px), `gen4-indoor` sensor model, "
        f"60 Hz display, `robust` profile, {duration:g} s clips, one run each.\n\n"
        "| N | BER before FEC | goodput (bit/s) | time to lock (s) | frames seen/read | "
        "real-time factor | CPU s per stage |\n|---|---|---|---|---|---|---|\n" + "\n".join(rows)
    )
    write_section(
        "receiver",
        "Receiver pipeline (virtual camera)",
        "python -m bench.receiver" + (" --quick" if args.quick else ""),
        body,
    )


if __name__ == "__main__":
    main()
