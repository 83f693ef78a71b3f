"""Mutated and truncated files: the readers raise EventFileError or read events, nothing else."""

from __future__ import annotations

import numpy as np
import pytest

from eventocc.receiver.events import make_events
from eventocc.receiver.io import EventFileError, read_events, write_events

MUTANTS_PER_FORMAT = 500
rng = np.random.default_rng(7)
N = 120
EVENTS = make_events(
    np.sort(rng.integers(0, 50_000, N)),
    rng.integers(0, 32, N),
    rng.integers(0, 24, N),
    rng.integers(0, 2, N),
)


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    for _ in range(rng.integers(1, 4)):
        kind = rng.integers(4)
        at = int(rng.integers(len(buf))) if buf else 0
        if kind == 0 and buf:
            buf[at] ^= 1 << int(rng.integers(8))
        elif kind == 1:
            buf[at:at] = rng.integers(0, 256, int(rng.integers(1, 4)), dtype=np.uint8).tobytes()
        elif kind == 2:
            del buf[at : at + int(rng.integers(1, 4))]
        else:
            del buf[at:]
    return bytes(buf)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("seed", "fmt", "name"),
    [
        (1, "evt3", "f.raw"),
        (2, "evt2", "f.raw"),
        (3, "dat", "f.dat"),
        (4, "text", "f.txt"),
        (5, "npz", "f.npz"),
    ],
)
def test_mutants_never_crash_or_hang(tmp_path, seed, fmt, name):
    original = tmp_path / name
    write_events(original, EVENTS, format=fmt, width=32, height=24)
    data = original.read_bytes()
    mutant = tmp_path / f"m_{name}"
    rng = np.random.default_rng(seed)
    outcomes = {"read": 0, "error": 0}
    for _ in range(MUTANTS_PER_FORMAT):
        mutant.write_bytes(mutate(data, rng))
        try:
            for chunk in read_events(mutant):
                assert chunk.dtype.names == ("t", "x", "y", "p")
            outcomes["read"] += 1
        except EventFileError as e:
            assert str(mutant) in str(e)
            outcomes["error"] += 1
    # Both outcomes happen: the fuzzing reaches the decoders, not only the header checks.
    assert outcomes["read"] and outcomes["error"], outcomes
