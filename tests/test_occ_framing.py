"""Cell order, header bytes, CRC, interleaving."""

from __future__ import annotations

import numpy as np
import pytest

from eventocc.occ.framing import (
    FrameHeader,
    FramingError,
    bytes_to_cells,
    cells_to_bytes,
    deinterleave,
    interleave,
    seal,
    unseal,
)


def test_cells_are_row_major_msb_first() -> None:
    cells = bytes_to_cells(b"\x80\x01", 4)
    assert cells.tolist() == [[1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]
    assert cells_to_bytes(cells, 2).tobytes() == b"\x80\x01"


def test_too_many_bytes_for_a_frame() -> None:
    with pytest.raises(ValueError, match="do not fit a 4x4 frame"):
        bytes_to_cells(b"abc", 4)


def test_header_bytes_both_ways() -> None:
    header = FrameHeader(stream_id=0x1234, block=0x010203, block_symbols=700, esi=0x0506)
    packed = bytes.fromhex("20 1234 010203 02bc 0506")
    assert header.pack() == packed
    assert FrameHeader.unpack(packed) == header


def test_header_of_another_version_is_refused() -> None:
    # Version 1 put the CRC right after an unpacked frame's aligned symbol.
    with pytest.raises(FramingError, match="version 1"):
        FrameHeader.unpack(bytes.fromhex("10 1234 010203 02bc 0506"))


def test_seal_detects_any_single_bit_flip() -> None:
    header = FrameHeader(7, 0, 3, 1)
    sealed = seal(header, b"symbol")
    assert unseal(sealed) == (header, b"symbol")
    for bit in range(8 * len(sealed)):
        flipped = bytearray(sealed)
        flipped[bit // 8] ^= 0x80 >> bit % 8
        with pytest.raises(FramingError):
            unseal(bytes(flipped))


def test_interleave_spreads_adjacent_bytes_over_codewords() -> None:
    words = np.arange(12, dtype=np.uint8).reshape(3, 4)
    frame = interleave(words)
    assert frame[:3].tolist() == [0, 4, 8]  # three adjacent frame bytes, three codewords
    np.testing.assert_array_equal(deinterleave(frame, 3), words)
