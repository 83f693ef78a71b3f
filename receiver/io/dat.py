"""Prophesee DAT files: an ASCII header, a type/size byte pair, then 8-byte CD records.

Record: u32 t (us), u32 word with x in bits 0-13, y in bits 14-27 and polarity in bit 28.
Readers accept event types 0x00 (Event2D, OpenEB's writer) and 0x0C (EventCD); the writer uses
0x0C, which faery and Metavision both read.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from receiver.events import EVENT_DTYPE
from receiver.io.errors import EventFileError
from receiver.io.prophesee_header import header_geometry, read_header, write_header
from receiver.io.stream import (
    BLOCK_BYTES,
    EventChecker,
    EventStream,
    Progressed,
    as_event_chunks,
    check_writable,
    read_blocks,
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
    width, height = header_geometry(header) or (None, None)
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
                raw_t = rec["t"].astype(np.int64)
                wrapped = np.diff(raw_t, prepend=last_t) < -(1 << 31)
                t = raw_t + ((wraps + np.cumsum(wrapped)) << 32)
                wraps += int(wrapped.sum())
                last_t = int(raw_t[-1])
                events = np.empty(len(rec), EVENT_DTYPE)
                events["t"] = t
                events["x"] = rec["w"] & 0x3FFF
                events["y"] = (rec["w"] >> 14) & 0x3FFF
                events["p"] = np.where(rec["w"] & (1 << 28), 1, -1)
                problem = checker.first_problem(events)
                reserved = np.flatnonzero(rec["w"] >> 29)
                if reserved.size and (problem is None or reserved[0] < problem[0]):
                    problem = int(reserved[0]), "reserved bits 29-31 are set (corrupt record)"
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
