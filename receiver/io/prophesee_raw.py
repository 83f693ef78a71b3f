"""Prophesee RAW files: EVT 2.0, EVT 2.1 and EVT 3.0 decoding, EVT 2.0 and EVT 3.0 encoding.

The word layouts are Prophesee's (OpenEB ``evt2/evt21/evt3`` event types). Decoding runs in
numba over fixed-size blocks of the file; the decoder state (time base, row, vector base) is
carried from block to block, so memory stays bounded whatever the file size.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from eventocc.receiver.events import EVENT_DTYPE
from eventocc.receiver.io.errors import EventFileError
from eventocc.receiver.io.prophesee_header import (
    format_fields,
    header_geometry,
    read_header,
    write_header,
)
from eventocc.receiver.io.stream import (
    BLOCK_BYTES,
    MAX_TIME_REVERSAL_US,
    EventStream,
    Progressed,
    as_event_chunks,
    check_writable,
    read_blocks,
    sensor_size,
    sorted_by_time,
)

log = logging.getLogger(__name__)

COORD_LIMIT = 1 << 11  # x and y are 11-bit fields in every EVT encoding
CHUNK_EVENTS = 1 << 20  # events per decoded chunk (bounded memory)
EVT2_MAX_T = (1 << 34) - 1  # TIME_HIGH carries t[33:6]
# EVT3 holds 24 bits of time and counts wraps from the file start, so the writer pads TIME_HIGH
# from t = 0 (8 kB per 16.8 s); this cap (EVT2's range) keeps that padding under 8 MB.
EVT3_MAX_T = EVT2_MAX_T

# Decoder state slots (one int64 array carried across blocks).
T_MAX, TIME_HIGH, TIME_LOW, LOOPS, ROW, BASE_X, VECT_P, MONOTONIC = range(8)
# Decoder outcome codes and what they mean.
OK, NO_TIME, NO_ROW, NO_BASE, UNKNOWN_WORD, OUTSIDE, BACKWARDS = range(7)
PROBLEMS = {
    NO_TIME: "CD event before any TIME_HIGH word (corrupt, or not this encoding)",
    NO_ROW: "EVT3 ADDR_X before any ADDR_Y word (corrupt, or not EVT3)",
    NO_BASE: "EVT3 vector before any VECT_BASE_X word (corrupt, or not EVT3)",
    UNKNOWN_WORD: "word of a type this encoding does not define (corrupt, or wrong encoding)",
    OUTSIDE: "event outside the sensor geometry given in the header",
    BACKWARDS: f"TIME_HIGH goes back by more than {MAX_TIME_REVERSAL_US} us (corrupt)",
}


def new_decoder_state(monotonic: bool = False) -> np.ndarray:
    state = np.full(8, -1, dtype=np.int64)
    state[T_MAX] = np.iinfo(np.int64).min + MAX_TIME_REVERSAL_US
    state[TIME_LOW] = state[LOOPS] = state[VECT_P] = 0
    state[MONOTONIC] = monotonic
    return state


@njit(inline="always")
def _push(out, n, t, x, y, p, sensor):
    """Store one event as ``out[n]`` if it lies on the ``sensor`` = (width, height); returns an
    outcome code."""
    if x >= sensor[0] or y >= sensor[1]:
        return OUTSIDE
    e = out[n]
    e.t = t
    e.x = x
    e.y = y
    e.p = 1 if p else -1
    return OK


@njit(inline="always")
def _advance_time(t, t_max):
    """Check a new time base against the latest one; returns (outcome, new latest)."""
    if t < t_max - MAX_TIME_REVERSAL_US:
        return BACKWARDS, t_max
    return OK, max(t, t_max)


@njit(cache=True, nogil=True)
def _decode_evt3(words, state, out, sensor):
    """Decode EVT 3.0 words until the output is nearly full; returns (events, words, outcome).

    The state lives in locals inside the loop (numba keeps them in registers) and goes back
    to ``state`` at the end, for the next block.
    """
    t_max, high, low, loops = state[T_MAX], state[TIME_HIGH], state[TIME_LOW], state[LOOPS]
    row, base, vect_p = state[ROW], state[BASE_X], state[VECT_P]
    monotonic = state[MONOTONIC] != 0
    t = (loops << 24) | (high << 12) | low
    n = 0
    err = OK
    i = 0
    room = len(out) - 12
    while i < len(words) and n <= room:
        w = np.int64(words[i])
        kind = w >> 12
        if kind == 0x2:  # EVT_ADDR_X: one event
            if high < 0:
                err = NO_TIME
            elif row < 0:
                err = NO_ROW
            else:
                err = _push(out, n, t, w & 0x7FF, row, (w >> 11) & 1, sensor)
                n += err == OK
        elif kind == 0x0:  # EVT_ADDR_Y
            row = w & 0x7FF
        elif kind == 0x6:  # EVT_TIME_LOW; a decrease is sensor reordering, not a wrap
            low = w & 0xFFF
            t_low = (loops << 24) | (high << 12) | low
            t = max(t, t_low) if monotonic else t_low
        elif kind == 0x8:  # EVT_TIME_HIGH; a drop of half the range or more is a 24-bit wrap
            new_high = w & 0xFFF
            if high >= new_high + 2048:
                loops += 1
            high = new_high
            low = 0
            t_high = (loops << 24) | (high << 12)
            err, t_max = _advance_time(t_high, t_max)
            t = max(t, t_high) if monotonic else t_high
        elif kind == 0x3:  # VECT_BASE_X
            base = w & 0x7FF
            vect_p = (w >> 11) & 1
        elif kind == 0x4 or kind == 0x5:  # VECT_12 / VECT_8
            bits = 12 if kind == 0x4 else 8
            if high < 0:
                err = NO_TIME
            elif row < 0:
                err = NO_ROW
            elif base < 0:
                err = NO_BASE
            else:
                for j in range(bits):
                    if (w >> j) & 1:
                        err = _push(out, n, t, base + j, row, vect_p, sensor)
                        if err != OK:
                            break
                        n += 1
                base += bits
        elif kind == 0x1 or kind == 0x9 or kind == 0xB or kind == 0xC:
            err = UNKNOWN_WORD
        # 0x7 CONTINUED_4, 0xA EXT_TRIGGER, 0xD IMU, 0xE OTHERS, 0xF CONTINUED_12: not CD events
        if err != OK:
            break
        i += 1
    state[T_MAX], state[TIME_HIGH], state[TIME_LOW], state[LOOPS] = t_max, high, low, loops
    state[ROW], state[BASE_X], state[VECT_P] = row, base, vect_p
    return n, i, err


@njit(cache=True, nogil=True)
def _decode_evt2(words, state, out, sensor):
    """Decode EVT 2.0 words (see ``_decode_evt3`` for the contract)."""
    t_max, high = state[T_MAX], state[TIME_HIGH]
    n = 0
    err = OK
    i = 0
    room = len(out) - 1
    while i < len(words) and n <= room:
        w = np.int64(words[i])
        kind = w >> 28
        if kind <= 0x1:  # CD_OFF / CD_ON
            if high < 0:
                err = NO_TIME
            else:
                err = _push(
                    out,
                    n,
                    (high << 6) | ((w >> 22) & 0x3F),
                    (w >> 11) & 0x7FF,
                    w & 0x7FF,
                    kind,
                    sensor,
                )
                n += err == OK
        elif kind == 0x8:  # EVT_TIME_HIGH: t[33:6]
            high = w & 0x0FFFFFFF
            err, t_max = _advance_time(high << 6, t_max)
        elif kind != 0xA and kind < 0xD:  # EXT_TRIGGER, IMU, OTHERS, CONTINUED are skipped
            err = UNKNOWN_WORD
        if err != OK:
            break
        i += 1
    state[T_MAX], state[TIME_HIGH] = t_max, high
    return n, i, err


@njit(cache=True, nogil=True)
def _decode_evt21(words, state, out, sensor):
    """Decode EVT 2.1 words, each a logical u64 (see ``_decode_evt3`` for the contract)."""
    t_max, high = state[T_MAX], state[TIME_HIGH]
    n = 0
    err = OK
    i = 0
    room = len(out) - 32
    while i < len(words) and n <= room:
        w = np.int64(words[i])
        kind = (w >> 60) & 0xF
        if kind <= 0x1:  # EVT_NEG / EVT_POS: up to 32 events in a row, one per mask bit
            if high < 0:
                err = NO_TIME
            else:
                t = (high << 6) | ((w >> 54) & 0x3F)
                x = (w >> 43) & 0x7FF
                y = (w >> 32) & 0x7FF
                for j in range(32):
                    if (w >> j) & 1:
                        err = _push(out, n, t, x + j, y, kind, sensor)
                        if err != OK:
                            break
                        n += 1
        elif kind == 0x8:
            high = (w >> 32) & 0x0FFFFFFF
            err, t_max = _advance_time(high << 6, t_max)
        elif kind != 0xA and kind < 0xD:
            err = UNKNOWN_WORD
        if err != OK:
            break
        i += 1
    state[T_MAX], state[TIME_HIGH] = t_max, high
    return n, i, err


def _evt21_legacy_words(block: bytes) -> np.ndarray:
    # IMX636 "legacy" order stores the type/time/x/y half first: swap the u32 halves.
    return np.frombuffer(block, "<u4").reshape(-1, 2)[:, ::-1].copy().view("<i8").ravel()


@dataclass(frozen=True)
class Encoding:
    name: str
    word_bytes: int
    max_events_per_word: int
    words: Callable[[bytes], np.ndarray]
    decode: Callable


ENCODINGS = {
    "evt2": Encoding("evt2", 4, 1, lambda b: np.frombuffer(b, "<u4"), _decode_evt2),
    "evt21": Encoding("evt21", 8, 32, lambda b: np.frombuffer(b, "<i8"), _decode_evt21),
    "evt21-legacy": Encoding("evt21-legacy", 8, 32, _evt21_legacy_words, _decode_evt21),
    "evt3": Encoding("evt3", 2, 12, lambda b: np.frombuffer(b, "<u2"), _decode_evt3),
}


def header_encoding(header: dict[str, str]) -> str | None:
    """Encoding named by a RAW header (``% format`` first, then legacy ``% evt``)."""
    fields = format_fields(header)
    name = fields["name"].replace(".", "")
    if name in ("EVT2", "EVT20"):
        return "evt2"
    if name == "EVT21":
        return "evt21-legacy" if fields.get("endianness") == "legacy" else "evt21"
    if name in ("EVT3", "EVT30"):
        return "evt3"
    return {"2.0": "evt2", "2.1": "evt21", "3.0": "evt3"}.get(header.get("evt", ""))


def open_raw(path: Path, encoding: str | None = None, *, monotonic: bool = False) -> EventStream:
    """Stream a RAW file; ``encoding`` overrides the header (needed for headerless files).

    EVT 3.0 sensors send TIME_LOW words that step back by a few microseconds; by default they
    are decoded literally, as OpenEB does. ``monotonic`` holds the EVT 3.0 clock at its latest
    value instead (the rule faery follows); other encodings ignore it (``read_events`` makes
    their timestamps monotonic after decoding)."""
    with path.open("rb") as f:
        header, payload = read_header(f)
    named = header_encoding(header)
    if encoding is None:
        if named is None:
            raise EventFileError(
                path,
                "no '% evt' or '% format' header line naming the EVT "
                "encoding; pass format='evt2', 'evt21' or 'evt3'",
                offset=0,
            )
        encoding = named
    elif named is not None and named != encoding:
        log.warning("%s: header says %s, reading as %s as asked", path, named, encoding)
    if encoding not in ENCODINGS:
        raise ValueError(f"unknown EVT encoding {encoding!r}; choose one of {sorted(ENCODINGS)}")
    width, height = sensor_size(
        path, *(header_geometry(header) or (None, None)), limit=COORD_LIMIT, where="in the header"
    )
    return EventStream(
        _decode_file(path, payload, ENCODINGS[encoding], width, height, monotonic),
        path=path,
        format=encoding,
        width=width,
        height=height,
        size=path.stat().st_size,
    )


def _decode_file(
    path: Path, payload: int, enc: Encoding, width: int | None, height: int | None, monotonic: bool
) -> Iterator[Progressed]:
    state = new_decoder_state(monotonic)
    limit_w, limit_h = width or COORD_LIMIT, height or COORD_LIMIT
    offset = payload
    with path.open("rb") as f:
        f.seek(payload)
        for block in read_blocks(f, enc.word_bytes, BLOCK_BYTES):
            whole = len(block) - len(block) % enc.word_bytes
            words = enc.words(block[:whole])
            done = 0
            while done < len(words):
                size = min(CHUNK_EVENTS, (len(words) - done) * enc.max_events_per_word)
                out = np.empty(size, EVENT_DTYPE)
                n, used, err = enc.decode(words[done:], state, out, (limit_w, limit_h))
                done += used
                position = offset + done * enc.word_bytes
                if n:  # copy a mostly empty buffer rather than keep it alive
                    yield (out[:n].copy() if n < size // 2 else out[:n]), position
                if err != OK:
                    raise EventFileError(path, PROBLEMS[err], offset=position)
            offset += whole
            if whole < len(block):
                raise EventFileError(
                    path,
                    f"file ends inside a {enc.word_bytes}-byte word (truncated)",
                    offset=offset,
                )


# ---------------------------------------------------------------------------- encoding

# Encoder state slots: last TIME_HIGH step written (t >> 12 or t >> 6), last t, last row.
E_STEP, E_T, E_ROW = range(3)


@njit(cache=True, nogil=True)
def _encode_evt3(t, x, y, p, state, out):
    """EVT 3.0 words for events (TIME_HIGH for every 4096 us step from t = 0, as a sensor
    does; TIME_LOW when t changes, ADDR_Y when the row changes, one ADDR_X per event).
    Stops when ``out`` is nearly full; returns (words, events consumed, failed)."""
    n = 0
    i = 0
    room = len(out) - 4
    while i < len(t) and n < room:
        step = t[i] >> 12
        cur = state[E_STEP]
        if cur < step:  # pad forward one step at a time (resumable when out fills up)
            cur += 1
            out[n] = 0x8000 | (cur & 0xFFF)
            n += 1
            state[E_STEP] = cur
            state[E_T] = -1
            continue
        if step < cur:  # a small step back: allowed within one 24-bit period
            if cur - step >= 2048 or (cur >> 12) != (step >> 12):
                return n, i, True
            out[n] = 0x8000 | (step & 0xFFF)
            n += 1
            state[E_STEP] = step
            state[E_T] = -1
        if t[i] != state[E_T]:
            out[n] = 0x6000 | (t[i] & 0xFFF)
            n += 1
            state[E_T] = t[i]
        if y[i] != state[E_ROW]:
            out[n] = y[i]
            n += 1
            state[E_ROW] = y[i]
        out[n] = 0x2000 | (np.int64(p[i] > 0) << 11) | x[i]
        n += 1
        i += 1
    return n, i, False


@njit(cache=True, nogil=True)
def _encode_evt2(t, x, y, p, state, out):
    """EVT 2.0 words: TIME_HIGH whenever t >> 6 changes, then one CD word per event."""
    n = 0
    for i in range(len(t)):
        step = t[i] >> 6
        if step != state[E_STEP]:
            out[n] = 0x80000000 | step
            n += 1
            state[E_STEP] = step
        out[n] = (np.int64(p[i] > 0) << 28) | ((t[i] & 0x3F) << 22) | (np.int64(x[i]) << 11) | y[i]
        n += 1
    return n


def _raw_header(evt: str, name: str, width: int, height: int) -> bytes:
    # Keys as OpenEB writes them (sorted), plus the legacy ones older readers need.
    return write_header(
        {
            "camera_integrator_name": "Prophesee",
            "evt": evt,
            "format": f"{name};height={height};width={width}",
            "geometry": f"{width}x{height}",
            "plugin_integrator_name": "Prophesee",
        },
        end=True,
    )


def write_evt3(path: Path, chunks: Iterable[np.ndarray], *, width: int, height: int) -> int:
    _check_geometry(width, height)
    state = np.array([-1, -1, -1], dtype=np.int64)
    out = np.empty(CHUNK_EVENTS * 3, dtype="<u2")
    count = 0
    with path.open("wb") as f:
        f.write(_raw_header("3.0", "EVT3", width, height))
        for chunk in as_event_chunks(chunks):
            chunk = sorted_by_time(chunk)
            check_writable(chunk, format="EVT3", width=width, height=height, max_t=EVT3_MAX_T)
            done = 0
            while done < len(chunk):
                rest = chunk[done:]
                n, used, failed = _encode_evt3(
                    rest["t"], rest["x"], rest["y"], rest["p"], state, out
                )
                f.write(out[:n].tobytes())
                done += used
                if failed:
                    raise ValueError(
                        f"EVT3 cannot go back in time from {state[E_STEP] << 12} us to "
                        f"{rest['t'][used]} us (more than 8 s, or across a 16.8 s wrap); "
                        "sort the events by time"
                    )
            count += len(chunk)
    return count


def write_evt2(path: Path, chunks: Iterable[np.ndarray], *, width: int, height: int) -> int:
    _check_geometry(width, height)
    state = np.array([-1, -1, -1], dtype=np.int64)
    count = 0
    with path.open("wb") as f:
        f.write(_raw_header("2.0", "EVT2", width, height))
        for chunk in as_event_chunks(chunks):
            chunk = sorted_by_time(chunk)
            check_writable(chunk, format="EVT2", width=width, height=height, max_t=EVT2_MAX_T)
            out = np.empty(2 * len(chunk), dtype="<u4")
            n = _encode_evt2(chunk["t"], chunk["x"], chunk["y"], chunk["p"], state, out)
            f.write(out[:n].tobytes())
            count += len(chunk)
    return count


def _check_geometry(width: int, height: int) -> None:
    if not (0 < width <= COORD_LIMIT and 0 < height <= COORD_LIMIT):
        raise ValueError(
            f"EVT formats hold sensors up to {COORD_LIMIT}x{COORD_LIMIT}, got {width}x{height}"
        )
