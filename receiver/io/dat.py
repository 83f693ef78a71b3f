"""Prophesee DAT files: an ASCII header, a type/size byte pair, then 8-byte CD records.

Record: u32 t (us), u32 word with x in bits 0-13, y in bits 14-27 and polarity in bit 28.
Readers accept event types 0x00 (Event2D, OpenEB's writer) and 0x0C (EventCD); the writer uses
0x0C, which faery and Metavision both read.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numba
import numpy as np

from eventocc.receiver.events import EVENT_DTYPE
from eventocc.receiver.io.errors import EventFileError
from eventocc.receiver.io.prophesee_header import header_geometry, read_header, write_header
from eventocc.receiver.io.stream import (
    BLOCK_BYTES,
    EventChecker,
    EventStream,
    Progressed,
    as_event_chunks,
    check_writable,
    read_blocks,
    sensor_size,
    sorted_by_time,
)

RECORD = np.dtype([("t", "<u4"), ("w", "<u4")])
CD_TYPES = (0x00, 0x0C)
COORD_LIMIT = 1 << 14
MAX_T = (1 << 32) - 1


def is_dat_header(header: dict[str, str]) -> bool:
    return header.get("data", "").lower().startswith("file containing") or "version" in header


def open_dat(path: Path) -> EventStream:
    with path.open("rb") as f:
        header, offset = read_header(f)
        if header:  # headerless legacy files have no type/size bytes either
            kind = f.read(2)
            if len(kind) < 2:
                raise EventFileError(path, "file ends before the event type bytes", offset=offset)
            if kind[0] not in CD_TYPES or kind[1] != RECORD.itemsize:
                raise EventFileError(
                    path,
                    f"event type 0x{kind[0]:02x} of size {kind[1]} is not CD events "
                    "(type 0x00 or 0x0c, size 8)",
                    offset=offset,
                )
            offset += 2
    width, height = sensor_size(
        path, *(header_geometry(header) or (None, None)), limit=COORD_LIMIT, where="in the header"
    )
    return EventStream(
        _records(path, offset, width, height),
        path=path,
        format="dat",
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _records(
    path: Path, offset: int, width: int | None, height: int | None
) -> Iterator[Progressed]:
    checker = EventChecker(width, height, COORD_LIMIT)
    wraps = 0  # u32 timestamps wrap every 71.6 min; a long recording counts the wraps
    last_t = 0
    with path.open("rb") as f:
        f.seek(offset)
        for block in read_blocks(f, RECORD.itemsize, BLOCK_BYTES):
            whole = len(block) - len(block) % RECORD.itemsize
            rec = np.frombuffer(block, RECORD, count=whole // RECORD.itemsize)
            if len(rec):
                events = np.empty(len(rec), EVENT_DTYPE)
                wraps, last_t, reserved = _decode(rec, events, wraps, last_t)
                problem = checker.first_problem(events)
                if reserved >= 0 and (problem is None or reserved < problem[0]):
                    problem = reserved, "reserved bits 29-31 are set (corrupt record)"
                if problem is not None:
                    i, what = problem
                    if i:
                        yield events[:i], offset + i * RECORD.itemsize
                    raise EventFileError(path, what, offset=offset + i * RECORD.itemsize)
                yield events, offset + whole
            offset += whole
            if whole < len(block):
                raise EventFileError(
                    path, "file ends inside an 8-byte record (truncated)", offset=offset
                )


@numba.njit(cache=True, nogil=True)
def _decode(rec, events, wraps, last_t):
    """Fill ``events`` from the records; return the timestamp wraps counted so far (u32
    microseconds wrap every 71.6 min), the last raw time and the first record with reserved
    bits set (-1: none). One compiled pass: with numpy's a DAT file took four to eight times
    as long to read (``bench.readers``; 4 M events in memory)."""
    reserved = -1
    for i in range(rec.shape[0]):
        t, w = np.int64(rec[i].t), rec[i].w
        if t - last_t < -(1 << 31):
            wraps += 1
        last_t = t
        e = events[i]
        e.t = t + (wraps << 32)
        e.x, e.y = w & 0x3FFF, (w >> 14) & 0x3FFF
        e.p = 1 if w & (1 << 28) else -1
        if reserved < 0 and w >> 29:
            reserved = i
    return wraps, last_t, reserved


def write_dat(path: Path, chunks: Iterable[np.ndarray], *, width: int, height: int) -> int:
    if not (0 < width <= COORD_LIMIT and 0 < height <= COORD_LIMIT):
        raise ValueError(
            f"DAT holds sensors up to {COORD_LIMIT}x{COORD_LIMIT}, got {width}x{height}"
        )
    count = 0
    with path.open("wb") as f:
        f.write(
            write_header(
                {
                    "Data": "file containing CD events",
                    "Version": "2",
                    "Width": str(width),
                    "Height": str(height),
                },
                end=False,
            )
        )
        f.write(bytes([0x0C, RECORD.itemsize]))
        for chunk in as_event_chunks(chunks):
            chunk = sorted_by_time(chunk)
            check_writable(chunk, format="DAT", width=width, height=height, max_t=MAX_T)
            rec = np.empty(len(chunk), RECORD)
            rec["t"] = chunk["t"]
            rec["w"] = (
                chunk["x"].astype(np.uint32)
                | (chunk["y"].astype(np.uint32) << 14)
                | ((chunk["p"] > 0).astype(np.uint32) << 28)
            )
            f.write(rec.tobytes())
            count += len(chunk)
    return count
