"""Damaged and hostile event files: every reader ends each in events or an ``EventFileError``,
never another exception, never a hang (the timeouts), and never grows the process by more than
the readers' bound on what a file may inflate to.

A small file of every format is mutated (bits flipped, bytes inserted or deleted, the end cut
off) ``CASES`` times in the default suite and ``SLOW_CASES`` times under ``pytest -m slow``.
The mutations are seeded, so a failure repeats; the third-party decoders (h5py, rosbags with
apsw and mcap, aedat, numpy's npy parser) are the real ones.
"""

from __future__ import annotations

import io
import os
import struct
import subprocess
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from eventocc.receiver.events import make_events
from eventocc.receiver.io import EventFileError, read_events, write_events
from eventocc.receiver.io.stream import INFLATION_FLOOR_BYTES
from tests.event_files import write_aedat4, write_bag, write_evt21

CASES = 300
SLOW_CASES = 5000
MEMORY_BOUND = INFLATION_FLOOR_BYTES + (16 << 20)
"""Resident memory a read may add: what any file may inflate to, and room for the decoders'
own buffers."""
rng = np.random.default_rng(7)
N = 120
EVENTS = make_events(
    np.sort(rng.integers(0, 50_000, N)),
    rng.integers(0, 32, N),
    rng.integers(0, 24, N),
    rng.integers(0, 2, N),
)


def _ours(fmt: str, name: str) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        write_events(folder / name, EVENTS, format=fmt, width=32, height=24)
        return folder / name

    return write


def _bag(storage: str) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        events = EVENTS.copy()
        events["t"] += 1_700_000_000_000_000
        path = folder / ("f.bag" if storage == "ros1" else "bag2")
        write_bag(path, storage, "dvs_msgs", [events[:40], events[40:80], events[80:]], 32, 24)
        if storage == "ros1":
            return path
        # A ROS 2 bag's storage file, which rosbags reads without its folder.
        (storage_file,) = path.glob("*.db3" if storage == "sqlite3" else "*.mcap")
        return storage_file

    return write


def _evt21(folder: Path) -> Path:
    write_evt21(folder / "f.raw", EVENTS, 32, 24)
    return folder / "f.raw"


def _aedat4(folder: Path) -> Path:
    write_aedat4(folder / "f.aedat4", EVENTS, 32, 24)
    return folder / "f.aedat4"


SEEDS: dict[str, Callable[[Path], Path]] = {
    "evt3": _ours("evt3", "f.raw"),
    "evt2": _ours("evt2", "f.raw"),
    "evt21": _evt21,
    "dat": _ours("dat", "f.dat"),
    "text": _ours("text", "f.txt"),
    "npz": _ours("npz", "f.npz"),
    "hdf5": _ours("hdf5", "f.h5"),
    "aedat4": _aedat4,
    "rosbag1": _bag("ros1"),
    "rosbag2-sqlite3": _bag("sqlite3"),
    "rosbag2-mcap": _bag("mcap"),
}


@pytest.fixture(autouse=True)
def quiet_rust_panics(monkeypatch) -> None:
    """With ``RUST_BACKTRACE`` set, the first panic of a Rust decoder (aedat's) symbolizes a
    backtrace for stderr, which takes some 50 MB once: the environment's memory, not the
    file's."""
    monkeypatch.setenv("RUST_BACKTRACE", "0")


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


def _status(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) << 10
    raise LookupError(field)


def read_to_end(path: Path) -> tuple[str, int]:
    """("read" or "error", bytes the process's resident memory grew by at its peak meanwhile).
    Any exception but ``EventFileError`` fails the test."""
    Path("/proc/self/clear_refs").write_text("5")  # resets the peak to what is resident now
    before = _status("VmRSS")
    try:
        for chunk in read_events(path):
            assert chunk.dtype.names == ("t", "x", "y", "p")
        outcome = "read"
    except EventFileError as e:
        assert str(path) in str(e)
        outcome = "error"
    return outcome, _status("VmHWM") - before


def fuzz(tmp_path: Path, fmt: str, cases: int) -> None:
    seed = SEEDS[fmt](tmp_path)
    assert read_to_end(seed)[0] == "read"  # and compiles, imports and warms up the reader
    data = seed.read_bytes()
    mutant = tmp_path / f"m{seed.suffix}"
    rng = np.random.default_rng(list(SEEDS).index(fmt))
    outcomes = {"read": 0, "error": 0}
    for case in range(cases):
        mutant.write_bytes(mutate(data, rng))
        outcome, grown = read_to_end(mutant)
        outcomes[outcome] += 1
        assert grown <= MEMORY_BOUND, f"case {case} grew the process by {grown:,} bytes"
    # Both outcomes happen: the fuzzing reaches the decoders, not only the header checks.
    assert outcomes["read"] and outcomes["error"], outcomes


@pytest.mark.timeout(120)
@pytest.mark.parametrize("fmt", SEEDS)
def test_mutants_end_in_events_or_an_event_file_error(tmp_path, fmt: str) -> None:
    fuzz(tmp_path, fmt, CASES)


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("fmt", SEEDS)
def test_many_mutants_end_in_events_or_an_event_file_error(tmp_path, fmt: str) -> None:
    fuzz(tmp_path, fmt, SLOW_CASES)


# ------------------------------------------------------------------------------ hostile files


def _npy(dtype: str, shape: tuple[int, ...], body: bytes = b"") -> bytes:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": dtype, "fortran_order": False, "shape": shape}
    )
    return header.getvalue() + body


def npz_bomb(path: Path, n: int = 8 << 20) -> None:
    """An npz of ``n`` all-zero events: a few hundred kB that inflate to 13 bytes an event."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, dtype in (("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "|u1")):
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                member.write(_npy(dtype, (n,)))
                block = bytes(1 << 20)
                for _ in range(n * np.dtype(dtype).itemsize >> 20):
                    member.write(block)


def npz_of(path: Path, **members: bytes) -> None:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(f"{name}.npy", data)


def hdf5_of(path: Path, build: Callable) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        events = f.create_group("events")
        build(events)


def _columns(events, n: int, **options) -> None:
    for name, dtype in (("t", "i8"), ("x", "u2"), ("y", "u2"), ("p", "u1")):
        events.create_dataset(name, shape=(n,), dtype=dtype, **options)


def _hdf5_zeros(events) -> None:
    _columns(events, 8 << 20, chunks=(1 << 20,), compression="gzip")
    for column in events.values():
        for start in range(0, len(column), 1 << 20):
            column[start : start + (1 << 20)] = 0


def _hdf5_text_column(events) -> None:
    _columns(events, 3)
    del events["t"]
    events["t"] = np.array([b"one", b"two", b"six"])


HOSTILE: dict[str, tuple[Callable[[Path], None], str]] = {
    # name: (writes the file, what the EventFileError says)
    "dat with a 20-digit height": (
        lambda p: p.with_suffix(".dat").write_bytes(
            b"% Data file containing CD events\n% Version 2\n% Width 32\n"
            b"% Height 99999999999999999999\n\x0c\x08" + bytes(16)
        ),
        "is not 1..16384 pixels a side",
    ),
    "raw with a 20-digit width": (
        lambda p: p.with_suffix(".raw").write_bytes(
            b"% evt 3.0\n% format EVT3;height=24;width=99999999999999999999\n% end\n" + bytes(8)
        ),
        "is not 1..2048 pixels a side",
    ),
    "a ros bag's magic in a .raw": (
        lambda p: p.with_suffix(".raw").write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 4),
        "not a readable ROS bag",
    ),
    "an mcap's magic and nothing": (
        lambda p: p.with_suffix(".raw").write_bytes(b"\x89MCAP0\r\n" + bytes(64)),
        "not a readable ROS bag",
    ),
    "an sqlite file's magic and nothing": (
        lambda p: p.with_suffix(".db3").write_bytes(b"SQLite format 3\x00" + bytes(200)),
        "not a readable ROS bag",
    ),
    "an aedat4 magic and a bad description": (
        lambda p: p.with_suffix(".aedat4").write_bytes(b"#!AER-DAT4.0\r\n" + bytes(range(256))),
        "AEDAT4",
    ),
    "an hdf5 magic and nothing": (
        lambda p: p.with_suffix(".h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100)),
        "not a readable HDF5 file",
    ),
    "a zip that is no npz": (
        lambda p: p.with_suffix(".npz").write_bytes(b"PK\x03\x04" + bytes(100)),
        "not a readable npz file",
    ),
    "an npz bomb": (lambda p: npz_bomb(p.with_suffix(".npz")), "decompression bomb"),
    "an npz claiming a trillion events": (
        lambda p: npz_of(
            p.with_suffix(".npz"),
            **{k: _npy("<i8", (10**12,), bytes(8)) for k in "txyp"},
        ),
        "not the 1000000000000 of int64 its header says",
    ),
    "an npz whose header does not parse": (
        lambda p: npz_of(p.with_suffix(".npz"), t=b"\x93NUMPY\x01\x00\x10\x00{'descr': '<i8',\n"),
        "not a readable npz file",
    ),
    "an npz with three time offsets": (
        lambda p: npz_of(
            p.with_suffix(".npz"),
            **{k: _npy("<i8", (1,), bytes(8)) for k in "txyp"},
            t_offset=_npy("<i8", (3,), bytes(24)),
        ),
        "t_offset",
    ),
    "an hdf5 bomb": (lambda p: hdf5_of(p.with_suffix(".h5"), _hdf5_zeros), "decompression bomb"),
    "an hdf5 trillion events never written": (
        lambda p: hdf5_of(p.with_suffix(".h5"), lambda e: _columns(e, 10**12, chunks=(4096,))),
        "decompression bomb",
    ),
    "an hdf5 chunk of a billion events": (
        lambda p: hdf5_of(
            p.with_suffix(".h5"),
            lambda e: _columns(e, 10, chunks=(10**9,), maxshape=(None,), compression="gzip"),
        ),
        "decompression bomb",
    ),
    "an hdf5 column of text": (
        lambda p: hdf5_of(p.with_suffix(".h5"), _hdf5_text_column),
        "/events/t is not a 1-D column of integers",
    ),
    "an hdf5 sensor size in words": (
        lambda p: hdf5_of(
            p.with_suffix(".h5"),
            lambda e: (_columns(e, 3), e.attrs.update(width="wide", height="tall")),
        ),
        "is not two whole numbers",
    ),
    "a text line of a megabyte": (
        lambda p: p.with_suffix(".txt").write_bytes(b"1 2 3 1\n" + b"7" * (1 << 20)),
        "a line longer than 64 KiB",
    ),
    "a text time of 30 digits": (
        lambda p: p.with_suffix(".txt").write_bytes(b"1 2 3 1\n" + b"9" * 30 + b" 2 3 1\n"),
        "not 't x y p' text",
    ),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", HOSTILE)
def test_hostile_files_are_refused_in_bounded_memory(tmp_path, name: str) -> None:
    write, says = HOSTILE[name]
    write(tmp_path / "f")
    (path,) = tmp_path.iterdir()
    Path("/proc/self/clear_refs").write_text("5")
    before = _status("VmRSS")
    with pytest.raises(EventFileError, match=says) as refused:
        for _ in read_events(path):
            pass
    assert str(path) in str(refused.value)
    assert _status("VmHWM") - before <= MEMORY_BOUND


def test_a_bomb_reads_once_the_limit_is_raised(tmp_path, monkeypatch) -> None:
    npz_bomb(tmp_path / "zeros.npz", n=2 << 20)
    with pytest.raises(EventFileError, match=r"allow it with EVENTOCC_MAX_INFLATION=\d+") as e:
        read_events(tmp_path / "zeros.npz")
    monkeypatch.setenv("EVENTOCC_MAX_INFLATION", str(e.value).rsplit("=", 1)[1])
    assert sum(len(chunk) for chunk in read_events(tmp_path / "zeros.npz")) == 2 << 20


def test_an_aedat4_description_not_in_utf8_is_refused_not_fatal(tmp_path) -> None:
    """aedat's decoder aborted the whole process (SIGABRT) on this one, so it is read in a
    child process: a regression fails this test, not the suite."""
    path = tmp_path / "f.aedat4"
    write_aedat4(path, EVENTS, 32, 24)
    data = path.read_bytes()
    header_end = 18 + struct.unpack_from("<I", data, 14)[0]
    at = data.rindex(b"</node>", 0, header_end) + len(b"</node")
    path.write_bytes(data[:at] + b"\xdf9" + data[at:])  # a closing tag the XML parser quotes
    code = (
        "from eventocc.receiver.io import EventFileError, read_events\n"
        f"try:\n    list(read_events({str(path)!r}))\n"
        "except EventFileError as e:\n    print(e)\n"
    )
    child = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "RUST_BACKTRACE": "0"},
        timeout=60,
    )
    assert child.returncode == 0, child.stderr[-2000:]
    assert "damaged AEDAT4 IOHeader" in child.stdout
