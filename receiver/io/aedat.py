"""iniVation AEDAT 4.0 files, decoded by the ``aedat`` package (extra ``aedat``).

The first event stream in the file is read; its packets become chunks.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from eventocc.receiver.events import make_events
from eventocc.receiver.io.errors import EventFileError, MissingExtraError
from eventocc.receiver.io.stream import EventChecker, EventStream, Progressed


def _decoder(path: Path):
    try:
        import aedat
    except ImportError:
        raise MissingExtraError("AEDAT4 files", "aedat", "aedat") from None
    try:
        return aedat.Decoder(str(path))
    except Exception as e:  # the Rust decoder raises plain exceptions for bad files
        raise EventFileError(path, f"not a readable AEDAT4 file ({e})", offset=0) from None


def _event_stream(path: Path, decoder) -> tuple[int, int, int]:
    for stream_id, stream in sorted(decoder.id_to_stream().items()):
        if stream.get("type") == "events":
            return stream_id, int(stream["width"]), int(stream["height"])
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
    index = 0
    try:
        for index, packet in enumerate(decoder):
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
    except (RuntimeError, OSError, ValueError) as e:
        if isinstance(e, EventFileError):
            raise
        raise EventFileError(
            path, f"corrupt AEDAT4 packet ({e})", where=f"after packet {index}"
        ) from None
