"""Packed frames: one message's symbols across densities and profiles, progress kept."""

from __future__ import annotations

import numpy as np
import pytest

from eventocc.occ.frame_codec import FrameCodec
from eventocc.occ.packing import BLOCK_BYTES, SYMBOL_SIZE
from eventocc.occ.profiles import get_profile
from eventocc.occ.stream import StreamDecoder, StreamEncoder

MESSAGE = bytes(np.random.default_rng(7).integers(0, 256, 3000, dtype=np.uint8))


def data_frames(enc: StreamEncoder, refreshes: int) -> list[np.ndarray]:
    return [enc.payload_bits(k) for k in range(refreshes) if enc.is_data_frame(k)]


def frames_to_finish(dec: StreamDecoder, enc: StreamEncoder) -> int | None:
    """Data frames of ``enc`` pushed until ``dec`` returns the message (None: never)."""
    for i, bits in enumerate(data_frames(enc, enc.cycle)):
        if got := dec.push(bits):
            assert got[0].data == MESSAGE and got[0].verified
            return i + 1
    return None


@pytest.mark.parametrize(("profile", "cells"), [("robust", 16), ("robust", 40), ("fast", 64)])
def test_a_packed_stream_alone_decodes(profile: str, cells: int) -> None:
    enc = StreamEncoder(MESSAGE, name="m.bin", profile=profile, cells=cells, packed=True)
    assert frames_to_finish(StreamDecoder(profile=profile, cells=cells), enc) is not None


def test_packed_frames_carry_whole_symbols_of_one_size() -> None:
    for cells, per_frame in ((16, 2), (32, 14), (64, 62), (128, 254)):
        enc = StreamEncoder(MESSAGE, cells=cells, packed=True)
        assert enc.symbols_per_frame == per_frame
    dec = StreamDecoder(cells=64)
    dec.push(StreamEncoder(MESSAGE, cells=64, packed=True).payload_bits(0))
    assert dec.verified_bits == 8 * 62 * SYMBOL_SIZE


@pytest.mark.parametrize("cells", [16, 24, 32, 48, 64, 72, 80])
def test_a_packed_frame_fills_the_room_an_unpacked_one_leaves(cells: int) -> None:
    """The symbol size divides these densities' rooms: a packed frame carries all of it, an
    unpacked one its RaptorQ-aligned symbol (80 of N = 32's 84 bytes)."""
    room = FrameCodec(get_profile("robust"), cells).room
    carried = {}
    for packed in (False, True):
        dec = StreamDecoder(cells=cells)
        dec.push(StreamEncoder(MESSAGE, cells=cells, packed=packed).payload_bits(0))
        carried[packed] = dec.verified_bits // 8
    assert carried[True] == room >= carried[False]
    if cells == 32:
        assert carried == {False: 80, True: 84}


def test_progress_survives_density_and_profile_changes() -> None:
    """Half the symbols at N = 16 robust, then a receiver rebuilt for N = 48 fast that adopts
    the first one's progress: it finishes in about half the frames a fresh one needs."""
    first = StreamEncoder(MESSAGE, name="m.bin", cells=16, packed=True)
    dec16 = StreamDecoder(cells=16)
    needed = len(MESSAGE) // SYMBOL_SIZE
    shown = 0
    for k in range(first.cycle):
        if first.is_data_frame(k):
            dec16.push(first.payload_bits(k))
        shown = k + 1
        (held,) = [p["symbols_held"] for p in dec16.progress().values()]
        if held >= needed // 2:
            break
    second = StreamEncoder(
        MESSAGE,
        name="m.bin",
        profile="fast",
        cells=48,
        packed=True,
        symbol_start=first.symbol_end(shown),
    )
    adopted = StreamDecoder(profile="fast", cells=48)
    adopted.adopt(dec16)
    (progress,) = adopted.progress().values()
    assert progress["symbols_held"] >= needed // 2
    with_history = frames_to_finish(adopted, second)
    fresh = frames_to_finish(StreamDecoder(profile="fast", cells=48), second)
    assert with_history is not None and fresh is not None
    assert with_history <= 0.65 * fresh


def test_the_next_segment_sends_symbols_the_last_did_not() -> None:
    first = StreamEncoder(MESSAGE, cells=32, packed=True)
    second = StreamEncoder(MESSAGE, cells=24, packed=True, symbol_start=first.symbol_end(40))
    dec = StreamDecoder(cells=32)
    for bits in data_frames(first, 40):
        dec.push(bits)
    (before,) = [p["symbols_held"] for p in dec.progress().values()]
    later = StreamDecoder(cells=24)
    later.adopt(dec)
    for bits in data_frames(second, 10):
        later.push(bits)
    (after,) = [p["symbols_held"] for p in later.progress().values()]
    # Every symbol of the next segment is new: none repeats one already held.
    assert after - before == 5 * second.symbols_per_frame


def test_unpacked_progress_is_not_adopted_across_densities() -> None:
    enc = StreamEncoder(MESSAGE, cells=32)
    dec = StreamDecoder(cells=32)
    for bits in data_frames(enc, 20):
        dec.push(bits)
    assert dec.progress()
    later = StreamDecoder(cells=48)
    later.adopt(dec)
    assert later.progress() == {}


def test_a_delivered_message_stays_delivered_after_a_rebuild() -> None:
    enc = StreamEncoder(MESSAGE, cells=64, packed=True)
    dec = StreamDecoder(cells=64)
    assert frames_to_finish(dec, enc) is not None
    later = StreamDecoder(cells=32)
    later.adopt(dec)
    assert frames_to_finish(later, StreamEncoder(MESSAGE, cells=32, packed=True)) is None


def test_paper_cannot_be_packed() -> None:
    with pytest.raises(ValueError, match="no fountain symbols"):
        StreamEncoder(MESSAGE, profile="paper", cells=16, packed=True)
    with pytest.raises(ValueError, match="symbol_start"):
        StreamEncoder(MESSAGE, cells=16, packed=True, symbol_start=-1)


def test_packed_blocks_hold_as_many_bytes_as_an_unpacked_n16_streams() -> None:
    """Blocks of BLOCK_BYTES (12 kB): a 7 kB message is one block, a 13 kB one two, and the
    two-block message decodes from packed frames."""
    assert 1024 * FrameCodec(get_profile("robust"), 16).symbol_size == BLOCK_BYTES
    codec = FrameCodec(get_profile("robust"), 64)
    for size, blocks in ((7000, {0}), (13000, {0, 1})):
        message = bytes(np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8))
        enc = StreamEncoder(message, name="m.bin", cells=64, packed=True)
        frames = data_frames(enc, enc.cycle)
        seen = {codec.decode(bits)[0].block for bits in frames}
        assert seen == blocks
        dec = StreamDecoder(cells=64)
        got = next(r for bits in frames if (r := dec.push(bits)))
        assert got[0].data == message and got[0].verified
