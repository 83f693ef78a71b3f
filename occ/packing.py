"""Packed frames: one message's fountain symbols the same whatever the marker's density.

A framed data frame normally carries one fountain symbol as large as its payload allows, so the
symbol size, and with it every RaptorQ block of the message, depends on the cell count: symbols
received at N = 16 are of no use to a decoder of the same message at N = 32. A link that changes
its density while a message is under way (the transmitter's ``auto`` mode) would lose every
symbol collected before each change.

A packed frame instead carries ``symbols_per_frame(room)`` symbols of a fixed ``SYMBOL_SIZE``
in the whole room between its header and CRC (``FrameCodec.room``), with consecutive esis of
one block: the header names the first (``FrameHeader.flags`` has ``FLAG_PACKED``), the rest
follow. Every density and both framed profiles then send symbols of one and the same RaptorQ
code, which a receiver keeps collecting across changes.

The symbol size is chosen for the rooms of the densities the auto mode sends
(``link_policy.CELLS_LADDER``): it divides N = 16's 12 bytes, and 6 bytes divide the rooms of
N = 24, 32, 40, 48, 64, 72, 80 and 112 exactly, leaving 2 bytes at N = 20, 56 and 96 and 3 at
N = 128. A packed frame thus carries its whole room, where an unpacked one carries its room
less RaptorQ's alignment (80 of N = 32's 84 bytes). What it costs: more, smaller symbols per
frame, each one RaptorQ decoder call.

A packed stream's fountain blocks hold ``BLOCK_BYTES`` (``packed_profile``), as many source
symbols as make the blocks of an unpacked N = 16 stream: a frame carries symbols of one block
only, so one that starts near the end of its block's run skips the first positions of the next
block's, and a message cut into more, smaller blocks meets more such boundaries.
"""

from __future__ import annotations

from dataclasses import replace

from eventocc.occ.profiles import LinkProfile

SYMBOL_SIZE = 6
"""Bytes per packed symbol."""
BLOCK_BYTES = 12 * 1024
"""Source bytes per fountain block of a packed stream (1024 symbols of N = 16's 12 bytes)."""
FLAG_PACKED = 0x1
"""``FrameHeader.flags`` bit: the frame carries packed symbols."""


def symbols_per_frame(room: int) -> int:
    """Packed symbols in a frame with ``room`` bytes between header and CRC
    (``FrameCodec.room``)."""
    return room // SYMBOL_SIZE


def packed_profile(profile: LinkProfile) -> LinkProfile:
    """``profile`` with the fountain blocks of packed streams (``BLOCK_BYTES``)."""
    return replace(profile, block_symbols=BLOCK_BYTES // SYMBOL_SIZE)
