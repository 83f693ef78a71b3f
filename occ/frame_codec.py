"""One framed (robust/fast) data frame: header + fountain symbol + CRC, Reed-Solomon coded,
interleaved and whitened onto the N x N payload cells, and back.

The frame's ``N * N // 8`` whole bytes are split into ``ceil(bytes / 255)`` equal RS codewords
(the few bytes and cells left over carry only the whitening). Each codeword spends
``profile.parity_fraction`` of its bytes on parity (an even count, at least 2).
"""

from __future__ import annotations

import math

import numpy as np

from occ.fec import MAX_CODEWORD, ReedSolomon
from occ.fountain import symbol_size_for
from occ.framing import (
    FrameHeader,
    FramingError,
    byte_min,
    bytes_to_cells,
    cells_to_bytes,
    deinterleave,
    interleave,
    seal,
    unseal,
    whitening_mask,
)
from occ.profiles import LinkProfile

OVERHEAD = FrameHeader.SIZE + FrameHeader.CRC_SIZE


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
        self.symbol_size = symbol_size_for(capacity)
        self.rs = ReedSolomon(n, n - nsym)
        self.mask = whitening_mask(cells)
        self.coded_bytes = self.codewords * n

    def encode(self, header: FrameHeader, symbol: bytes) -> np.ndarray:
        """(cells, cells) uint8 bits of one data frame."""
        if len(symbol) != self.symbol_size:
            raise ValueError(f"symbol must be {self.symbol_size} bytes, got {len(symbol)}")
        sealed = seal(header, symbol).ljust(self.codewords * self.rs.k, b"\0")
        data = np.frombuffer(sealed, dtype=np.uint8)
        coded = interleave(self.rs.encode(data.reshape(self.codewords, self.rs.k)))
        return bytes_to_cells(coded, self.cells) ^ self.mask

    def decode(
        self, bits: np.ndarray, confidence: np.ndarray | None = None
    ) -> tuple[FrameHeader, bytes] | None:
        """Header and symbol of a frame read from the cells, or None if it cannot be trusted."""
        coded = cells_to_bytes(np.asarray(bits, dtype=np.uint8) ^ self.mask, self.coded_bytes)
        erasures = None
        if confidence is not None:
            low = byte_min(confidence, self.coded_bytes) < self.profile.erasure_below
            erasures = deinterleave(low, self.codewords)
        data, ok = self.rs.decode(deinterleave(coded, self.codewords), erasures)
        if not ok.all():
            return None
        try:
            return unseal(data.tobytes()[: OVERHEAD + self.symbol_size])
        except FramingError:
            return None
