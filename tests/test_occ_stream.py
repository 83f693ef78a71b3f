"""StreamEncoder -> channel -> StreamDecoder: messages come back byte-exact, or not at all."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eventocc.occ.frame_codec import FrameCodec
from eventocc.occ.framing import FrameHeader
from eventocc.occ.profiles import get_profile
from eventocc.occ.stream import StreamDecoder, StreamEncoder

FRAMED = ("robust", "fast")


def flip(bits: np.ndarray, rng: np.random.Generator, ber: float) -> np.ndarray:
    return bits ^ (rng.random(bits.shape) < ber).astype(np.uint8)


def noisy_channel(
    enc: StreamEncoder,
    start: int,
    rng: np.random.Generator,
    *,
    ber: float = 0.0,
    loss: float = 0.0,
    repeat: float = 0.0,
    window: int = 1,
):
    """Payload bits the receiver reads, from refresh ``start`` on: each data frame lost with
    probability ``loss``, repeated with ``repeat``, shuffled within ``window`` frames, with
    independent bit errors at rate ``ber``."""
    k, pending = start, []
    while True:
        if enc.is_data_frame(k) and rng.random() >= loss:
            bits = enc.payload_bits(k)
            pending += [bits] * (2 if rng.random() < repeat else 1)
        k += 1
        if len(pending) >= window:
            rng.shuffle(pending)
            for bits in pending:
                yield flip(bits, rng, ber)
            pending = []


def receive(dec: StreamDecoder, frames, limit: int) -> list:
    for _, bits in zip(range(limit), frames, strict=False):
        if got := dec.push(bits):
            return got
    return []


@settings(max_examples=25, deadline=None)
@given(
    profile=st.sampled_from(FRAMED),
    message=st.binary(max_size=3000),
    cells=st.sampled_from([16, 24, 32]),
    start=st.integers(0, 10**6),
    loss=st.floats(0, 0.3),
    repeat=st.floats(0, 0.2),
    ber=st.floats(0, 0.005),
    seed=st.integers(0, 2**32 - 1),
)
def test_framed_round_trip_from_any_start(
    profile: str,
    message: bytes,
    cells: int,
    start: int,
    loss: float,
    repeat: float,
    ber: float,
    seed: int,
) -> None:
    enc = StreamEncoder(message, name="m.bin", profile=profile, cells=cells)
    dec = StreamDecoder(profile=profile, cells=cells)
    frames = noisy_channel(
        enc, start, np.random.default_rng(seed), ber=ber, loss=loss, repeat=repeat, window=5
    )
    got = receive(dec, frames, limit=enc.symbols)
    assert len(got) == 1
    assert got[0].data == message
    assert got[0].name == "m.bin"
    assert got[0].sha256 == hashlib.sha256(message).hexdigest()
    assert got[0].stream_id == enc.stream_id
    assert dec.push(enc.payload_bits(next(k for k in range(9) if enc.is_data_frame(k)))) == []


@pytest.mark.parametrize("profile", FRAMED)
def test_verified_bits_count_every_checked_frame_delivered_or_not(profile: str) -> None:
    # The link's live throughput: it goes on after the looping message was delivered.
    enc = StreamEncoder(b"hello" * 40, profile=profile, cells=16)
    dec = StreamDecoder(profile=profile, cells=16)
    symbol_bits = 8 * FrameCodec(enc.profile, 16).symbol_size
    frames = noisy_channel(enc, 0, np.random.default_rng(1))
    assert receive(dec, frames, 200)
    after_delivery = dec.verified_bits
    assert after_delivery == symbol_bits * dec.frames_pushed
    garbage = np.random.default_rng(2).integers(0, 2, (16, 16), dtype=np.uint8)
    dec.push(garbage)  # fails its CRC: not counted
    for _ in range(3):
        assert dec.push(next(frames)) == []  # the same message: not delivered again
    assert dec.verified_bits == after_delivery + 3 * symbol_bits


@pytest.mark.parametrize("profile", FRAMED)
def test_clean_message_needs_about_k_plus_two_frames(profile: str) -> None:
    message = bytes(range(256)) * 8
    enc = StreamEncoder(message, profile=profile, cells=32)
    dec = StreamDecoder(profile=profile, cells=32)
    start = 3 * enc.cycle // 4 + 1  # deep inside the repair symbols
    frames = noisy_channel(enc, start, np.random.default_rng(0))
    k = dec_k = None
    for count, bits in enumerate(frames, 1):
        if dec.push(bits):
            break
        ((_, progress),) = dec.progress().items()
        dec_k = progress["symbols_needed"]
        k = count
    assert dec_k is not None and k is not None
    assert k + 1 <= dec_k + 2


def test_clustered_burst_is_spread_over_codewords() -> None:
    message = bytes(np.random.default_rng(3).integers(0, 256, 2000, dtype=np.uint8))
    enc = StreamEncoder(message, cells=64)
    dec = StreamDecoder(cells=64)
    got, k = [], 0
    while not got:
        if enc.is_data_frame(k):
            bits = enc.payload_bits(k)
            bits[20:30, 10:20] ^= 1  # 100 adjacent wrong cells in every frame
            got = dec.push(bits)
        k += 1
    assert got[0].data == message


@pytest.mark.parametrize("profile", FRAMED)
def test_multi_block_message(profile: str) -> None:
    message = np.random.default_rng(5).integers(0, 256, 64 * 1024, dtype=np.uint8).tobytes()
    enc = StreamEncoder(message, profile=profile, cells=16)
    assert enc._fountain.layout.blocks > 1
    dec = StreamDecoder(profile=profile, cells=16)
    frames = noisy_channel(enc, 12345, np.random.default_rng(1), ber=0.003, loss=0.1)
    got = receive(dec, frames, limit=enc.symbols)
    assert [m.data == message for m in got] == [True]


@pytest.mark.slow
@pytest.mark.parametrize("profile", FRAMED)
def test_one_megabyte(profile: str) -> None:
    message = np.random.default_rng(6).integers(0, 256, 1 << 20, dtype=np.uint8).tobytes()
    enc = StreamEncoder(message, profile=profile, cells=96)
    dec = StreamDecoder(profile=profile, cells=96)
    frames = noisy_channel(enc, 777, np.random.default_rng(2), ber=0.003, loss=0.1)
    got = receive(dec, frames, limit=enc.symbols)
    assert [m.data == message for m in got] == [True]


@settings(max_examples=10, deadline=None)
@given(profile=st.sampled_from(FRAMED), seed=st.integers(0, 2**32 - 1))
def test_garbage_and_heavy_noise_never_yield_wrong_bytes(profile: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    message = rng.integers(0, 256, 500, dtype=np.uint8).tobytes()
    enc = StreamEncoder(message, profile=profile, cells=16)
    dec = StreamDecoder(profile=profile, cells=16)
    for bits in noisy_channel(enc, int(rng.integers(0, 10**5)), rng, ber=0.04):
        if got := dec.push(bits if rng.random() < 0.8 else rng.integers(0, 2, (16, 16))):
            assert got[0].data == message
            break
        if dec.frames_pushed > 400:
            break


def test_erasures_from_low_confidence_cells() -> None:
    message = b"erasures are cheaper than errors" * 20
    enc = StreamEncoder(message, cells=32)
    dec = StreamDecoder(cells=32)
    rng = np.random.default_rng(4)
    got, k = [], 0
    while not got:
        if enc.is_data_frame(k):
            bits = enc.payload_bits(k)
            confidence = np.ones(bits.shape)
            dark = rng.random(bits.shape) < 0.02  # 2% of the cells unreadable, as garbage
            bits[dark] = rng.integers(0, 2, dark.sum())
            confidence[dark] = 0.0
            got = dec.push(bits, confidence)
        k += 1
    assert got[0].data == message
    assert k < 2 * 4 * enc.symbols // 8


@settings(max_examples=15, deadline=None)
@given(
    message=st.binary(max_size=2000),
    cells=st.sampled_from([16, 32, 48]),
    seed=st.integers(0, 2**32 - 1),
)
def test_paper_round_trip_in_order_with_bit_errors(message: bytes, cells: int, seed: int) -> None:
    enc = StreamEncoder(message, profile="paper", cells=cells, preamble=True)
    dec = StreamDecoder(profile="paper", cells=cells, message_size=len(message), name="p")
    rng = np.random.default_rng(seed)
    got = []
    for k in range(180, enc.preamble_length + 20 * enc.cycle, 2):  # every lit refresh
        bits = enc.geometry.payload_of(enc.frame(k)).astype(np.uint8)
        if got := dec.push(flip(bits, rng, 2e-4) if enc.is_data_frame(k) else bits):
            break
    assert [(m.data, m.name, m.profile) for m in got] == [(message, "p", "paper")]


@settings(max_examples=15, deadline=None)
@given(
    message=st.binary(max_size=2000),
    cells=st.sampled_from([16, 32]),
    start=st.integers(0, 10**5),
    seed=st.integers(0, 2**32 - 1),
)
def test_paper_joining_late_finds_the_cycle_start_or_waits(
    message: bytes, cells: int, start: int, seed: int
) -> None:
    enc = StreamEncoder(message, profile="paper", cells=cells)
    dec = StreamDecoder(profile="paper", cells=cells, message_size=len(message))
    frames = noisy_channel(enc, start, np.random.default_rng(seed), ber=2e-4)
    got = receive(dec, frames, limit=6 * enc.symbols)
    assert [m.data for m in got] in ([message], [])


def test_paper_joining_late_recovers_the_message() -> None:
    message = bytes(np.random.default_rng(8).integers(0, 256, 1000, dtype=np.uint8))
    enc = StreamEncoder(message, profile="paper", cells=16)
    dec = StreamDecoder(profile="paper", cells=16, message_size=len(message))
    frames = noisy_channel(enc, 12_345, np.random.default_rng(0), ber=1e-4)
    assert [m.data for m in receive(dec, frames, limit=3 * enc.symbols)] == [message]


def test_paper_late_join_decodes_only_whole_codewords() -> None:
    """Joining at frame 21 of 24: codeword 94 has 222 bytes in frame 20 and 33 in frame 21.
    Decoded before frame 20 is in place, its missing bytes must count as erasures, not zeros
    (the all-zero word is a codeword, 33 bytes away)."""
    message = bytes(np.random.default_rng(9).integers(0, 256, 13415, dtype=np.uint8))
    enc = StreamEncoder(message, profile="paper", cells=96)
    dec = StreamDecoder(profile="paper", cells=96, message_size=len(message))
    frames = noisy_channel(enc, 2 * 21, np.random.default_rng(0))
    assert [m.data for m in receive(dec, frames, limit=enc.symbols)] == [message]


def test_paper_decodes_right_bits_under_more_low_confidence_bytes_than_parity() -> None:
    """A paper codeword spans ~8 frames at N = 16; two low-confidence bytes per frame outnumber
    its 4 parity bytes, yet the bits themselves are right and must decode."""
    message = bytes(np.random.default_rng(3).integers(0, 256, 576, dtype=np.uint8))
    enc = StreamEncoder(message, profile="paper", cells=16)
    dec = StreamDecoder(profile="paper", cells=16, message_size=len(message))
    confidence = np.ones((16, 16))
    confidence[::8, 0] = 0.2  # one cell in each of two bytes per frame
    got = []
    for k in range(6, 6 + 4 * enc.cycle, 2):  # joins mid-cycle: the rotation search decodes
        if got := dec.push(enc.payload_bits(k), confidence):
            break
    assert [m.data for m in got] == [message]


def test_paper_decoder_without_size_never_claims_a_message() -> None:
    enc = StreamEncoder(b"abc", profile="paper")
    dec = StreamDecoder(profile="paper")
    assert dec.push(enc.payload_bits(0)) == []
    assert dec.progress() == {}


@pytest.mark.parametrize("profile", ["paper", "robust", "fast"])
def test_empty_message_is_a_valid_message(profile: str) -> None:
    enc = StreamEncoder(b"", profile=profile)
    dec = StreamDecoder(profile=profile, message_size=0)
    frames = noisy_channel(enc, 0, np.random.default_rng(0))
    assert [m.data for m in receive(dec, frames, limit=10)] == [b""]


def test_fast_frames_toggle_by_the_payload_bits() -> None:
    enc = StreamEncoder(bytes(range(200)), profile="fast", cells=16)
    geo = enc.geometry
    previous = geo.payload_of(enc.frame(0))
    for k in range(1, 3 * enc.profile.key_every):
        shown = geo.payload_of(enc.frame(k))
        if enc.is_data_frame(k):
            np.testing.assert_array_equal(shown ^ previous, enc.payload_bits(k).astype(bool))
        else:
            assert not shown.any()  # key refresh: back to all black
        locator_on = bool(enc.frame(k)[geo.payload_offset - 1, geo.payload_offset - 1])
        assert locator_on == (k % 2 == 0)
        previous = shown


@pytest.mark.parametrize("profile", ["paper", "robust", "fast"])
def test_frame_is_a_pure_function_of_k(profile: str) -> None:
    message = bytes(range(256)) * 3
    sequential = StreamEncoder(message, profile=profile, cells=16).frames(0, 120)
    fresh = StreamEncoder(message, profile=profile, cells=16)
    for k in np.random.default_rng(0).permutation(120):
        np.testing.assert_array_equal(fresh.frame(int(k)), sequential[k])
    np.testing.assert_array_equal(fresh.frame(fresh.cycle + 5), sequential[5])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"profile": "turbo"}, "valid profiles: paper, robust, fast"),
        ({"cells": 7}, "cells must be 8..128"),
        ({"cells": 129}, "cells must be 8..128"),
        ({"profile": "paper", "cells": 18}, "multiple of 4"),
        ({"cells": 8}, "too small"),
        ({"stream_id": 70000}, "stream_id must be 0..65535"),
        ({"name": "x" * 300}, "at most 255"),
    ],
)
def test_bad_encoder_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        StreamEncoder(b"hello", **kwargs)


def test_bad_refresh_indices_and_shapes() -> None:
    enc = StreamEncoder(b"hello")
    with pytest.raises(ValueError, match="refresh index must be >= 0"):
        enc.frame(-1)
    with pytest.raises(ValueError, match="carries no data"):
        enc.payload_bits(1)
    dec = StreamDecoder()
    with pytest.raises(ValueError, match="bits must be 16x16"):
        dec.push(np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError, match="confidence must be 16x16"):
        dec.push(np.zeros((16, 16), np.uint8), np.ones(3))
    with pytest.raises(ValueError, match="valid profiles"):
        StreamDecoder(profile="nope")


def test_fast_cells_do_not_toggle_in_lockstep_with_the_inner_locator() -> None:
    # The header repeats from frame to frame; whitened by a key that changes with every frame,
    # no payload cell carries the same symbol bit for long, so none blinks like the locator.
    enc = StreamEncoder(bytes(range(256)) * 8, profile="fast", cells=32)
    symbols = np.array([enc.payload_bits(k) for k in range(1, 41) if enc.is_data_frame(k)])
    assert len(symbols) > 30
    always_one = np.all(symbols == 1, axis=0)
    assert not always_one.any()


def _frame_with_unsure_errors(cells: int, wrong: int):
    """A robust frame whose first codeword has ``wrong`` wrong bytes, more than its parity
    corrects as errors; each wrong byte holds one cell of middling confidence (above the
    outright erasure level), every other cell full confidence."""
    codec = FrameCodec(get_profile("robust"), cells)
    symbol = bytes(range(codec.symbol_size))
    bits = codec.encode(FrameHeader(7, 0, 1, 3), symbol)
    confidence = np.ones(bits.shape)
    # Frame byte p belongs to codeword p % codewords: flip one cell of each of its bytes.
    positions = np.arange(wrong) * codec.codewords
    flat_bits, flat_conf = bits.reshape(-1), confidence.reshape(-1)
    flat_bits[8 * positions] ^= 1
    flat_conf[8 * positions] = 0.3
    return codec, bits, confidence, symbol


def test_least_confident_bytes_are_erased_when_errors_alone_fail() -> None:
    # Beyond errors-only decoding, within erasures:
    wrong = FrameCodec(get_profile("robust"), 32).rs.nsym // 2 + 3
    codec, bits, confidence, symbol = _frame_with_unsure_errors(32, wrong)
    assert get_profile("robust").erasure_below < 0.3  # not erased outright
    hard = FrameCodec(replace(get_profile("robust"), erasure_rounds=0), 32)
    assert hard.decode(bits, confidence) is None
    header, got = codec.decode(bits, confidence)
    assert got == symbol and header.esi == 3
    # The retries report what they corrected like a first-pass decode: the flipped cells.
    assert np.array_equal(codec.corrected, confidence < 1)
    # Without confidences nothing tells the wrong bytes apart.
    assert codec.decode(bits) is None


@pytest.mark.parametrize("profile", FRAMED)
def test_decoder_marks_the_cells_its_code_corrected(profile: str) -> None:
    enc = StreamEncoder(b"hello" * 40, profile=profile, cells=16)
    dec = StreamDecoder(profile=profile, cells=16)
    k = next(k for k in range(10) if enc.is_data_frame(k))
    bits = enc.payload_bits(k)
    flipped = np.zeros_like(bits, dtype=bool)
    flipped[[0, 3, 9], [2, 7, 11]] = True
    dec.push(bits ^ flipped)
    assert dec.verified_bits, "the frame decoded"
    assert np.array_equal(dec.corrected, flipped)
    dec.push(bits)
    assert not dec.corrected.any(), "a clean frame needs no correction"
    dec.push(np.random.default_rng(2).integers(0, 2, (16, 16), dtype=np.uint8))
    assert dec.corrected is None, "a frame that did not decode has no corrections"
    assert StreamDecoder(profile="paper", cells=16, message_size=10).corrected is None


def test_unsure_right_bytes_never_cost_a_frame_the_bits_alone_decode() -> None:
    # As many wrong bytes as the parity corrects as errors, plus right bytes with a cell read
    # at zero confidence: erasing those would need 2 errors + erasures > nsym.
    nsym = FrameCodec(get_profile("robust"), 32).rs.nsym
    codec, bits, confidence, symbol = _frame_with_unsure_errors(32, nsym // 2)
    confidence[confidence < 1] = 1.0  # the wrong bytes look sure
    sure_bytes = (nsym // 2 + np.arange(4)) * codec.codewords  # right bytes, codeword 0
    confidence.reshape(-1)[8 * sure_bytes + 3] = 0.0
    assert codec.decode(bits) is not None
    header, got = codec.decode(bits, confidence)
    assert got == symbol and header.esi == 3
    threshold = FrameCodec(replace(get_profile("robust"), erasure_rounds=0), 32)
    assert threshold.decode(bits, confidence) is not None
