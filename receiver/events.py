"""The event array type shared by every reader, writer, simulator and pipeline stage.

Events are a numpy structured array: ``t`` int64 microseconds, ``x``/``y`` uint16 pixel
coordinates, ``p`` int8 polarity (+1 brighter, -1 darker). A chunk is sorted by ``t`` up to the
small reversals real sensors produce (about 10 us); consumers must tolerate them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

EVENT_DTYPE = np.dtype([("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8)])


def empty_events(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=EVENT_DTYPE)


def make_events(t, x, y, p) -> np.ndarray:
    """Build an event array from column arrays; polarity may be {0,1}, bool or {-1,+1}."""
    t = np.asarray(t)
    ev = np.empty(t.shape[0], dtype=EVENT_DTYPE)
    ev["t"] = t
    ev["x"] = x
    ev["y"] = y
    ev["p"] = np.where(np.asarray(p) > 0, 1, -1)
    return ev


def concat(chunks: Iterable[np.ndarray]) -> np.ndarray:
    chunks = list(chunks)
    return np.concatenate(chunks) if chunks else empty_events()


def rechunk_by_count(chunks: Iterable[np.ndarray], count: int) -> Iterator[np.ndarray]:
    """Re-cut a chunk stream into chunks of exactly ``count`` events (the last may be shorter)."""
    if count <= 0:
        raise ValueError(f"chunk count must be positive, got {count}")
    pending: list[np.ndarray] = []
    held = 0
    for chunk in chunks:
        pending.append(chunk)
        held += len(chunk)
        if held >= count:
            buf = np.concatenate(pending)
            cut = len(buf) - len(buf) % count
            for start in range(0, cut, count):
                yield buf[start : start + count]
            pending, held = [buf[cut:]], len(buf) - cut
    if held:
        yield np.concatenate(pending)


def rechunk_by_time(chunks: Iterable[np.ndarray], window_us: int) -> Iterator[np.ndarray]:
    """Re-cut a chunk stream into consecutive windows of ``window_us`` microseconds.

    Windows are aligned to multiples of ``window_us``; empty windows are skipped. Events that
    arrive slightly out of order across a window edge stay in the window they arrived in.
    """
    if window_us <= 0:
        raise ValueError(f"window must be positive, got {window_us} us")
    pending: list[np.ndarray] = []
    edge: int | None = None
    for chunk in chunks:
        if not len(chunk):
            continue
        # One contiguous copy of the times per chunk: searching the structured field would copy
        # what is left of it for every window.
        t, start = np.ascontiguousarray(chunk["t"]), 0
        if edge is None:
            edge = (int(t[0]) // window_us + 1) * window_us
        while True:
            cut = start + int(np.searchsorted(t[start:], edge, side="left"))
            if cut == len(t):
                pending.append(chunk[start:])
                break
            pending.append(chunk[start:cut])
            out = _joined(pending)
            if len(out):
                yield out
            pending, start = [], cut
            edge = (int(t[start]) // window_us + 1) * window_us
    if pending:
        out = _joined(pending)
        if len(out):
            yield out


def _joined(parts: list[np.ndarray]) -> np.ndarray:
    """The parts as one array: a lone part as it is, a view and no copy."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)
