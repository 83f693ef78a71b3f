"""The ``paper`` profile's payloads: the message Reed-Solomon coded per the paper's footnote, then
raw bits, row-major, MSB first, 1 = white, zero-padded to whole frames.

The coded stream is the message cut into RS(255, k) codewords (the last one shortened to the
bytes left plus its parity), concatenated. Unlike the authors' generator, a stream that fills its
last frame exactly gets no extra all-zero frame; an empty message is one all-zero frame.

There is no header, so the decoder cannot tell one frame from another: it must be given the
message size (that fixes the layout) and fed the data frames *in order*, as the authors' receiver
is. Because the transmitter loops, a codeword that fails is decoded again from the next cycle.
Leading all-white frames (the blink preamble) are skipped until the first other frame arrives,
so a message whose first frame is all ones must be sent without a preamble.
"""

from __future__ import annotations

import math

import numpy as np

from occ.fec import paper_rs
from occ.framing import byte_min, bytes_to_cells, cells_to_bytes


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

    def codeword_span(self, i: int) -> tuple[int, int]:
        """Byte range [start, end) of codeword ``i`` in the coded stream."""
        start = i * self.rs.n
        return start, min(start + self.rs.n, self.coded_size)

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
    """Recovers a message of known ``size`` from its data frames pushed in order."""

    def __init__(self, size: int, cells: int, erasure_below: float) -> None:
        self.layout = PaperLayout(size, cells)
        self.erasure_below = erasure_below
        lay = self.layout
        self.coded = np.zeros(lay.frames * lay.frame_bytes, dtype=np.uint8)
        self.erased = np.zeros_like(self.coded, dtype=bool)
        self.data = bytearray(size)
        self.done = np.zeros(lay.codewords, dtype=bool)
        self.pushed = 0  # data frames pushed since the first non-preamble frame

    @property
    def complete(self) -> bool:
        return bool(self.done.all())

    def push(self, bits: np.ndarray, confidence: np.ndarray | None) -> None:
        lay = self.layout
        if self.pushed == 0 and np.all(bits) and lay.size:
            return  # still in the blink preamble
        j = self.pushed % lay.frames
        self.pushed += 1
        lo = j * lay.frame_bytes
        self.coded[lo : lo + lay.frame_bytes] = cells_to_bytes(bits, lay.frame_bytes)
        if confidence is not None:
            low = byte_min(confidence, lay.frame_bytes) < self.erasure_below
            self.erased[lo : lo + lay.frame_bytes] = low
        # Decode every pending codeword that ends inside this frame.
        for i in np.flatnonzero(~self.done):
            start, end = lay.codeword_span(i)
            if not lo <= end - 1 < lo + lay.frame_bytes:
                continue
            self._decode(i, start, end)

    def _decode(self, i: int, start: int, end: int) -> None:
        rs, pad = self.layout.rs, self.layout.rs.n - (end - start)
        word = np.concatenate([np.zeros(pad, np.uint8), self.coded[start:end]])
        erased = np.concatenate([np.zeros(pad, bool), self.erased[start:end]])
        data, ok = rs.decode(word, erased)
        if ok[0]:
            lo, hi = self.layout.data_span(i)
            self.data[lo:hi] = data[0, pad:].tobytes()
            self.done[i] = True
