"""The ``paper`` profile against the authors' generator, rebuilt cell by cell from its description
(ring layout, dashed locator, MSB-first row-major bits), not from the code under test."""

from __future__ import annotations

import numpy as np
import pytest
import reedsolo

from eventocc.occ.stream import StreamEncoder

PAPER_K = {16: 251, 32: 247, 48: 239, 64: 223, 80: 159, 96: 127}


def expected_marker(payload_bits: list[int] | None, n: int) -> np.ndarray:
    """The generator's frame with 1-cell rings: black, white, black, then the inner locator
    (only with a payload) around the N x N payload; ``None`` is the blank frame."""
    side = n + 8
    m = np.zeros((side, side), dtype=bool)
    for r in range(side):
        for c in range(side):
            if min(r, c, side - 1 - r, side - 1 - c) == 1:
                m[r, c] = True  # the white ring B
    if payload_bits is None:
        return m
    top, left = 3, 3  # inner locator's top-left cell
    last = n + 1
    for i in range(n + 2):
        m[top, left + i] = i % 2 == 0 or i == last  # dashed top row, corner white
        m[top + i, left + last] = i in (0, 1) or i % 2 == 1  # dashed right column
        m[top + i, left] = True  # solid left column
        m[top + last, left + i] = True  # solid bottom row
    for i, bit in enumerate(payload_bits):
        m[4 + i // n, 4 + i % n] = bool(bit)
    return m


def msb_first_bits(data: bytes) -> list[int]:
    return [(byte >> (7 - b)) & 1 for byte in data for b in range(8)]


def paper_coded(message: bytes, n: int) -> bytes:
    """The message RS-coded per the paper's footnote, by reedsolo's own codec."""
    k = PAPER_K[n]
    rs = reedsolo.RSCodec(255 - k)
    return b"".join(bytes(rs.encode(message[i : i + k])) for i in range(0, len(message), k))


@pytest.mark.parametrize("n", [16, 32])
def test_paper_frames_match_the_generator_layout(n: int) -> None:
    message = bytes(np.random.default_rng(n).integers(0, 256, 700, dtype=np.uint8))
    enc = StreamEncoder(message, profile="paper", cells=n, ring=1, preamble=True)
    bits = msb_first_bits(paper_coded(message, n))
    per_frame = n * n
    frames = -(-len(bits) // per_frame)
    bits += [0] * (frames * per_frame - len(bits))  # zero padding, no extra frame
    assert enc.cycle == 2 * frames

    blank = expected_marker(None, n)
    white = expected_marker([1] * per_frame, n)
    for k in (0, 179):
        np.testing.assert_array_equal(enc.frame(k), blank)
    for k in (180, 358):
        np.testing.assert_array_equal(enc.frame(k), white)
        np.testing.assert_array_equal(enc.frame(k + 1), blank)
    for j in range(frames):
        k = 360 + 2 * j
        expected = expected_marker(bits[j * per_frame : (j + 1) * per_frame], n)
        np.testing.assert_array_equal(enc.frame(k), expected)
        np.testing.assert_array_equal(enc.frame(k + 1), blank)
        np.testing.assert_array_equal(enc.frame(k + enc.cycle), expected)  # it loops
        assert enc.is_data_frame(k) and not enc.is_data_frame(k + 1)


def test_exact_multiple_gets_no_extra_frame() -> None:
    message = bytes(532)  # 3 codewords: 532 + 3 * 4 parity = 544 bytes = exactly 17 frames
    assert len(paper_coded(message, 16)) == 17 * 32
    assert StreamEncoder(message, profile="paper", cells=16).cycle == 2 * 17


def test_marker_without_preamble_starts_with_data() -> None:
    enc = StreamEncoder(b"\x80", profile="paper", cells=16, ring=1)
    frame = enc.frame(0)
    assert frame[4, 4] and not frame[4, 5]  # MSB first: 0x80 lights only the first cell
    assert enc.is_data_frame(0) and not enc.is_data_frame(1)
