"""Column files in the DSEC layout: ``events/{t,x,y,p}`` plus ``t_offset`` (us added to t).

HDF5 (``.h5``/``.hdf5``): DSEC's ``/events/t`` (relative us), ``/events/x``, ``/events/y``,
``/events/p`` (0/1), ``/t_offset`` and ``/ms_to_idx``; sensor size in attributes ``width`` and
``height`` of ``/events`` when known. Blosc/Zstd-compressed files (DSEC) need ``hdf5plugin``,
imported when installed. npz: the same columns as arrays ``t``, ``x``, ``y``, ``p``,
``t_offset``, ``width``, ``height``; npz cannot be streamed, so it suits small files.
"""

from __future__ import annotations

import contextlib
import io
import math
import operator
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from eventocc.receiver.events import EVENT_DTYPE, concat
from eventocc.receiver.io.errors import EventFileError, MissingExtraError, foreign_errors
from eventocc.receiver.io.stream import (
    EventChecker,
    EventStream,
    Progressed,
    as_event_chunks,
    check_inflation,
    check_writable,
    sensor_size,
    sorted_by_time,
)

CHUNK_EVENTS = 1 << 20
NPZ_ARRAYS = ("t", "x", "y", "p", "t_offset", "width", "height")
MAX_T = np.iinfo(np.int64).max


def _h5py():
    try:
        import h5py
    except ImportError:
        raise MissingExtraError("HDF5 event files", "h5py", "h5") from None
    with contextlib.suppress(ImportError):
        import hdf5plugin  # noqa: F401  (registers Blosc/Zstd filters used by DSEC)
    return h5py


def _columns_to_events(t, x, y, p, t_offset: int) -> np.ndarray:
    events = np.empty(len(t), EVENT_DTYPE)
    events["t"] = np.asarray(t, dtype=np.int64) + t_offset
    events["x"] = x
    events["y"] = y
    events["p"] = np.where(np.asarray(p) > 0, 1, -1)
    return events


def _checked(
    path: Path,
    pieces: Iterator[tuple[np.ndarray, int]],
    checker: EventChecker,
    n_total: int,
    size: int,
) -> Iterator[Progressed]:
    """Yield checked chunks; ``pieces`` yields (events, index of the first one)."""
    for events, start in pieces:
        problem = checker.first_problem(events)
        if problem is not None:
            i, what = problem
            if i:
                yield events[:i], size * (start + i) // max(n_total, 1)
            raise EventFileError(path, what, where=f"at event {start + i}")
        yield events, size * (start + len(events)) // max(n_total, 1)


def open_hdf5(path: Path) -> EventStream:
    h5py = _h5py()
    with foreign_errors(path, "not a readable HDF5 file", offset=0):
        f = h5py.File(path, "r")
    with f, foreign_errors(path, "damaged HDF5 file", where="in the HDF5 tree"):
        events = f.get("events")
        if not isinstance(events, h5py.Group) or not {"t", "x", "y", "p"} <= set(events):
            raise EventFileError(
                path,
                f"no /events/{{t,x,y,p}} datasets (DSEC layout); top-level keys: {sorted(f)}",
                where="in the HDF5 tree",
            )
        columns = [_column(path, h5py, events, k) for k in "txyp"]
        lengths = {len(c) for c in columns}
        if len(lengths) != 1:
            raise EventFileError(
                path, f"/events columns differ in length: {lengths}", where="in /events"
            )
        n_total = lengths.pop()
        # A read inflates whole chunks: count a chunk larger than its column as read in full.
        decoded = sum(max(n_total, (c.chunks or (0,))[0]) * c.dtype.itemsize for c in columns)
        check_inflation(path, decoded, path.stat().st_size, where="in /events")
        attrs = events.attrs
        width, height = sensor_size(
            path, attrs.get("width"), attrs.get("height"), where="in the /events attributes"
        )
        t_offset = _t_offset(path, f["t_offset"][()] if "t_offset" in f else 0, "/t_offset")
    return EventStream(
        _hdf5_chunks(path, width, height, n_total, t_offset),
        path=path,
        format="hdf5",
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _column(path: Path, h5py, events, key: str):
    """``/events/<key>``, checked to be a 1-D column of integers stored in this file."""
    column = events[key]
    if not isinstance(column, h5py.Dataset) or column.ndim != 1 or column.dtype.kind not in "iub":
        raise EventFileError(
            path,
            f"/events/{key} is not a 1-D column of integers ({column!r})",
            where="in /events",
        )
    if column.is_virtual or column.external:
        raise EventFileError(
            path,
            f"/events/{key} is stored outside this file, which is not read",
            where="in /events",
        )
    return column


def _t_offset(path: Path, value, where: str) -> int:
    try:
        return operator.index(value)
    except TypeError:
        raise EventFileError(
            path, f"t_offset {value!r} is not a whole number", where=where
        ) from None


def _hdf5_chunks(path: Path, width, height, n_total: int, t_offset: int) -> Iterator[Progressed]:
    h5py = _h5py()
    with foreign_errors(path, "not a readable HDF5 file", offset=0):
        f = h5py.File(path, "r")
    with f:
        cols = [f["events"][k] for k in "txyp"]

        def pieces():
            for start in range(0, n_total, CHUNK_EVENTS):
                stop = min(start + CHUNK_EVENTS, n_total)
                with foreign_errors(path, "cannot read /events", where=f"at event {start}"):
                    try:
                        t, x, y, p = (c[start:stop] for c in cols)
                    except OSError as e:  # e.g. a compression filter that is not installed
                        raise EventFileError(
                            path,
                            f"cannot read /events ({e}); Blosc/Zstd files "
                            "need 'pip install hdf5plugin'",
                            where=f"at event {start}",
                        ) from None
                yield _columns_to_events(t, x, y, p, t_offset), start

        yield from _checked(
            path, pieces(), EventChecker(width, height), n_total, path.stat().st_size
        )


def write_hdf5(path: Path, chunks: Iterable[np.ndarray], *, width: int, height: int) -> int:
    """DSEC layout, t relative to the first event's time (``t_offset``), gzip-compressed."""
    h5py = _h5py()
    count = 0
    with h5py.File(path, "w") as f:
        group = f.create_group("events")
        group.attrs["width"], group.attrs["height"] = width, height
        cols = {
            k: group.create_dataset(
                k,
                shape=(0,),
                maxshape=(None,),
                dtype=dt,
                chunks=(1 << 16,),
                compression="gzip",
                shuffle=True,
            )
            for k, dt in (("t", "i8"), ("x", "u2"), ("y", "u2"), ("p", "u1"))
        }
        t_offset = None
        t_max = np.iinfo(np.int64).min
        ms_to_idx: list[np.ndarray] = []
        next_ms = 0
        for chunk in as_event_chunks(chunks):
            chunk = sorted_by_time(chunk)
            check_writable(chunk, format="HDF5", width=width, height=height, max_t=MAX_T)
            if not len(chunk):
                continue
            if t_offset is None:
                t_offset = int(chunk["t"][0])
            rel = chunk["t"] - t_offset
            for k, values in (
                ("t", rel),
                ("x", chunk["x"]),
                ("y", chunk["y"]),
                ("p", chunk["p"] > 0),
            ):
                cols[k].resize((count + len(chunk),))
                cols[k][count:] = values
            # ms_to_idx[ms]: first event at or after ms (over the running maximum of t).
            running = np.maximum.accumulate(np.maximum(rel, t_max))
            t_max = int(running[-1])
            last_ms = t_max // 1000
            if last_ms >= next_ms:
                ms = np.arange(next_ms, last_ms + 1) * 1000
                ms_to_idx.append(count + np.searchsorted(running, ms, side="left"))
                next_ms = last_ms + 1
            count += len(chunk)
        f["t_offset"] = np.int64(t_offset or 0)
        f["ms_to_idx"] = np.concatenate(ms_to_idx) if ms_to_idx else np.zeros(0, np.uint64)
    return count


def open_npz(path: Path) -> EventStream:
    arrays = _load_npz(path)
    missing = [k for k in "txyp" if k not in arrays]
    if missing:
        raise EventFileError(
            path, f"missing array {missing[0]!r}; expected t, x, y, p", where="in the npz"
        )
    t, x, y, p = (arrays[k] for k in "txyp")
    if not len(t) == len(x) == len(y) == len(p) or t.ndim != 1:
        raise EventFileError(
            path, "arrays t, x, y, p must be 1-D and of one length", where="in the npz"
        )
    if not all(a.dtype.kind in "iub" for a in (t, x, y, p)):
        raise EventFileError(path, "arrays t, x, y, p must be integers", where="in the npz")
    t_offset = _t_offset(path, arrays["t_offset"][()], "in the npz") if "t_offset" in arrays else 0
    width, height = sensor_size(
        path,
        *(arrays[k][()] if k in arrays else None for k in ("width", "height")),
        where="in the npz",
    )
    n = len(t)
    if (
        (x.min(initial=0) < 0)
        or (y.min(initial=0) < 0)
        or max(x.max(initial=0), y.max(initial=0)) >= 1 << 16
    ):
        raise EventFileError(path, "x or y outside 0..65535", where="in the npz")
    pieces = (
        (
            _columns_to_events(
                t[s : s + CHUNK_EVENTS],
                x[s : s + CHUNK_EVENTS],
                y[s : s + CHUNK_EVENTS],
                p[s : s + CHUNK_EVENTS],
                t_offset,
            ),
            s,
        )
        for s in range(0, n, CHUNK_EVENTS)
    )
    return EventStream(
        _checked(path, pieces, EventChecker(width, height), n, path.stat().st_size),
        path=path,
        format="npz",
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays an npz holds of ``NPZ_ARRAYS``. ``np.load`` would allocate whatever size an
    array's header claims and inflate whatever a member holds: here the members' sizes are
    checked against the file's first (``check_inflation``), and each array's against its
    member's."""
    with (
        foreign_errors(path, "not a readable npz file", where="in the npz"),
        zipfile.ZipFile(path) as archive,
    ):
        members = {
            info.filename.removesuffix(".npy"): info
            for info in archive.infolist()
            if info.filename.removesuffix(".npy") in NPZ_ARRAYS
        }
        decoded = sum(info.file_size for info in members.values())
        check_inflation(path, decoded, path.stat().st_size, where="in the npz")
        return {name: _npy_array(path, name, archive.read(info)) for name, info in members.items()}


def _npy_array(path: Path, name: str, data: bytes) -> np.ndarray:
    """One array of an npz from its member's bytes (numpy's own header parser, no copy)."""
    f = io.BytesIO(data)
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise EventFileError(
            path, f"array {name!r} is in npy format {version}, not 1.0 or 2.0", where="in the npz"
        )
    count = math.prod(shape)
    if dtype.hasobject or count * dtype.itemsize != len(data) - f.tell():
        raise EventFileError(
            path,
            f"array {name!r} holds {len(data) - f.tell()} bytes, not the {count} of {dtype} "
            "its header says",
            where="in the npz",
        )
    return np.frombuffer(data, dtype, count, f.tell()).reshape(shape, order="F" if fortran else "C")


def write_npz(path: Path, chunks: Iterable[np.ndarray], *, width: int, height: int) -> int:
    events = concat(as_event_chunks(chunks))
    events = sorted_by_time(events)
    check_writable(events, format="npz", width=width, height=height, max_t=MAX_T)
    t_offset = int(events["t"][0]) if len(events) else 0
    with path.open("wb") as f:  # a file object, so numpy does not append ".npz"
        np.savez_compressed(
            f,
            t=events["t"] - t_offset,
            x=events["x"],
            y=events["y"],
            p=(events["p"] > 0).astype(np.uint8),
            t_offset=np.int64(t_offset),
            width=np.int64(width),
            height=np.int64(height),
        )
    return len(events)
