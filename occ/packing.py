"""Packed frames: one message's fountain symbols the same whatever the marker's density.

A framed data frame normally carries one fountain symbol as large as its payload allows, so the
symbol size, and with it every RaptorQ block of the message, depends on the cell count: symbols
received at N = 16 are of no use to a decoder of the same message at N = 32. A link that changes
its density while a message is under way (the transmitter's ``auto`` mode) would lose every
symbol collected before each change.

A packed frame instead carries ``symbols_per_frame(N)`` symbols of a fixed ``SYMBOL_SIZE``, the
symbol of the smallest framed frame (N = 16), with consecutive esis of one block: the header
names the first (``FrameHeader.flags`` has ``FLAG_PACKED``), the rest follow. Every density and
both framed profiles then send symbols of one and the same RaptorQ code, which a receiver keeps
collecting across changes. What it costs: the bytes a frame's payload holds beyond a whole
number of symbols (3% at N = 32, under 1% from N = 64), and more, smaller symbols per block.
"""

from __future__ import annotations

SYMBOL_SIZE = 12
"""Bytes per packed symbol: a 16 x 16 frame's whole room for a symbol (``FrameCodec``)."""
FLAG_PACKED = 0x1
"""``FrameHeader.flags`` bit: the frame carries packed symbols."""


def symbols_per_frame(room: int) -> int:
    """Packed symbols in a frame with ``room`` bytes for its symbol (``FrameCodec.symbol_size``)."""
    return room // SYMBOL_SIZE
