"""Bits on cells: byte <-> cell order, the frame header, interleaving and whitening.

Cell order everywhere is the paper's: row-major from the top-left payload cell, each byte MSB
first, 1 = white.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass

import numpy as np

HEADER_VERSION = 2
"""2: the CRC follows the frame's whole room (``FrameCodec.room``) and packed symbols are of
``eventocc.occ.packing.SYMBOL_SIZE`` bytes; a version-1 frame does not decode."""


class FramingError(ValueError):
    """A frame's header is malformed, of another version, or fails its CRC."""


def bytes_to_cells(data: bytes | np.ndarray, cells: int) -> np.ndarray:
    """Bytes -> (cells, cells) uint8 bits, row-major, MSB first; cells beyond the data are 0."""
    bits = np.unpackbits(np.frombuffer(bytes(data), dtype=np.uint8))
    if bits.size > cells * cells:
        raise ValueError(f"{len(data)} bytes do not fit a {cells}x{cells} frame")
    out = np.zeros(cells * cells, dtype=np.uint8)
    out[: bits.size] = bits
    return out.reshape(cells, cells)


def cells_to_bytes(bits: np.ndarray, nbytes: int) -> np.ndarray:
    """The first ``nbytes`` bytes (uint8 array) read row-major, MSB first, from a bit matrix."""
    flat = np.asarray(bits, dtype=np.uint8).reshape(-1)
    return np.packbits(flat[: 8 * nbytes] != 0)


def byte_min(values: np.ndarray, nbytes: int) -> np.ndarray:
    """Per byte, the minimum over its 8 cells of a per-cell value (e.g. confidence)."""
    flat = np.asarray(values, dtype=float).reshape(-1)
    return flat[: 8 * nbytes].reshape(nbytes, 8).min(axis=1)


def interleave(codewords: np.ndarray) -> np.ndarray:
    """(c, n) codewords -> c*n frame bytes: frame byte p belongs to codeword p % c, so a burst of
    adjacent wrong cells is shared out over all codewords."""
    return np.ascontiguousarray(codewords.T).reshape(-1)


def deinterleave(frame_bytes: np.ndarray, count: int) -> np.ndarray:
    """Inverse of ``interleave``: frame bytes (or any per-byte array) -> (count, n)."""
    return np.ascontiguousarray(np.asarray(frame_bytes).reshape(-1, count).T)


def whitening_mask(cells: int) -> np.ndarray:
    """(cells, cells) fixed pseudo-random bits XORed onto framed payloads, so about half the cells
    are white whatever the data (the detector and the decoder's thresholds rely on that)."""
    rng = np.random.default_rng(0x0CC0 + cells)
    return rng.integers(0, 2, size=(cells, cells), dtype=np.uint8)


def keyed_whitening(key: bytes, nbytes: int) -> np.ndarray:
    """``nbytes`` pseudo-random bytes chosen by ``key`` (a frame's CRC). XORed onto everything
    but the key itself, they make fields that repeat from frame to frame (the header) look
    different in every frame: under ``fast``'s differential cells, a cell with the same bit in
    every frame would otherwise toggle on every refresh, in lockstep with the inner locator."""
    rng = np.random.default_rng(0x0CC1 << 16 | int.from_bytes(key, "big"))
    return rng.integers(0, 256, size=nbytes, dtype=np.uint8)


@dataclass(frozen=True)
class FrameHeader:
    """The header of a framed (robust/fast) data frame, followed by its fountain symbol (or,
    with ``FLAG_PACKED``, symbols: ``eventocc.occ.packing``) and a CRC-16/CCITT of header and
    symbols.

    Layout (big-endian): ``version u4 | flags u4 | stream_id u16 | block u24 | block_symbols u16
    | esi u16``, 10 bytes. ``block_symbols`` is the source-symbol count of this fountain block;
    ``esi`` the RaptorQ encoding symbol id within it (packed: the first symbol's).
    """

    stream_id: int
    block: int
    block_symbols: int
    esi: int
    flags: int = 0

    SIZE = 10
    CRC_SIZE = 2

    def pack(self) -> bytes:
        return struct.pack(
            ">BH3sHH",
            HEADER_VERSION << 4 | self.flags,
            self.stream_id,
            self.block.to_bytes(3, "big"),
            self.block_symbols,
            self.esi,
        )

    @classmethod
    def unpack(cls, data: bytes) -> FrameHeader:
        version_flags, stream_id, block, block_symbols, esi = struct.unpack(
            ">BH3sHH", data[: cls.SIZE]
        )
        if version_flags >> 4 != HEADER_VERSION:
            raise FramingError(f"header version {version_flags >> 4}, expected {HEADER_VERSION}")
        if block_symbols == 0:
            raise FramingError("header says the block has no source symbols")
        return cls(stream_id, int.from_bytes(block, "big"), block_symbols, esi, version_flags & 15)


def seal(header: FrameHeader, symbol: bytes) -> bytes:
    """Header + symbol + CRC: the data bytes of one framed data frame."""
    body = header.pack() + symbol
    return body + binascii.crc_hqx(body, 0xFFFF).to_bytes(FrameHeader.CRC_SIZE, "big")


def unseal(data: bytes) -> tuple[FrameHeader, bytes]:
    """Inverse of ``seal``; raises ``FramingError`` on a CRC mismatch or a bad header."""
    body, crc = data[: -FrameHeader.CRC_SIZE], data[-FrameHeader.CRC_SIZE :]
    if binascii.crc_hqx(body, 0xFFFF) != int.from_bytes(crc, "big"):
        raise FramingError("frame CRC mismatch")
    return FrameHeader.unpack(body), body[FrameHeader.SIZE :]
