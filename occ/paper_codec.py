"""The ``paper`` profile's payloads: the message Reed-Solomon coded per the paper's footnote, then
raw bits, row-major, MSB first, 1 = white, zero-padded to whole frames.

The coded stream is the message cut into RS(255, k) codewords (the last one shortened to the
bytes left plus its parity), concatenated. Unlike the authors' generator, a stream that fills its
last frame exactly gets no extra all-zero frame; an empty message is one all-zero frame.

There is no header, so the decoder cannot tell one frame from another: it must be given the
message size (that fixes the layout) and fed the data frames *in order*, as the authors' receiver
is, with none lost or repeated. It finds where the cycle starts from the blink preamble or, when
it joined later, by trying every rotation of one cycle of frames (``PaperDecoder``). Because
the transmitter loops, a codeword that fails is decoded again from the next cycle. All-white
frames count as preamble, so a message whose coded frames include an all-white one needs the
``robust`` profile.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from eventocc.occ.fec import paper_rs
from eventocc.occ.framing import byte_min, bytes_to_cells, cells_to_bytes

DETECTION_MARGIN = 2
"""Parity bytes the paper decoder keeps for detection. There is no CRC, and rs(255, 251) can
correct 2 errors: a word with 3 or more is then "corrected" to a wrong codeword about half the
time. Correcting one error less makes that ~1.5e-5, and the looping transmitter resends."""


PADDING_ONES_MAX = 0.1
"""Share of ones (bit errors) the zero padding may show under the right rotation."""


def _check_cells(cells: int) -> None:
    if cells % 4:
        raise ValueError(
            f"the paper profile needs cells to be a multiple of 4 (whole bytes per "
            f"frame, as the authors' decoder assumes), got {cells}"
        )


class PaperLayout:
    """Where the coded bytes of a message of ``size`` bytes sit, for payload side ``cells``."""

    def __init__(self, size: int, cells: int) -> None:
        _check_cells(cells)
        self.size, self.cells, self.rs = size, cells, paper_rs(cells)
        self.codewords = math.ceil(size / self.rs.k)
        self.coded_size = size + self.codewords * self.rs.nsym
        self.frame_bytes = cells * cells // 8
        self.frames = max(1, math.ceil(self.coded_size / self.frame_bytes))

    def data_span(self, i: int) -> tuple[int, int]:
        """Byte range of codeword ``i``'s data in the message."""
        return i * self.rs.k, min((i + 1) * self.rs.k, self.size)


class PaperEncoder:
    def __init__(self, message: bytes, cells: int) -> None:
        self.message = memoryview(message)
        self.layout = PaperLayout(len(message), cells)

    def _codeword(self, i: int) -> bytes:
        lo, hi = self.layout.data_span(i)
        data = np.frombuffer(self.message[lo:hi], dtype=np.uint8)
        # A shortened code is the full code with leading zeros that are never sent.
        padded = np.concatenate([np.zeros(self.layout.rs.k - data.size, np.uint8), data])
        return self.layout.rs.encode(padded)[0, self.layout.rs.k - data.size :].tobytes()

    def payload(self, j: int) -> np.ndarray:
        """(cells, cells) uint8 bits of data frame ``j`` (0 <= j < layout.frames)."""
        lay = self.layout
        lo, hi = j * lay.frame_bytes, min((j + 1) * lay.frame_bytes, lay.coded_size)
        first, last = lo // lay.rs.n, max(lo, hi - 1) // lay.rs.n
        coded = b"".join(self._codeword(i) for i in range(first, min(last + 1, lay.codewords)))
        start = first * lay.rs.n
        return bytes_to_cells(coded[lo - start : hi - start], lay.cells)


class PaperDecoder:
    """Recovers a message of known ``size`` from its data frames pushed in order.

    The decoder must learn which frame of the cycle it is looking at. After the blink preamble
    (all-white frames), the next frame is frame 0. A receiver that joined later holds one whole
    cycle of frames and tries every rotation: it accepts the one rotation under which the zero
    padding is (nearly) zero and every codeword decodes, and waits for the next cycle if none
    or several do (so it never guesses).
    """

    def __init__(self, size: int, cells: int, erasure_below: float) -> None:
        self.layout = lay = PaperLayout(size, cells)
        self.erasure_below = erasure_below
        self.coded = np.zeros(lay.frames * lay.frame_bytes, dtype=np.uint8)
        self.missing = np.ones_like(self.coded, dtype=bool)  # bytes not received yet
        self.unsure = np.zeros_like(self.missing)  # bytes read with low confidence
        self.data = bytearray(size)
        self.done = np.zeros(lay.codewords, dtype=bool)
        self.ends = np.minimum(np.arange(1, lay.codewords + 1) * lay.rs.n, lay.coded_size)
        """Byte just past each codeword in the coded stream."""
        self.next_index: int | None = None
        """Cycle index of the next frame pushed, once known."""
        self.in_preamble = False
        self.recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=lay.frames)
        self.pushed = 0

    @property
    def complete(self) -> bool:
        return bool(self.done.all())

    def push(self, bits: np.ndarray, confidence: np.ndarray | None) -> None:
        lay = self.layout
        self.pushed += 1
        frame = cells_to_bytes(bits, lay.frame_bytes)
        unsure = np.zeros(lay.frame_bytes, dtype=bool)
        if confidence is not None:
            unsure = byte_min(confidence, lay.frame_bytes) < self.erasure_below
        if self.next_index is None:
            self._find_phase(frame, unsure)
            return
        self._store(self.next_index, frame, unsure)
        self.next_index = (self.next_index + 1) % lay.frames

    def _find_phase(self, frame: np.ndarray, unsure: np.ndarray) -> None:
        lay = self.layout
        if lay.size and np.all(frame == 0xFF):
            self.in_preamble = True  # the blink preamble: data starts with the next other frame
            self.recent.clear()
            return
        if self.in_preamble:
            self.next_index = 1 % lay.frames
            self._store(0, frame, unsure)
            return
        self.recent.append((frame, unsure))
        if len(self.recent) < lay.frames or self.pushed % lay.frames:
            return  # search once per cycle of frames
        rotation = self._unique_rotation()
        if rotation is not None:
            for i, (held, held_unsure) in enumerate(self.recent):
                self._place((rotation + i) % lay.frames, held, held_unsure)
            self._decode_codewords(0, lay.codewords)
            self.next_index = rotation

    def _unique_rotation(self) -> int | None:
        """The cycle index of the oldest held frame, if exactly one choice decodes."""
        lay, rs = self.layout, self.layout.rs
        found = []
        for r in range(lay.frames):
            order = [self.recent[(c - r) % lay.frames] for c in range(lay.frames)]
            coded = np.concatenate([f for f, _ in order])
            padding = np.unpackbits(coded[lay.coded_size :])
            if padding.size and padding.mean() > PADDING_ONES_MAX:
                continue  # real padding is zeros (bar bit errors); another rotation's is data
            unsure = np.concatenate([e for _, e in order])
            missing = np.zeros_like(unsure)
            starts = np.arange(lay.codewords) * rs.n
            if all(
                self._correct(coded, missing, unsure, a, b) is not None
                for a, b in zip(starts, self.ends, strict=True)
            ):
                found.append(r)
                if len(found) > 1:
                    return None
        return found[0] if found else None

    def _place(self, index: int, frame: np.ndarray, unsure: np.ndarray) -> tuple[int, int]:
        """Put frame ``index`` of the cycle in place; returns its byte range."""
        lo, hi = index * self.layout.frame_bytes, (index + 1) * self.layout.frame_bytes
        self.coded[lo:hi], self.unsure[lo:hi] = frame, unsure
        self.missing[lo:hi] = False
        return lo, hi

    def _store(self, index: int, frame: np.ndarray, unsure: np.ndarray) -> None:
        """Place frame ``index`` and decode the codewords that end in it."""
        lo, hi = self._place(index, frame, unsure)
        self._decode_codewords(*np.searchsorted(self.ends, [lo + 1, hi + 1]))

    def _decode_codewords(self, first: int, stop: int) -> None:
        lay = self.layout
        for i in range(first, stop):
            if self.done[i]:
                continue
            data = self._correct(self.coded, self.missing, self.unsure, i * lay.rs.n, self.ends[i])
            if data is not None:
                a, b = lay.data_span(i)
                self.data[a:b] = data
                self.done[i] = True

    def _correct(
        self, coded: np.ndarray, missing: np.ndarray, unsure: np.ndarray, start: int, end: int
    ) -> bytes | None:
        """The data of the (possibly shortened) codeword at bytes [start, end), or None.

        Bytes not received are always erasures. Low-confidence bytes are erasures only while the
        parity can fill them: a codeword spans several frames, whose flags together often
        outnumber the paper's few parity bytes even when every bit is right, so then the bits
        alone decide (the authors' receiver has no confidences at all)."""
        rs = self.layout.rs
        pad = rs.n - (end - start)  # a shortened codeword is a full one with leading zeros
        word = np.concatenate([np.zeros(pad, np.uint8), coded[start:end]])
        attempts = [missing[start:end] | unsure[start:end]]
        if unsure[start:end].any():
            attempts.append(missing[start:end])
        for erased in attempts:
            data, ok = rs.decode(word, np.pad(erased, (pad, 0)), margin=DETECTION_MARGIN)
            if ok[0]:
                return data[0, pad:].tobytes()
        return None
