"""Plain text events, one ``t x y p`` line each (the RPG Event Camera Dataset's events.txt).

``t`` is seconds when the first event's time has a decimal point or exponent, otherwise integer
microseconds; ``p`` may be {0, 1} or {-1, 1}. Lines starting with ``#`` are comments. The
writer uses seconds with microsecond precision and p in {0, 1}, as that dataset does.
"""

from __future__ import annotations

import io
import re
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from eventocc.receiver.events import EVENT_DTYPE
from eventocc.receiver.io.errors import EventFileError
from eventocc.receiver.io.stream import (
    EventChecker,
    EventStream,
    Progressed,
    as_event_chunks,
    check_writable,
    sensor_size,
    sorted_by_time,
)

TEXT_BLOCK_BYTES = 4 << 20
MAX_LINE_BYTES = 64 << 10
"""An event line is some 40 bytes: a longer line is not 't x y p' text (and is not held)."""
# Seconds below 2**32 parse from text into float64 with sub-microsecond error.
MAX_T = (1 << 32) * 1_000_000 - 1
# "# width 640 height 480": an optional comment the writer adds so geometry survives.
GEOMETRY_COMMENT = re.compile(rb"#\s*width\s+(\d{1,9})\s+height\s+(\d{1,9})\b")


def open_text(path: Path) -> EventStream:
    width = height = None
    seconds = False
    with path.open("rb") as f:
        while line := f.readline(MAX_LINE_BYTES + 1):
            _check_line_length(path, line, f.tell() - len(line))
            if line.startswith(b"#"):
                if m := GEOMETRY_COMMENT.match(line):
                    width, height = m[1], m[2]
                continue
            if line.strip():
                seconds = any(c in line.split()[0] for c in b".eE")
                break
    if width is not None:
        width, height = sensor_size(path, int(width), int(height), where="in its geometry comment")
    return EventStream(
        _lines(path, seconds, width, height),
        path=path,
        format="text",
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _lines(
    path: Path, seconds: bool, width: int | None, height: int | None
) -> Iterator[Progressed]:
    checker = EventChecker(width, height)
    offset = 0
    tail = b""
    with path.open("rb") as f:
        while True:
            data = f.read(TEXT_BLOCK_BYTES)
            text = tail + data
            cut = text.rfind(b"\n") + 1 if data else len(text)
            block, tail = text[:cut], text[cut:]
            _check_line_length(path, tail, offset + len(block))
            if block:
                events = _parse(path, block, offset, seconds)
                problem = checker.first_problem(events)
                if problem is not None:
                    i, what = problem
                    if i:
                        yield events[:i], offset
                    raise EventFileError(
                        path, what, where=f"at event {i} of the block starting at byte {offset}"
                    )
                offset += len(block)
                if len(events):
                    yield events, offset
            if not data:
                return


def _check_line_length(path: Path, line: bytes, offset: int) -> None:
    if len(line) > MAX_LINE_BYTES:
        raise EventFileError(
            path,
            f"a line longer than {MAX_LINE_BYTES >> 10} KiB: not 't x y p' text",
            offset=offset,
        )


def _parse(path: Path, block: bytes, offset: int, seconds: bool) -> np.ndarray:
    columns = np.dtype(
        [
            ("t", np.float64 if seconds else np.int64),
            ("x", np.int64),
            ("y", np.int64),
            ("p", np.int64),
        ]
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data" for comment-only blocks
            rows = np.atleast_1d(
                np.loadtxt(io.BytesIO(block), dtype=columns, comments="#", ndmin=1)
            )
    except ValueError as e:
        raise EventFileError(
            path, f"not 't x y p' text ({e})", where=f"in the lines starting at byte {offset}"
        ) from None
    bad = (rows["x"] < 0) | (rows["x"] >= 1 << 16) | (rows["y"] < 0) | (rows["y"] >= 1 << 16)
    bad |= (rows["p"] < -1) | (rows["p"] > 1)
    if seconds:
        bad |= ~np.isfinite(rows["t"]) | (np.abs(rows["t"]) > MAX_T / 1e6)
    if bad.any():
        i = int(np.argmax(bad))
        raise EventFileError(
            path,
            f"event {tuple(rows[i].tolist())} has a coordinate or "
            "polarity out of range (p must be 0, 1 or -1)",
            where=f"at line {i + 1} of the lines starting at byte {offset}",
        )
    events = np.empty(len(rows), EVENT_DTYPE)
    events["t"] = np.rint(rows["t"] * 1e6) if seconds else rows["t"]
    events["x"] = rows["x"]
    events["y"] = rows["y"]
    events["p"] = np.where(rows["p"] > 0, 1, -1)
    return events


def write_text(path: Path, chunks: Iterable[np.ndarray], *, width: int, height: int) -> int:
    count = 0
    with path.open("w") as f:
        f.write(f"# width {width} height {height}\n# t[s] x y p\n")
        for chunk in as_event_chunks(chunks):
            chunk = sorted_by_time(chunk)
            check_writable(chunk, format="text", width=width, height=height, max_t=MAX_T)
            if not len(chunk):
                continue
            sec, us = np.divmod(chunk["t"], 1_000_000)
            lines = np.char.add(np.char.add(sec.astype(str), "."), np.char.zfill(us.astype(str), 6))
            rows = np.column_stack(
                [
                    lines,
                    chunk["x"].astype(str),
                    chunk["y"].astype(str),
                    (chunk["p"] > 0).astype(int).astype(str),
                ]
            )
            np.savetxt(f, rows, fmt="%s")
            count += len(chunk)
    return count
