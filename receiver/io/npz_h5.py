"""Column files in the DSEC layout: ``events/{t,x,y,p}`` plus ``t_offset`` (us added to t).

HDF5 (``.h5``/``.hdf5``): DSEC's ``/events/t`` (relative us), ``/events/x``, ``/events/y``,
``/events/p`` (0/1), ``/t_offset`` and ``/ms_to_idx``; sensor size in attributes ``width`` and
``height`` of ``/events`` when known. Blosc/Zstd-compressed files (DSEC) need ``hdf5plugin``,
imported when installed. npz: the same columns as arrays ``t``, ``x``, ``y``, ``p``,
``t_offset``, ``width``, ``height``; npz cannot be streamed, so it suits small files.
"""

from __future__ import annotations

import contextlib
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from eventocc.receiver.events import EVENT_DTYPE, concat
from eventocc.receiver.io.errors import EventFileError, MissingExtraError
from eventocc.receiver.io.stream import (
    EventChecker,
    EventStream,
    Progressed,
    as_event_chunks,
    check_writable,
    sorted_by_time,
)

CHUNK_EVENTS = 1 << 20
# What numpy's npz loader raises for a damaged zip archive or member.
NPZ_ERRORS = (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error)
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


def _geometry(width, height) -> tuple[int | None, int | None]:
    if width is None or height is None:
        return None, None
    return int(width), int(height)


def open_hdf5(path: Path) -> EventStream:
    h5py = _h5py()
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise EventFileError(path, f"not a readable HDF5 file ({e})", offset=0) from None
    with f:
        if "events" not in f or not {"t", "x", "y", "p"} <= set(f["events"]):
            raise EventFileError(
                path,
                f"no /events/{{t,x,y,p}} datasets (DSEC layout); top-level keys: {sorted(f)}",
                where="in the HDF5 tree",
            )
        lengths = {len(f["events"][k]) for k in "txyp"}
        if len(lengths) != 1:
            raise EventFileError(
                path, f"/events columns differ in length: {lengths}", where="in /events"
            )
        attrs = f["events"].attrs
        width, height = _geometry(attrs.get("width"), attrs.get("height"))
        n_total = lengths.pop()
    return EventStream(
        _hdf5_chunks(path, width, height, n_total),
        path=path,
        format="hdf5",
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _hdf5_chunks(path: Path, width, height, n_total: int) -> Iterator[Progressed]:
    h5py = _h5py()
    with h5py.File(path, "r") as f:
        t_offset = int(f["t_offset"][()]) if "t_offset" in f else 0
        cols = [f["events"][k] for k in "txyp"]

        def pieces():
            for start in range(0, n_total, CHUNK_EVENTS):
                stop = min(start + CHUNK_EVENTS, n_total)
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
    try:
        data = np.load(path, allow_pickle=False)
    except NPZ_ERRORS as e:
        raise EventFileError(path, f"not a readable npz file ({e})", offset=0) from None
    with data:
        try:
            t, x, y, p = (data[k] for k in "txyp")
            t_offset = int(data["t_offset"]) if "t_offset" in data.files else 0
            width, height = _geometry(
                data["width"] if "width" in data.files else None,
                data["height"] if "height" in data.files else None,
            )
        except KeyError as e:
            raise EventFileError(
                path, f"missing array {e}; expected t, x, y, p", where="in the npz"
            ) from None
        except NPZ_ERRORS as e:
            raise EventFileError(path, f"corrupt npz member ({e})", where="in the npz") from None
    if not len(t) == len(x) == len(y) == len(p) or t.ndim != 1:
        raise EventFileError(
            path, "arrays t, x, y, p must be 1-D and of one length", where="in the npz"
        )
    if not all(np.issubdtype(a.dtype, np.integer) or a.dtype == bool for a in (t, x, y, p)):
        raise EventFileError(path, "arrays t, x, y, p must be integers", where="in the npz")
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
