"""BER before FEC and verified goodput against pixels per cell, ``evk4`` against ``ideal``.

The paper's still set-up (1.25 m, the marker facing the camera, 250 lux, 1280x720) with the
marker sized for ``P`` pixels per cell and the largest payload side N whose white ring fits
``FIT_SHARE`` of the view. Each clip's accepted frames are decoded again offline three ways, to
show what the reader's confidences are worth: ``hard`` (no confidences: errors only),
``threshold`` (then, in a codeword the bits alone do not decode, the bytes with a cell below
``erasure_below`` erased) and ``soft`` (the receiver's own: then retries erasing the least
confident bytes).

Run: ``NUMBA_NUM_THREADS=1 nice .venv/bin/python -m bench.realistic --jobs 1``
(``--px 7 13 --profiles robust --rates 60`` for a subset).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from bench.experiments.eventcam import clip_message, raw_bps
from bench.experiments.streaming import DISTANCE_M, PAPER_PEAK_BPS
from bench.report import write_section
from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.stream import StreamDecoder, StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.receiver import FrameOutput, Receiver
from eventocc.receiver.pipeline.report import FrameTruth
from eventocc.receiver.sim import Display, Optics, Scene, SensorModel, StaticMotion, simulate
from eventocc.receiver.sim.scene import marker_size_for_cell_px

DOCS = Path(__file__).resolve().parent.parent / "docs"
PX_PER_CELL = (4, 5, 6, 7, 8, 10, 13, 18, 24, 30)
PRESETS = ("evk4", "evk4-link", "ideal")
PROFILES = ("paper", "robust", "fast")
RATES = (60.0, 240.0)
FIT_SHARE = 0.92
"""The white ring spans at most this share of the sensor height (at 30 px per cell N = 16's
white ring is 22 cells, 660 px)."""
CLIP_S = {60.0: 0.3, 240.0: 0.15}
"""Clip length per refresh rate: the same number of refreshes (the simulator's cost)."""
MODES = ("hard", "threshold", "soft")
PAPER_BER = {7.0: 0.01, 13.0: 0.0}
"""The paper's Sec. V-A: BER passes 1% beyond 96x96 (7 px per cell), zero up to 13 px."""


def cells_for(px: float, height: int = 720) -> int:
    """Largest payload side N (a multiple of 8, at least 16) whose white ring fits."""
    fits = [
        n for n in range(16, 129, 8) if MarkerGeometry(n).tracked_side * px <= FIT_SHARE * height
    ]
    return max(fits, default=16)


@dataclass(frozen=True)
class Point:
    preset: str
    profile: str
    refresh_hz: float
    px_per_cell: float
    cells: int
    seed: int
    clip_s: float
    ber: float | None
    """Bit errors before FEC over the accepted data frames (None: none accepted)."""
    frames: int
    goodput_bps: dict[str, float]
    """Per decoding mode, verified goodput: ``robust``/``fast``, the payload bits of the frames
    whose Reed-Solomon code and CRC passed, per second from the first frame read to the last
    (what a long message gets); ``paper`` (no check), the message's bits over the time from
    the first frame read to the frame that completed it, 0 if it did not complete."""
    wrong_messages: dict[str, int]
    frames_passed: dict[str, int]
    """Per decoding mode: accepted frames whose Reed-Solomon code and CRC passed (framed
    profiles; ``paper`` frames carry no check)."""
    raw_bps: float
    events_per_s: float
    """Events the camera delivered, per second of clip."""
    made_per_s: float
    """Events the pixels made, before the readout's limits."""
    dropped_share: float
    delayed_share: float
    wall_s: float

    def to_dict(self) -> dict:
        return asdict(self)


NO_READOUT = " without readout limits"
"""Appended to a preset's name: the same camera with every readout stage off, which shows what
the sensor's readout, its rate controller and the link cost."""


def sensor_for(preset: str) -> SensorModel:
    if preset.endswith(NO_READOUT):
        base = SensorModel.preset(preset.removesuffix(NO_READOUT))
        return replace(base, readout_hz=None, erc_hz=None, link_hz=None)
    return SensorModel.preset(preset)


def scene_for(preset: str, profile: str, refresh_hz: float, px: float, seed: int) -> Scene:
    cam = CameraModel.paper()
    cells = cells_for(px, cam.height)
    clip = CLIP_S[refresh_hz]
    encoder = StreamEncoder(
        clip_message(profile, cells, refresh_hz, clip, seed), profile=profile, cells=cells
    )
    return Scene(
        encoder=encoder,
        marker_size_m=marker_size_for_cell_px(px, encoder.geometry, DISTANCE_M, cam.K[0, 0]),
        camera=cam,
        motion=StaticMotion(DISTANCE_M),
        display=Display(refresh_hz=refresh_hz),
        sensor=sensor_for(preset),
        optics=Optics.preset(preset),
        seed=seed,
    )


def run_point(preset: str, profile: str, refresh_hz: float, px: float, seed: int = 0) -> Point:
    t0 = time.perf_counter()
    scene = scene_for(preset, profile, refresh_hz, px, seed)
    enc, clip = scene.encoder, CLIP_S[refresh_hz]
    config = ReceiverConfig(
        scene.camera,
        cells=enc.geometry.cells,
        profile=enc.profile.name,
        refresh_hz=refresh_hz,
        marker_size_m=scene.marker_size_m,
    )
    receiver = Receiver(config, message_size=len(enc.message))
    truth = FrameTruth(enc, refresh_hz, scene.start_refresh)
    recording = simulate(scene, clip)
    reads, first_read, delivered = [], None, 0
    for chunk in recording:
        delivered += len(chunk)
        outputs = receiver.push(chunk)
        reads += _accepted(outputs)
        first_read = first_read or _first_read(outputs)
    reads += _accepted(receiver.finish())
    errors = [truth.errors(r.bits, r.t_us) for r in reads]
    scored = [e for e in errors if e is not None]
    n2 = enc.geometry.cells**2
    frame_s = enc.profile.data_every / refresh_hz
    goodput, wrong, passed = {}, {}, {}
    for mode in MODES:
        goodput[mode], wrong[mode], passed[mode] = _decode(enc, reads, mode, first_read, frame_s)
    readout = recording.readout
    made = max(recording.made, 1)
    return Point(
        preset,
        profile,
        refresh_hz,
        px,
        enc.geometry.cells,
        seed,
        clip,
        sum(scored) / (len(scored) * n2) if scored else None,
        len(scored),
        goodput,
        wrong,
        passed,
        raw_bps(enc.geometry.cells, refresh_hz, enc.profile.data_every),
        delivered / clip,
        recording.made / clip,
        (readout.dropped_erc + readout.dropped_link) / made,
        readout.delayed / made,
        time.perf_counter() - t0,
    )


def _accepted(outputs: list) -> list:
    return [o.read for o in outputs if isinstance(o, FrameOutput) and o.accepted]


def _first_read(outputs: list) -> int | None:
    reads = [o.read.t_us for o in outputs if isinstance(o, FrameOutput)]
    return reads[0] if reads else None


def _decode(
    enc: StreamEncoder, reads: list, mode: str, first_read: int | None, frame_s: float
) -> tuple[float, int, int]:
    """(verified goodput in bit/s (``Point.goodput_bps``), wrong messages, frames whose
    Reed-Solomon code and CRC passed) of the reads decoded in ``mode``."""
    profile = enc.profile
    if mode != "soft":
        profile = replace(profile, erasure_rounds=0)
    if mode == "hard":
        profile = replace(profile, erasure_below=0.0)
    dec = StreamDecoder(
        profile=profile, cells=enc.geometry.cells, message_size=len(enc.message), name=enc.name
    )
    goodput, wrong, passed = 0.0, 0, 0
    for read in reads:
        before = dec.verified_bits
        for msg in dec.push(read.bits, None if mode == "hard" else read.confidence):
            if msg.data != enc.message:
                wrong += 1
            elif first_read is not None and not goodput:
                span = (read.t_us - first_read) / 1e6 + frame_s
                goodput = 8 * len(enc.message) / span
        passed += dec.verified_bits > before
    if enc.profile.framed and reads and first_read is not None:
        # What a long message gets: the verified symbols' bits per second of frames read.
        goodput = dec.verified_bits / ((reads[-1].t_us - first_read) / 1e6 + frame_s)
    return goodput, wrong, passed


# --- report ------------------------------------------------------------------------------------


def _kbps(x: float) -> str:
    return f"{x / 1e3:,.0f}" if x >= 1e3 else f"{x / 1e3:.2f}"


def table(points: list[Point]) -> str:
    rows = [
        "| camera | profile | Hz | px/cell | N | BER before FEC | frames passed hard / "
        "threshold / soft, of read | goodput hard / threshold / soft, kbit/s | raw kbit/s | "
        "events/s made -> delivered | dropped |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in sorted(points, key=lambda p: (p.preset, p.profile, p.refresh_hz, p.px_per_cell)):
        ber = "no frame" if p.ber is None else f"{100 * p.ber:.3f}%"
        good = " / ".join(_kbps(p.goodput_bps[m]) for m in MODES)
        if any(p.wrong_messages.values()):
            good += f" ({max(p.wrong_messages.values())} wrong)"
        passed = "-"
        if p.profile != "paper":
            passed = " / ".join(str(p.frames_passed[m]) for m in MODES) + f" of {p.frames}"
        rows.append(
            f"| {p.preset} | {p.profile} | {p.refresh_hz:g} | {p.px_per_cell:g} | {p.cells} | "
            f"{ber} | {passed} | {good} | {_kbps(p.raw_bps)} | {p.made_per_s / 1e6:.0f} M -> "
            f"{p.events_per_s / 1e6:.0f} M | {100 * p.dropped_share:.1f}% |"
        )
    return "\n".join(rows)


def best(points: list[Point], preset: str, refresh_hz: float) -> Point | None:
    ok = [
        p
        for p in points
        if p.preset == preset and p.refresh_hz == refresh_hz and not p.wrong_messages["soft"]
    ]
    return max(ok, key=lambda p: p.goodput_bps["soft"], default=None)


def plot(points: list[Point], path: Path) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5), sharex=True)
    colours = {"paper": "tab:green", "robust": "tab:blue", "fast": "tab:red"}
    for col, rate in enumerate(RATES):
        ax_ber, ax_rate = axes[0, col], axes[1, col]
        for preset, style in (("evk4", "o-"), ("evk4-link", "^--"), ("ideal", "s:")):
            for profile in PROFILES:
                ps = sorted(
                    (
                        p
                        for p in points
                        if (p.preset, p.profile, p.refresh_hz) == (preset, profile, rate)
                    ),
                    key=lambda p: p.px_per_cell,
                )
                if not ps:
                    continue
                x = [p.px_per_cell for p in ps]
                label = f"{profile}, {preset}"
                ber = [np.nan if p.ber is None else max(100 * p.ber, 1e-4) for p in ps]
                ax_ber.plot(x, ber, style, color=colours[profile], label=label, ms=4)
                rate_k = [max(p.goodput_bps["soft"] / 1e3, 0.5) for p in ps]
                ax_rate.plot(x, rate_k, style, color=colours[profile], label=label, ms=4)
        ax_ber.plot([7, 13], [1.0, 1e-4], "k*", ms=12, label="paper (Sec. V-A): ~1% at 7, 0 at 13")
        ax_ber.set_yscale("log")
        ax_ber.set_ylim(5e-5, 60)
        ax_ber.set_ylabel("BER before FEC [%] (0 drawn at 1e-4)")
        ax_ber.set_title(f"{rate:g} Hz display, still camera at 1.25 m")
        if rate == 60.0:
            ax_rate.plot([8], [PAPER_PEAK_BPS / 1e3], "k*", ms=12, label="paper, 114 kbit/s")
        ax_rate.set_ylabel("verified goodput [kbit/s] (0 drawn at 0.5)")
        ax_rate.set_yscale("log")
        ax_rate.set_ylim(bottom=0.4)
        ax_rate.set_xlabel("pixels per cell")
        ax_rate.set_xscale("log")
        ax_rate.set_xticks(PX_PER_CELL, [str(p) for p in PX_PER_CELL])
        ax_rate.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        for ax in (ax_ber, ax_rate):
            ax.grid(alpha=0.3)
        ax_rate.legend(fontsize=7)
        ax_ber.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--px", type=float, nargs="+", default=PX_PER_CELL)
    parser.add_argument(
        "--presets",
        nargs="+",
        default=PRESETS,
        help=f"sensor presets; a name ending in '{NO_READOUT}' turns the readout limits off",
    )
    parser.add_argument("--profiles", nargs="+", default=PROFILES)
    parser.add_argument("--rates", type=float, nargs="+", default=RATES)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--out", type=Path, default=DOCS)
    parser.add_argument("--no-write", action="store_true", help="print only; leave docs alone")
    parser.add_argument(
        "--report-only", action="store_true", help="redraw the figure and section from the JSON"
    )
    args = parser.parse_args(argv)
    results = args.out / "results" / "realistic.json"
    if args.report_only:
        _write(args.out, [Point(**d) for d in json.loads(results.read_text())], _command(args))
        return
    calls = [
        (preset, profile, rate, px)
        for preset in args.presets
        for rate in args.rates
        for profile in args.profiles
        for px in args.px
    ]
    points: list[Point] = []
    if results.exists() and not args.no_write:  # keep the points a subset run does not redo
        kept = [Point(**d) for d in json.loads(results.read_text())]
        keys = set(calls)
        points = [p for p in kept if (p.preset, p.profile, p.refresh_hz, p.px_per_cell) not in keys]
    if args.jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs) as pool:
            new = list(pool.map(run_point, *zip(*calls, strict=True)))
    else:
        new = []
        for call in calls:
            new.append(run_point(*call))
            p = new[-1]
            print(table([p]).splitlines()[-1], f"{p.wall_s:.0f} s", flush=True)
    points += new
    if args.no_write:
        return
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(json.dumps([p.to_dict() for p in points], indent=1))
    _write(args.out, points, _command(args))


def _command(args: argparse.Namespace) -> str:
    """The command line of this run, its options other than the defaults and ``--out``."""
    words = ["NUMBA_NUM_THREADS=1 nice .venv/bin/python -m bench.realistic"]
    for name, default in (
        ("px", PX_PER_CELL),
        ("presets", PRESETS),
        ("profiles", PROFILES),
        ("rates", RATES),
    ):
        value = getattr(args, name)
        if list(value) != list(default):
            words.append(
                f"--{name} " + " ".join(f"{v:g}" if isinstance(v, float) else v for v in value)
            )
    words.append(f"--jobs {args.jobs}")
    return " ".join(words)


def _write(out: Path, points: list[Point], command: str) -> None:
    plot(points, out / "realistic.png")
    write_section(
        "realistic",
        "A camera that does not flatter us: BER and goodput against pixels per cell",
        command,
        report(points),
        out / "BENCHMARKS.md",
    )


def report(points: list[Point]) -> str:
    lines = [
        "The paper's still set-up at 1.25 m (1280x720, 250 lux, an LCD at 60 or 240 Hz) with "
        "the marker sized for each pixels-per-cell value and the largest N (a multiple of 8) "
        f"whose white ring fits {FIT_SHARE:.0%} of the view; one clip per point ("
        + ", ".join(f"{s:g} s at {r:g} Hz" for r, s in CLIP_S.items())
        + ", seed 0), a message of a fifth of the clip's raw capacity. `evk4` is the "
        "Prophesee EVK4 preset (sources beside each parameter in `receiver/sim/sensor.py` "
        "and `optics.py`); `ideal` (ESIM's clean sensor, our default lens) is the upper bound. "
        "Verified goodput: `robust`/`fast`, the payload bits of the frames whose Reed-Solomon "
        "code and CRC passed per second from the first frame read to the last (what a long "
        "message gets, as `bench.receiver` counts it); `paper` (no check), the message's bits "
        "over the time from the first frame read to the frame completing it. Each clip's "
        "reads are decoded three ways (hard: errors only; threshold: then, in a codeword the "
        "bits alone do not decode, the outright erasures; soft: then retries erasing the least "
        "confident bytes, the receiver's own). Events/s: what the pixels made, and what the "
        "camera delivered after the sensor's readout, its rate controller and the USB link.",
        "",
        "![BER and goodput against pixels per cell](realistic.png)",
        "",
        "Where our reader is better than the paper's on the same camera, the paper's receiver "
        "(as its published code reads) approximates the locator from the tracked ring by an "
        "affine scaling that ignores perspective, keeps a fixed-period frame clock it never "
        "re-times, binarises a polarity surface normalised to the newest event anywhere on "
        "the sensor at fixed levels, calls a cell 1 when 60% of its bilinearly warped pixels "
        "are on, and ORs three scans, which turns noise into 0->1 errors. Ours maps every "
        "burst through the full homography, re-fits the clock and the scan-out slope on every "
        "frame, reads each cell as the share of its inner pixels (a fifth of each side left "
        "out) that fired inside its row's gate, and fits the threshold to each frame's own "
        "two clusters of densities.",
        "",
        "Measured, not only argued: `python -m bench.authors_reader` (at 6255986) reads this "
        "section's `evk4` `paper` clips the way the authors' code does, given the locator's true "
        "corners and the display's exact clock, so that only its reading of the cells differs "
        "from ours. It gets 13.5% of the bits wrong at 7 px per cell, 2.7% at 10 and 0.36% at 13 "
        "(on `ideal`: 0.27%, 0 and 0), more than the paper's camera gave it (~1% at 7, errors "
        "from 10 on, none at 13): `evk4` is, if anything, harder on that reader than the paper's "
        "set-up was. Every one of its errors is a black cell read 1, and the black cells it "
        "reads 1 are those beside white ones: at 7 px, 1,053 of the 1,054 with four white "
        "neighbours, 3,320 of 4,198 with three, 518 of 6,769 with two, 22 of 4,907 with one, "
        "none of 1,523 with none. The lens's point-spread tails carry a few per cent of a lit "
        "neighbour's light into a black cell, a large step in the log of so little light: the "
        "black cell's pixels near its lit edges fire ON as the neighbour switches, and a surface "
        "that keeps every ON event of the last 10 ms, with a cell called 1 when 60% of its whole "
        "area fired, counts them. The same reader counting only each cell's inner part (a fifth "
        "of each side left out, as ours does) gets 1.04% wrong at 7 px and none at 10 or 13. "
        "Ours also counts only the bursts that begin within the row's gate at the switch and "
        "places its threshold between the frame's own two clusters of cells: on the same clips "
        "its `paper` reads are bit-exact at 7 px (9 frames, 46,656 bits). `fast`'s 0.012% at 7 "
        "px (10 of 82,944 bits; offline at 4ac1dc2) is the last of the same spill: each wrong "
        "bit a black cell left black for 2-5 refreshes beside 1-4 white neighbours, read as "
        "toggled with a confidence of 0.01-0.28, and all of them corrected (16 of 16 frames "
        "passed). At 7 px per cell our `fast` thus reads about 80 times fewer bits wrong than "
        "the paper's receiver did on its camera, and over a thousand times fewer than the "
        "authors' reader reads on this camera's `paper` frames: the reader, not the camera, "
        "makes the difference.",
        "",
    ]
    for px, paper in PAPER_BER.items():
        got = [
            p
            for p in points
            if p.preset == "evk4"
            and p.refresh_hz == 60.0
            and p.px_per_cell == px
            and p.ber is not None
        ]
        if got:
            each = ", ".join(f"{p.profile} {100 * p.ber:.3f}%" for p in got)
            lines.append(
                f"- against the paper, evk4 at 60 Hz, {px:g} px per cell: BER before FEC {each} "
                f"(the paper: {'~1%' if paper else '0'})"
            )
    present = sorted({p.preset for p in points}, key=lambda n: (n not in PRESETS, n))
    for rate in RATES:
        for preset in present:
            b = best(points, preset, rate)
            if b is not None:
                lines.append(
                    f"- best verified goodput, {preset} at {rate:g} Hz: "
                    f"{_kbps(b.goodput_bps['soft'])} kbit/s ({b.profile}, N = {b.cells}, "
                    f"{b.px_per_cell:g} px per cell, {b.events_per_s / 1e6:.0f} M events/s "
                    "delivered)"
                )
    return "\n".join([*lines, "", table(points)])


if __name__ == "__main__":
    main()
