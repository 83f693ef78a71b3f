"""Link-format speed: encoder refreshes/s, stream-decoder frames/s at 1% bit errors, and the
peak memory of encoding a 100 MB message.

Run: ``python -m bench.encoder`` (about a minute on one core).
"""

from __future__ import annotations

import os
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from bench.report import write_section
from eventocc.occ.profiles import PROFILE_NAMES
from eventocc.occ.stream import StreamDecoder, StreamEncoder

SIDES = (16, 48, 96)
REFRESHES = 600
REPEATS = 5
DECODE_FRAMES = 120
BER = 0.01
BIG_MESSAGE = 100 * 2**20


def encoder_rate(profile: str, cells: int, message: bytes) -> float:
    """Median refreshes/s of sequential ``frame(k)`` over ``REPEATS`` runs, from a fresh
    encoder each run (so the block encodings are included)."""
    rates = []
    for _ in range(REPEATS):
        enc = StreamEncoder(message, profile=profile, cells=cells)
        t0 = time.perf_counter()
        for k in range(REFRESHES):
            enc.frame(k)
        rates.append(REFRESHES / (time.perf_counter() - t0))
    return statistics.median(rates)


def decoder_rate(profile: str, cells: int, message: bytes) -> tuple[float, float]:
    """(data frames/s of ``push`` over ``DECODE_FRAMES`` frames at 1% BER, median of
    ``REPEATS`` runs; share of frames (``paper``: of RS codewords) the inner code recovered).
    Whole runs, not single pushes: ``paper`` pushes do work only when a codeword completes."""
    enc = StreamEncoder(message, profile=profile, cells=cells)
    rng = np.random.default_rng(0)
    data = [k for k in range(2 * DECODE_FRAMES) if enc.is_data_frame(k)][:DECODE_FRAMES]
    frames = [enc.payload_bits(k) ^ (rng.random((cells, cells)) < BER) for k in data]
    rates = []
    for _ in range(REPEATS):  # the first run also loads the compiled RS corrector
        dec = StreamDecoder(profile=profile, cells=cells, message_size=len(message))
        if not enc.profile.framed:  # end of the blink preamble: the next frame is frame 0
            dec.push(np.ones((cells, cells), dtype=np.uint8))
        t0 = time.perf_counter()
        for bits in frames:
            dec.push(bits)
        rates.append(len(frames) / (time.perf_counter() - t0))
    if enc.profile.framed:
        recovered = float(np.mean([dec._codec.decode(b) is not None for b in frames]))
    else:
        recovered = float(dec._paper.done.mean())
    return statistics.median(rates), recovered


def _status_mib(field: str) -> float:
    """A ``kB`` field of /proc/self/status (Linux), in MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


def peak_memory(profile: str) -> tuple[float, float, int]:
    """Run in a fresh process: (RSS MiB once the message and encoder exist, extra peak MiB
    while encoding into the second fountain block, refreshes encoded)."""
    enc = StreamEncoder(os.urandom(BIG_MESSAGE), profile=profile, cells=96)
    base = _status_mib("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # restart the peak (VmHWM) from here
    k, fountain = 0, enc._fountain
    while fountain._block is None or fountain._block[0] == 0 or k % 100:
        enc.frame(k)
        k += 1
    return base, _status_mib("VmHWM") - base, k


def main() -> None:
    load = os.getloadavg()[0]  # the machine is shared: say how busy it was
    message = np.random.default_rng(1).integers(0, 256, 200_000, dtype=np.uint8).tobytes()
    rows = [
        "| profile | N | encoder refreshes/s | decoder frames/s at 1% BER | inner code recovered |",
        "|---|---|---|---|---|",
    ]
    for profile in PROFILE_NAMES:
        for cells in SIDES:
            enc = encoder_rate(profile, cells, message)
            dec, ok = decoder_rate(profile, cells, message[:20_000])
            rows.append(f"| {profile} | {cells} | {enc:,.0f} | {dec:,.0f} | {ok:.0%} |")
            print(rows[-1], flush=True)
    fresh = {"mp_context": get_context("spawn"), "max_tasks_per_child": 1}
    with ProcessPoolExecutor(1, **fresh) as pool:  # a new process per profile
        memory = {p: pool.submit(peak_memory, p).result() for p in ("robust", "fast")}
    mem_rows = [
        f"- `{p}`, N = 96: RSS {base:.0f} MiB with the message and encoder built (Python, numpy, "
        f"numba and the 100 MiB message), **+{extra:.1f} MiB** peak while encoding {n} "
        "refreshes, into the second fountain block"
        for p, (base, extra, n) in memory.items()
    ]
    body = "\n".join(
        [
            f"Encoder: sequential `frame(k)`, {REFRESHES} refreshes of a 200 kB message, median "
            f"of {REPEATS} runs from a fresh encoder. Decoder: `StreamDecoder.push` of "
            f"{DECODE_FRAMES} data frames of a 20 kB message with {BER:.0%} independent bit "
            f"errors, median of {REPEATS} runs (`paper`: in order, as its decoder needs). "
            "'Inner code recovered' is the share of frames whose Reed-Solomon codewords and CRC "
            "all passed (`paper`: the share of RS codewords). One core. The display needs 30 "
            "data frames/s (`paper`, `robust`) or 60 (`fast`). At 1% BER about 20 bytes of each "
            "255 are wrong: beyond the paper's codes for N = 16 and 48, which correct 2 and 8.",
            "",
            f"Load average when the run started: {load:.1f}.",
            "",
            *rows,
            "",
            f"Peak memory encoding a {BIG_MESSAGE // 2**20} MiB message (a fresh process each, "
            "peak RSS counted from when the encoder exists; only the fountain block in flight is "
            "expanded):",
            "",
            *mem_rows,
        ]
    )
    print(body)
    write_section(
        "encoder", "Link format: encoder and decoder speed", "python -m bench.encoder", body
    )


if __name__ == "__main__":
    main()
