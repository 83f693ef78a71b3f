"""Reader throughput per format: million events per second on one core.

Writes a few million synthetic events to each writable format, then times ``read_events``
to the end (median of 3 runs, after one warm-up that also compiles the numba decoders).
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.report import write_section
from eventocc.receiver.events import make_events
from eventocc.receiver.io import WRITE_FORMATS, read_events, write_events

N_EVENTS = 4_000_000
N_TEXT = 400_000  # text is for interchange, not speed: fewer events keep the run short
WIDTH, HEIGHT = 1280, 720
RUNS = 3


def synthetic_events(n: int, seed: int = 0) -> np.ndarray:
    """Events at ~20 Mev/s with sensor-like bursts along rows."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, n // 20, n))
    return make_events(
        t, rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n), rng.integers(0, 2, n)
    )


def read_seconds(path: Path, fmt: str) -> float:
    start = time.perf_counter()
    for _ in read_events(path, format="raw" if fmt.startswith("evt") else fmt):
        pass
    return time.perf_counter() - start


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in WRITE_FORMATS:
            n = N_TEXT if fmt == "text" else N_EVENTS
            path = Path(tmp) / f"events.{fmt}"
            write_events(path, synthetic_events(n), format=fmt, width=WIDTH, height=HEIGHT)
            read_seconds(path, fmt)
            median = statistics.median(read_seconds(path, fmt) for _ in range(RUNS))
            rows.append((fmt, n, path.stat().st_size / n, n / median / 1e6))
            print(f"{fmt:6s} {n / median / 1e6:7.1f} Mev/s")
    table = "\n".join(f"| {fmt} | {n:,} | {size:.2f} | {rate:.1f} |" for fmt, n, size, rate in rows)
    write_section(
        "readers",
        "Event file readers",
        "python -m bench.readers",
        "Median of 3 full reads per format, one core (NUMBA_NUM_THREADS=1), files in the page "
        "cache. Target: EVT 3.0 >= 20 Mev/s.\n\n"
        "| format | events | bytes/event | read Mev/s |\n|---|---|---|---|\n" + table,
    )


if __name__ == "__main__":
    main()
