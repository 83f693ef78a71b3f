"""One framed (robust/fast) data frame: header + fountain symbol(s) + CRC, Reed-Solomon coded,
interleaved and whitened onto the N x N payload cells, and back.

The CRC follows the whole room the codewords leave after the header (``FrameCodec.room``):
an unpacked frame's symbol, RaptorQ-aligned, leaves a few zero bytes before it; a packed
frame's symbols fill it (``eventocc.occ.packing``).

The frame's ``N * N // 8`` whole bytes are split into ``ceil(bytes / 255)`` equal RS codewords
(the few bytes and cells left over carry only the whitening). Each codeword spends
``profile.parity_fraction`` of its bytes on parity (an even count, at least 2).

Whitening is two XORs. Before the Reed-Solomon code, everything but the CRC is XORed with bytes
keyed by the CRC (``framing.keyed_whitening``), so no field repeats from frame to frame; the
receiver reads the CRC after correcting the codewords and undoes it. Then all cells are XORed
with a fixed mask, which balances black and white cells in the CRC too.
"""

from __future__ import annotations

import math

import numpy as np

from eventocc.occ.fec import MAX_CODEWORD, ReedSolomon
from eventocc.occ.fountain import symbol_size_for
from eventocc.occ.framing import (
    FrameHeader,
    FramingError,
    byte_min,
    bytes_to_cells,
    cells_to_bytes,
    deinterleave,
    interleave,
    keyed_whitening,
    seal,
    unseal,
    whitening_mask,
)
from eventocc.occ.packing import FLAG_PACKED
from eventocc.occ.profiles import LinkProfile

OVERHEAD = FrameHeader.SIZE + FrameHeader.CRC_SIZE
ERASURE_MARGIN = 2
"""Parity bytes a ranked retry keeps back for detection (``FrameCodec._erase_unsure``)."""


class FrameCodec:
    def __init__(self, profile: LinkProfile, cells: int) -> None:
        self.profile, self.cells = profile, cells
        frame_bytes = cells * cells // 8
        self.codewords = max(1, math.ceil(frame_bytes / MAX_CODEWORD))
        n = frame_bytes // self.codewords
        nsym = max(2, 2 * round(profile.parity_fraction * n / 2))
        capacity = self.codewords * (n - nsym) - OVERHEAD
        if capacity < 1:
            raise ValueError(
                f"a {cells}x{cells} payload is too small for the {profile.name} profile's "
                f"header and parity; use more cells"
            )
        self.room = capacity
        """Bytes between header and CRC: a packed frame's symbols fill them
        (``eventocc.occ.packing``), an unpacked frame's one symbol and zero padding."""
        self.symbol_size = symbol_size_for(capacity)
        """An unpacked frame's fountain symbol: the room as RaptorQ aligns it."""
        self.rs = ReedSolomon(n, n - nsym)
        self.mask = whitening_mask(cells)
        self.coded_bytes = self.codewords * n
        self.frame_bytes = frame_bytes
        sealed = OVERHEAD + self.room
        self._crc = slice(sealed - FrameHeader.CRC_SIZE, sealed)
        self.corrected: np.ndarray | None = None
        """(cells, cells) bool: the cells whose bits the last ``decode`` corrected; None if
        it returned None."""

    def _keyed(self, key: bytes) -> np.ndarray:
        """The keyed whitening of a frame's data bytes, then of its left-over bytes; zero on the
        CRC."""
        left_over = self.frame_bytes - self.coded_bytes
        mask = keyed_whitening(key, self.codewords * self.rs.k + left_over)
        mask[self._crc] = 0
        return mask

    def encode(self, header: FrameHeader, symbol: bytes) -> np.ndarray:
        """(cells, cells) uint8 bits of one data frame: ``symbol_size`` bytes of one symbol, or,
        with ``FLAG_PACKED`` in the header, ``room`` bytes of packed symbols."""
        size = self.room if header.flags & FLAG_PACKED else self.symbol_size
        if len(symbol) != size:
            raise ValueError(f"symbol must be {size} bytes, got {len(symbol)}")
        sealed = seal(header, symbol.ljust(self.room, b"\0"))
        size = self.codewords * self.rs.k
        mask = self._keyed(sealed[self._crc])
        data = np.frombuffer(sealed.ljust(size, b"\0"), dtype=np.uint8) ^ mask[:size]
        coded = interleave(self.rs.encode(data.reshape(self.codewords, self.rs.k)))
        return bytes_to_cells(np.concatenate([coded, mask[size:]]), self.cells) ^ self.mask

    def decode(
        self, bits: np.ndarray, confidence: np.ndarray | None = None
    ) -> tuple[FrameHeader, bytes] | None:
        """Header and symbol of a frame read from the cells, or None if it cannot be trusted;
        ``self.corrected`` then marks the cells the code corrected (None if it failed).

        Every codeword is first decoded from its bits alone. With ``confidence``, one that
        fails is decoded again with its bytes that have a cell below ``profile.erasure_below``
        erased, then with more of its least confident bytes erased
        (``profile.erasure_rounds``): generalised minimum-distance decoding. Erasing a byte
        pays only when it was wrong (``2 errors + erasures <= nsym``: a wrong byte erased
        saves one, a right one costs one), and a reader's unsure cells are often right, so
        erasures are only ever tried where the bits alone failed: a frame that decodes
        without confidences decodes the same with them."""
        self.corrected = None
        received = cells_to_bytes(np.asarray(bits, dtype=np.uint8) ^ self.mask, self.coded_bytes)
        coded = deinterleave(received, self.codewords)
        codewords, ok = self.rs.correct(coded)
        if not ok.all() and confidence is not None:
            sureness = deinterleave(byte_min(confidence, self.coded_bytes), self.codewords)
            codewords, ok = self._erase_unsure(coded, sureness, codewords, ok)
        if not ok.all():
            return None
        data = codewords[:, : self.rs.k].reshape(-1)
        data = data ^ self._keyed(data[self._crc].tobytes())[: data.size]
        try:
            header, body = unseal(data[: self._crc.stop].tobytes())
        except FramingError:
            return None
        self.corrected = self._corrected_cells(received, interleave(codewords))
        return header, body if header.flags & FLAG_PACKED else body[: self.symbol_size]

    def _corrected_cells(self, received: np.ndarray, corrected: np.ndarray) -> np.ndarray:
        """(cells, cells) bool: the cells of the coded bytes whose bit the code changed (the
        left-over cells carry no code: never corrected)."""
        flips = np.zeros(self.frame_bytes, dtype=np.uint8)
        flips[: self.coded_bytes] = received ^ corrected
        return bytes_to_cells(flips, self.cells).astype(bool)

    def _erase_unsure(
        self, coded: np.ndarray, sureness: np.ndarray, codewords: np.ndarray, ok: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Retry the failed codewords with erasures: first their bytes below
        ``profile.erasure_below``, then also their ``k`` least sure bytes, for ``k`` in even
        steps up to ``nsym - 2 * ERASURE_MARGIN``, giving whole corrected codewords as
        ``ReedSolomon.correct`` does. The ranked retries keep ``ERASURE_MARGIN`` parity bytes
        back for detection (``ReedSolomon.correct``), so a word the erasures push next to the
        wrong codeword is refused rather than "corrected"."""
        codewords, ok = codewords.copy(), ok.copy()
        erasures = sureness < self.profile.erasure_below
        rounds = self.profile.erasure_rounds
        most = self.rs.nsym - 2 * ERASURE_MARGIN
        tries = [(erasures, 0)]
        if rounds >= 1 and most >= 1:
            order = np.argsort(sureness, axis=1, kind="stable")
            rank = np.empty_like(order)
            np.put_along_axis(rank, order, np.arange(order.shape[1])[None, :], axis=1)
            tries += [
                (erasures | (rank < round(most * r / rounds)), ERASURE_MARGIN)
                for r in range(1, rounds + 1)
            ]
        for erase, margin in tries:
            failed = np.flatnonzero(~ok & erase.any(axis=1))
            if not len(failed):
                continue
            got, fixed = self.rs.correct(coded[failed], erase[failed], margin=margin)
            codewords[failed[fixed]] = got[fixed]
            ok[failed[fixed]] = True
        return codewords, ok
