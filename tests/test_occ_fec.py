"""Reed-Solomon: the numpy fast paths agree with reedsolo, and decoding corrects what it should."""

from __future__ import annotations

import numpy as np
import pytest
import reedsolo
from hypothesis import example, given, settings
from hypothesis import strategies as st

from eventocc.occ.fec import PAPER_RS_K, ReedSolomon, paper_rs


@settings(max_examples=25, deadline=None)
@given(k=st.integers(1, 60), nsym=st.integers(1, 20), seed=st.integers(0, 2**32 - 1))
def test_encode_matches_reedsolo(k: int, nsym: int, seed: int) -> None:
    data = np.random.default_rng(seed).integers(0, 256, (3, k), dtype=np.uint8)
    coded = ReedSolomon(k + nsym, k).encode(data)
    for row, word in zip(data, coded, strict=True):
        assert word.tobytes() == bytes(reedsolo.rs_encode_msg(bytearray(row), nsym))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), errors=st.integers(0, 4), erasures=st.integers(0, 8))
def test_decode_corrects_errors_and_erasures_within_capacity(
    seed: int, errors: int, erasures: int
) -> None:
    rng = np.random.default_rng(seed)
    rs = ReedSolomon(40, 24)  # 16 parity: 2 * errors + erasures <= 16
    data = rng.integers(0, 256, (2, rs.k), dtype=np.uint8)
    coded = rs.encode(data)
    erased = np.zeros_like(coded, dtype=bool)
    for row in range(2):
        pos = rng.choice(rs.n, errors + erasures, replace=False)
        coded[row, pos] ^= rng.integers(1, 256, pos.size, dtype=np.uint8)
        erased[row, pos[errors:]] = True
    out, ok = rs.decode(coded, erased)
    assert ok.all()
    np.testing.assert_array_equal(out, data)


def test_decode_reports_failure_beyond_capacity() -> None:
    rs = ReedSolomon(20, 16)
    coded = rs.encode(np.arange(16, dtype=np.uint8))
    coded[0, :12] ^= 0x5A
    _, ok = rs.decode(coded)
    assert not ok[0]


def test_clean_codewords_have_zero_syndromes() -> None:
    rs = ReedSolomon(255, 223)
    coded = rs.encode(np.random.default_rng(1).integers(0, 256, (4, 223), dtype=np.uint8))
    assert rs.syndromes_clean(coded).all()
    coded[2, 100] ^= 1
    assert rs.syndromes_clean(coded).tolist() == [True, True, False, True]


def test_paper_codes_follow_the_footnote() -> None:
    for n, k in PAPER_RS_K.items():
        assert paper_rs(n) == ReedSolomon(255, k)
    assert paper_rs(20).k == 247  # untested sides take the next larger tested side's code
    assert paper_rs(128).k == 127


@pytest.mark.parametrize(("n", "k"), [(10, 10), (256, 200), (10, 0)])
def test_bad_code_parameters(n: int, k: int) -> None:
    with pytest.raises(ValueError, match="0 < k < n <= 255"):
        ReedSolomon(n, k)


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(8, 255),
    seed=st.integers(0, 2**32 - 1),
    load=st.floats(0, 1.5),
)
@example(n=10, seed=15456, load=1.5)  # a budget of 12 erasures on 10 symbols
def test_compiled_corrector_agrees_with_reedsolo(n: int, seed: int, load: float) -> None:
    """The numba corrector's twin is reedsolo: same answer within capacity, and beyond it never
    a claimed success that is not a codeword."""
    rng = np.random.default_rng(seed)
    nsym = 2 * int(rng.integers(1, min(n // 2 - 1, 20) + 1))
    rs = ReedSolomon(n, n - nsym)
    data = rng.integers(0, 256, (1, rs.k), dtype=np.uint8)
    word = rs.encode(data)
    budget = int(load * rs.nsym)
    erasures = int(rng.integers(0, min(budget, n) + 1))  # no more erasures than symbols
    errors = min((budget - erasures) // 2 if load <= 1 else budget - erasures, n - erasures)
    pos = rng.choice(n, errors + erasures, replace=False)
    word[0, pos] ^= rng.integers(1, 256, pos.size, dtype=np.uint8)
    erased = np.zeros_like(word, dtype=bool)
    erased[0, pos[errors:]] = True
    out, ok = rs.decode(word, erased)
    try:
        ref = bytes(
            reedsolo.rs_correct_msg(bytearray(word[0]), rs.nsym, erase_pos=pos[errors:].tolist())[0]
        )
    except reedsolo.ReedSolomonError:
        ref = None
    if 2 * errors + erasures <= rs.nsym:
        assert ok[0] and out[0].tobytes() == data[0].tobytes() == ref
    elif ok[0]:  # beyond capacity: a (wrong) codeword, the one reedsolo finds too
        assert out[0].tobytes() == ref


def test_margin_keeps_parity_back_for_detection() -> None:
    rs = ReedSolomon(255, 251)  # corrects 2 errors, or 1 with a margin of 2
    coded = rs.encode(np.arange(251, dtype=np.uint8))
    coded[0, [3, 70]] ^= 0xFF
    assert rs.decode(coded)[1][0]
    assert not rs.decode(coded, margin=2)[1][0]
    coded[0, 70] ^= 0xFF
    assert rs.decode(coded, margin=2)[1][0]
