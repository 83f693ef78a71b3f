"""iniVation AEDAT 4.0 files, decoded by the ``aedat`` package (extra ``aedat``).

The first event stream in the file is read; its packets become chunks. The decoder is Rust:
whatever it raises for a damaged file, a panic included, becomes ``EventFileError``.

Layout: ``#!AER-DAT4.0\r\n``, the IOHeader's size (u32) and the IOHeader, a flatbuffer table
of compression (i32), file data position (i64) and description (an XML string naming the
streams), then the packets.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Iterator
from pathlib import Path

from eventocc.receiver.events import make_events
from eventocc.receiver.io.errors import EventFileError, MissingExtraError, foreign_errors
from eventocc.receiver.io.stream import EventChecker, EventStream, Progressed, sensor_size


def _decoder(path: Path):
    try:
        import aedat
    except ImportError:
        raise MissingExtraError("AEDAT4 files", "aedat", "aedat") from None
    _check_ioheader(path)
    with foreign_errors(path, "not a readable AEDAT4 file", offset=0):
        return aedat.Decoder(str(path))


MAGIC = b"#!AER-DAT4.0\r\n"


def _check_ioheader(path: Path) -> None:
    """Check the IOHeader as flatbuffers' verifier would, before the decoder sees it: the
    decoder reads it unchecked, so a damaged offset reads outside the header, and a damaged
    description made it abort the whole process (its error message, holding the description's
    bytes, was not UTF-8)."""
    with path.open("rb") as f:
        magic, size = f.read(len(MAGIC)), f.read(4)
        if magic != MAGIC or len(size) < 4:
            raise EventFileError(path, "not an AEDAT4 file (no #!AER-DAT4.0 header)", offset=0)
        header = f.read(struct.unpack("<I", size)[0])
    try:
        (table,) = struct.unpack_from("<I", header, 0)
        vtable = table - struct.unpack_from("<i", header, table)[0]
        if vtable < 0:
            raise ValueError("its vtable lies before the header")
        vtable_size, table_size = struct.unpack_from("<HH", header, vtable)
        fields = struct.unpack_from(f"<{max(vtable_size - 4, 0) // 2}H", header, vtable + 4)
        if len(fields) < 3 or not fields[2]:
            raise ValueError("no description")
        if table + table_size > len(header) or any(
            offset + width > table_size
            for offset, width in zip(fields[:3], (4, 8, 4), strict=True)
            if offset
        ):
            raise ValueError("its table runs past the header")
        string = table + fields[2] + struct.unpack_from("<I", header, table + fields[2])[0]
        (length,) = struct.unpack_from("<I", header, string)
        description = header[string + 4 : string + 4 + length]
        if len(description) < length:
            raise ValueError("its description runs past the header")
        description.decode("utf-8")
    except (struct.error, ValueError) as e:  # UnicodeDecodeError is a ValueError
        raise EventFileError(
            path, f"damaged AEDAT4 IOHeader ({e})", offset=len(MAGIC) + 4
        ) from None


def _event_stream(path: Path, decoder) -> tuple[int, int | None, int | None]:
    with foreign_errors(path, "unreadable AEDAT4 stream description", where="in the header"):
        for stream_id, stream in sorted(decoder.id_to_stream().items()):
            if stream.get("type") == "events":
                size = stream["width"], stream["height"]
                return stream_id, *sensor_size(path, *size, where="in the header")
    raise EventFileError(path, "no event stream in this AEDAT4 file", where="in the header")


def open_aedat4(path: Path) -> EventStream:
    _, width, height = _event_stream(path, _decoder(path))
    return EventStream(
        _packets(path, width, height),
        path=path,
        format="aedat4",
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _packets(path: Path, width: int, height: int) -> Iterator[Progressed]:
    decoder = _decoder(path)
    stream_id = _event_stream(path, decoder)[0]
    checker = EventChecker(width, height)
    packets = iter(decoder)
    for index in itertools.count():
        with foreign_errors(path, "corrupt AEDAT4 packet", where=f"after packet {index}"):
            packet = next(packets, None)
            if packet is None:
                return
            if packet["stream_id"] != stream_id or "events" not in packet:
                continue
            raw = packet["events"]
            events = make_events(raw["t"].astype("int64"), raw["x"], raw["y"], raw["on"])
        problem = checker.first_problem(events)
        if problem is not None:
            i, what = problem
            if i:
                yield events[:i], 0
            raise EventFileError(path, what, where=f"in packet {index}, event {i}")
        yield events, 0
