"""Transmit service speed: how fast ``GET /api/messages/{id}/frames`` serves frame batches.

For each profile and marker size, a 64 KiB message is uploaded, then sequential batches of 60
frames (one second at 60 Hz) are fetched in-process (ASGI, no network). Reported: the first
batch (encoder built, cold), the median of the following batches (encoder cached), and how many
60 Hz displays one server core could feed.

Run: ``python -m bench.server_frames`` (well under a minute on one core).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from fastapi.testclient import TestClient

from bench.report import write_section
from eventocc.occ.profiles import PROFILE_NAMES
from eventocc.server.app import create_app
from eventocc.server.settings import Settings

CELLS = (16, 64)
BATCH = 60
BATCHES = 15
MESSAGE = os.urandom(64 * 1024)


def timed_get(client: TestClient, url: str) -> float:
    t0 = time.perf_counter()
    response = client.get(url)
    elapsed = time.perf_counter() - t0
    response.raise_for_status()
    return elapsed


def measure(client: TestClient, profile: str, cells: int) -> tuple[float, float, int]:
    """(cold batch s, median warm batch s, bytes per batch)."""
    created = client.post(
        f"/api/messages?profile={profile}&cells={cells}",
        content=MESSAGE,
        headers={"Content-Type": "application/octet-stream"},
    )
    created.raise_for_status()
    url = f"/api/messages/{created.json()['id']}/frames?count={BATCH}&start="
    cold = timed_get(client, f"{url}0")
    warm = [timed_get(client, f"{url}{i * BATCH}") for i in range(1, BATCHES + 1)]
    size = len(client.get(f"{url}0").content)
    return cold, statistics.median(warm), size


def main() -> None:
    rows = [
        "| profile | cells | cold batch (ms) | warm batch (ms) | frames/s | 60 Hz displays "
        "| KiB/batch |",
        "|---|---|---|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory() as data_dir:
        client = TestClient(create_app(Settings(data_dir=Path(data_dir))))
        for profile in PROFILE_NAMES:
            for cells in CELLS:
                cold, warm, size = measure(client, profile, cells)
                rate = BATCH / warm
                rows.append(
                    f"| {profile} | {cells} | {cold * 1e3:.1f} | {warm * 1e3:.1f} | "
                    f"{rate:.0f} | {rate / 60:.0f}x | {size / 1024:.1f} |"
                )
                print(rows[-1], flush=True)
    body = (
        f"Batches of {BATCH} frames of a 64 KiB message, fetched in order in-process (ASGI, "
        f"no network); warm = median of {BATCHES} batches with the encoder cached. "
        '"60 Hz displays" is how many transmitter pages one core keeps fed.\n\n' + "\n".join(rows)
    )
    write_section(
        "server_frames", "Transmit service: frame batches", "python -m bench.server_frames", body
    )


if __name__ == "__main__":
    main()
