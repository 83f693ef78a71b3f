"""Event files in and out: ``read_events`` streams any supported file, ``write_events`` writes one.

Formats (name: files): ``evt2``, ``evt21``, ``evt3`` (Prophesee RAW ``.raw``), ``dat`` (Prophesee
DAT), ``aedat4`` (iniVation), ``rosbag`` (ROS1 ``.bag``, ROS2 ``.mcap``/``.db3``/folder),
``text`` (``t x y p`` lines), ``npz`` and ``hdf5`` (DSEC layout). Writable: evt2, evt3, dat,
npz, hdf5, text.

The format is found from the file's content first (RAW/DAT header, AEDAT4, bag, HDF5, zip or
SQLite magic), then from its extension. A file whose content says one format and extension
another is read by its content, with a logged warning. ``format=`` overrides both.

Whatever a file holds, reading it ends in events or an ``EventFileError``: what the
third-party decoders raise is turned into one (``errors.foreign_errors``), and memory stays
bounded: files are read in blocks, and npz and HDF5 files whose columns would inflate to more
than ``stream.MAX_INFLATION`` times their size are refused (``EVENTOCC_MAX_INFLATION`` allows
more).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from eventocc.receiver.events import rechunk_by_count, rechunk_by_time
from eventocc.receiver.io.aedat import open_aedat4
from eventocc.receiver.io.dat import is_dat_header, open_dat, write_dat
from eventocc.receiver.io.errors import EventFileError, MissingExtraError
from eventocc.receiver.io.npz_h5 import open_hdf5, open_npz, write_hdf5, write_npz
from eventocc.receiver.io.prophesee_header import read_header
from eventocc.receiver.io.prophesee_raw import (
    ENCODINGS,
    header_encoding,
    open_raw,
    write_evt2,
    write_evt3,
)
from eventocc.receiver.io.rosbag import is_bag_dir, open_rosbag
from eventocc.receiver.io.stream import EventStream
from eventocc.receiver.io.text import open_text, write_text

__all__ = [
    "READ_FORMATS",
    "WRITE_FORMATS",
    "EventFileError",
    "EventStream",
    "MissingExtraError",
    "detect_format",
    "read_events",
    "write_events",
]

log = logging.getLogger(__name__)

READERS: dict[str, Callable[[Path], EventStream]] = {
    **{name: (lambda p, name=name: open_raw(p, name)) for name in ENCODINGS},
    "raw": open_raw,  # encoding from the header
    "dat": open_dat,
    "aedat4": open_aedat4,
    "rosbag": open_rosbag,
    "text": open_text,
    "npz": open_npz,
    "hdf5": open_hdf5,
}
WRITERS: dict[str, Callable[..., int]] = {
    "evt2": write_evt2,
    "evt3": write_evt3,
    "dat": write_dat,
    "npz": write_npz,
    "hdf5": write_hdf5,
    "text": write_text,
}
READ_FORMATS = tuple(READERS)
RAW_FORMATS = ("raw", *ENCODINGS)
WRITE_FORMATS = tuple(WRITERS)

# Extension -> (format when reading, format when writing).
EXTENSIONS: dict[str, tuple[str, str | None]] = {
    ".raw": ("raw", "evt3"),
    ".dat": ("dat", "dat"),
    ".aedat4": ("aedat4", None),
    ".bag": ("rosbag", None),
    ".mcap": ("rosbag", None),
    ".db3": ("rosbag", None),
    ".txt": ("text", "text"),
    ".npz": ("npz", "npz"),
    ".h5": ("hdf5", "hdf5"),
    ".hdf5": ("hdf5", "hdf5"),
}
MAGIC: tuple[tuple[bytes, str], ...] = (
    (b"#!AER-DAT4.0", "aedat4"),
    (b"#ROSBAG V2.0", "rosbag"),
    (b"\x89MCAP", "rosbag"),
    (b"SQLite format 3\x00", "rosbag"),
    (b"\x89HDF\r\n\x1a\n", "hdf5"),
    (b"PK\x03\x04", "npz"),
)


def _format_by_content(path: Path) -> str | None:
    if is_bag_dir(path):
        return "rosbag"
    with path.open("rb") as f:
        start = f.read(16)
        for magic, name in MAGIC:
            if start.startswith(magic):
                return name
        header, _ = read_header(f)
    if header_encoding(header) is not None:
        return "raw"
    if is_dat_header(header):
        return "dat"
    return None


def detect_format(path: str | Path) -> str:
    """The reader format for ``path``: by content, then by extension."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such event file: {path}")
    by_content = _format_by_content(path)
    by_extension = EXTENSIONS.get(path.suffix.lower(), (None, None))[0]
    if by_content and by_extension and by_content != by_extension:
        log.warning(
            "%s: content is %s although the extension says %s; reading it as %s",
            path,
            by_content,
            by_extension,
            by_content,
        )
    fmt = by_content or by_extension
    if fmt is None:
        raise EventFileError(
            path,
            "cannot tell the event format from the content or the "
            f"extension; pass one of {READ_FORMATS}",
            offset=0,
        )
    return fmt


def read_events(
    path: str | Path,
    *,
    format: str | None = None,
    chunk_events: int | None = None,
    chunk_us: int | None = None,
    on_error: str = "raise",
    monotonic: bool = False,
) -> EventStream:
    """Stream the events of a file as chunks of ``eventocc.receiver.events.EVENT_DTYPE``.

    ``chunk_events`` / ``chunk_us`` re-cut the chunks by count or time window (at most one).
    ``on_error="stop"`` turns a truncated or corrupt file into a ``UserWarning`` and a clean
    end after the last whole event; ``"raise"`` raises ``EventFileError``.
    Timestamps are kept as recorded, small reversals included; ``monotonic`` holds the clock
    at its latest value instead (for RAW files at the sensor's time words, as faery does).
    """
    path = Path(path)
    if on_error not in ("raise", "stop"):
        raise ValueError(f"on_error must be 'raise' or 'stop', got {on_error!r}")
    if chunk_events is not None and chunk_us is not None:
        raise ValueError("give chunk_events or chunk_us, not both")
    if format is not None and format not in READERS:
        raise ValueError(f"unknown event format {format!r}; choose one of {READ_FORMATS}")
    if format is None:
        format = detect_format(path)
    elif not path.exists():
        raise FileNotFoundError(f"no such event file: {path}")
    if format in RAW_FORMATS:
        stream = open_raw(path, None if format == "raw" else format, monotonic=monotonic)
    else:
        stream = READERS[format](path)
    if monotonic:  # a no-op after EVT 3.0's clock hold; the guarantee for every other format
        stream.map_chunks(_hold_clock)
    if on_error == "stop":
        stream.map_chunks(_stop_on_error)
    if chunk_events is not None:
        stream.map_chunks(lambda chunks: rechunk_by_count(chunks, chunk_events))
    if chunk_us is not None:
        stream.map_chunks(lambda chunks: rechunk_by_time(chunks, chunk_us))
    return stream


def _hold_clock(chunks: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
    latest = np.iinfo(np.int64).min
    for chunk in chunks:
        if len(chunk):
            chunk = chunk.copy()
            np.maximum(np.maximum.accumulate(chunk["t"]), latest, out=chunk["t"])
            latest = int(chunk["t"][-1])
        yield chunk


def _stop_on_error(chunks: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
    try:
        yield from chunks
    except EventFileError as e:
        warnings.warn(f"stopped reading early: {e}", UserWarning, stacklevel=2)


def write_events(
    path: str | Path,
    chunks: np.ndarray | Iterable[np.ndarray],
    *,
    format: str | None = None,
    width: int,
    height: int,
) -> int:
    """Write event chunks (or one array) to ``path``; returns the number of events written.

    The format comes from ``format`` or the extension (``.raw`` is written as EVT 3.0).
    Timestamps below 0 or beyond the format's range raise ``ValueError``. The file appears
    whole or not at all: it is written beside ``path`` and moved there once complete, so an
    error (in the events, or in the file they are read from) leaves a file of that name as it
    was.
    """
    path = Path(path)
    if format is None:
        format = EXTENSIONS.get(path.suffix.lower(), (None, None))[1]
        if format is None:
            raise ValueError(
                f"cannot tell the format to write from {path.name!r}; pass "
                f"format= one of {WRITE_FORMATS}"
            )
    if format not in WRITERS:
        raise ValueError(f"cannot write {format!r}; choose one of {WRITE_FORMATS}")
    partial = path.with_name(f".{path.name}.partial")
    try:
        count = WRITERS[format](partial, chunks, width=width, height=height)
        partial.replace(path)
    finally:
        partial.unlink(missing_ok=True)
    return count
