"""Receiver on the virtual event camera: BER before FEC, goodput, time to lock and to the first
verified message, real-time factor with its per-stage breakdown.

Run: ``python -m bench.receiver [--quick]``. Static camera, the marker filling the view,
``gen4-indoor`` sensor at 250 lux. ``--quick`` uses a 346x260 sensor (f = 300 px, marker at
0.6 m); the full run adds the paper's 1280x720 camera at N = 16..96 and refresh rates up to
240 Hz. The framed profiles join the stream mid-way (refresh 1000), so the first verified
message includes the wait for the fountain symbols it needs; ``paper`` has no header and starts
with the stream.

Goodput is the verified message's bits over the time from the first event to the frame that
completed it (frames buffered before the lock count: the receiver reads them after locking; the
message is sized to a few tenths of a second of symbols). The real-time factor is seconds of
events per CPU second of the receiver alone (simulation excluded, compiled kernels warmed up),
one core.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from bench.report import write_section
from occ.stream import StreamEncoder
from receiver.camera import CameraModel
from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.receiver import Receiver
from receiver.pipeline.report import DecodeLog, FrameTruth
from receiver.sim import Display, Scene, SensorModel, StaticMotion, simulate

SMALL = CameraModel(346, 260, np.array([[300.0, 0, 173], [0, 300.0, 130], [0, 0, 1]]))
JOIN_AT = 1000
"""Display refresh shown when the recording starts: the receiver joins mid-stream."""


@dataclass(frozen=True)
class Case:
    profile: str
    cells: int
    refresh_hz: float
    camera: CameraModel
    distance_m: float
    duration_s: float

    @property
    def label(self) -> str:
        sensor = f"{self.camera.width}x{self.camera.height}"
        return f"{self.profile} N={self.cells} {self.refresh_hz:g} Hz {sensor}"

    @property
    def join_at(self) -> int:
        """``paper`` frames carry no header: its receiver must see the stream from the start."""
        return 0 if self.profile == "paper" else JOIN_AT

    def scene(self) -> Scene:
        data_hz = self.refresh_hz / (1 if self.profile == "fast" else 2)
        size = max(64, int(self.cells**2 / 8 * data_hz * 0.1))  # ~0.2 s of symbols at rate 1/2
        message = bytes(np.random.default_rng(self.cells).integers(0, 256, size, np.uint8))
        # Faster displays switch faster: an LCD's response shrinks with its refresh period.
        tau_ms = min(2.5, 0.12 * 1e3 / self.refresh_hz)
        return Scene(
            encoder=StreamEncoder(message, profile=self.profile, cells=self.cells),
            marker_size_m=0.272,
            display=Display(refresh_hz=self.refresh_hz, rise_ms=tau_ms, fall_ms=0.6 * tau_ms),
            camera=self.camera,
            motion=StaticMotion(distance_m=self.distance_m),
            sensor=SensorModel.preset("gen4-indoor", lux=250.0),
            start_refresh=self.join_at,
            seed=0,
        )


def run_case(case: Case) -> dict:
    scene = case.scene()
    chunks = list(simulate(scene, duration_s=case.duration_s, chunk_us=10_000))
    config = ReceiverConfig(
        case.camera, cells=case.cells, profile=case.profile, refresh_hz=case.refresh_hz
    )
    rx = Receiver(config, message_size=len(scene.encoder.message))
    log = DecodeLog(rx, FrameTruth(scene.encoder, case.refresh_hz, case.join_at))
    cpu0 = time.process_time()
    for chunk in chunks:
        log.add(rx.push(chunk))
    cpu = time.process_time() - cpu0
    report = log.report()
    report["cpu_total_s"] = cpu
    report["realtime_factor"] = report["duration_s"] / cpu
    report["message_bits"] = 8 * len(scene.encoder.message)
    return report


def _row(case: Case, r: dict) -> str:
    ber = "n/a" if r["ber"] is None else f"{r['ber']:.2e}"
    lock = r["time_to_lock_s"]
    verified = [m for m in r["messages"] if m["verified"]]
    if verified:
        first = verified[0]["t_s"]
        goodput = f"{r['message_bits'] / first / 1e3:.1f}"
        first_msg = f"{first:.3f}"
    else:
        goodput, first_msg = "none", "none"
    data_hz = case.refresh_hz / (1 if case.profile == "fast" else 2)
    stages = ", ".join(f"{k} {v:.2f}" for k, v in sorted(r["cpu_s"].items()))
    return (
        f"| {case.label} | {case.cells**2 * data_hz / 1e3:.1f} | {ber} | {goodput} | "
        f"{'n/a' if lock is None else f'{lock:.3f}'} | {first_msg} | "
        f"{r['events'] / r['duration_s'] / 1e6:.1f} | {r['realtime_factor']:.2f} | {stages} |"
    )


def cases(quick: bool) -> list[Case]:
    small = [
        Case("robust", 16, 60.0, SMALL, 0.6, 1.5),
        Case("fast", 16, 60.0, SMALL, 0.6, 1.5),
        Case("paper", 16, 60.0, SMALL, 0.6, 1.5),
    ]
    if quick:
        return small
    paper_cam = CameraModel.paper()
    return (
        small
        + [Case("robust", 32, hz, SMALL, 0.35, 1.5) for hz in (120.0, 240.0)]
        + [Case("fast", 32, hz, SMALL, 0.35, 1.5) for hz in (120.0, 240.0)]
        + [Case("paper", n, 60.0, paper_cam, 0.48, 1.0) for n in (16, 48, 80, 96)]
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sensor, N = 16 only")
    args = parser.parse_args(argv)
    run_case(Case("robust", 16, 60.0, SMALL, 0.6, 0.7))  # load the compiled kernels first
    rows = []
    for case in cases(args.quick):
        rows.append(_row(case, run_case(case)))
        print(rows[-1], flush=True)
    body = (
        "Static camera, marker filling the view, `gen4-indoor` at 250 lux; `robust` and `fast` "
        f"join the stream at refresh {JOIN_AT}, `paper` at its start; one run per case. "
        "Raw rate = N² bits per data frame; goodput = "
        "verified message bits over the time from the first event to the frame completing it; "
        "times are seconds from the first event.\n\n"
        "| case | raw kbit/s | BER before FEC | goodput kbit/s | lock (s) | first message (s) | "
        "Mev/s | real-time factor | CPU s per stage |\n"
        "|---|---|---|---|---|---|---|---|---|\n" + "\n".join(rows)
    )
    write_section(
        "receiver",
        "Receiver pipeline (virtual camera)",
        "python -m bench.receiver" + (" --quick" if args.quick else ""),
        body,
    )


if __name__ == "__main__":
    main()
