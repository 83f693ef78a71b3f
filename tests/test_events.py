import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eventocc.receiver.events import (
    EVENT_DTYPE,
    concat,
    make_events,
    rechunk_by_count,
    rechunk_by_time,
)


def _events(times):
    n = len(times)
    return make_events(np.sort(np.asarray(times, np.int64)), np.zeros(n), np.zeros(n), np.ones(n))


TIMES = st.lists(st.integers(0, 10**6), max_size=300)
CUTS = st.lists(st.integers(0, 300))


def _split(ev, cuts):
    cuts = sorted({c % (len(ev) + 1) for c in cuts})
    return [ev[a:b] for a, b in zip([0, *cuts], [*cuts, len(ev)], strict=True)]


def test_make_events_normalises_polarity():
    ev = make_events([1, 2, 3], [0, 1, 2], [3, 4, 5], [0, 1, True])
    assert ev.dtype == EVENT_DTYPE
    assert ev["p"].tolist() == [-1, 1, 1]
    assert make_events([1, 2], [0, 0], [0, 0], [-1, 1])["p"].tolist() == [-1, 1]


@settings(max_examples=40, deadline=None)
@given(TIMES, CUTS, st.integers(1, 50))
def test_rechunk_by_count_keeps_every_event(times, cuts, count):
    ev = _events(times)
    out = list(rechunk_by_count(_split(ev, cuts), count))
    assert all(len(c) == count for c in out[:-1])
    assert np.array_equal(concat(out), ev)


@settings(max_examples=40, deadline=None)
@given(TIMES, CUTS, st.integers(1, 10**5))
def test_rechunk_by_time_gives_aligned_windows(times, cuts, window):
    ev = _events(times)
    out = list(rechunk_by_time(_split(ev, cuts), window))
    assert np.array_equal(concat(out), ev)
    for chunk in out:
        assert len(chunk) and len(set((chunk["t"] // window).tolist())) == 1


def test_rechunk_rejects_nonpositive_sizes():
    with pytest.raises(ValueError, match="positive"):
        list(rechunk_by_count([_events([1])], 0))
    with pytest.raises(ValueError, match="positive"):
        list(rechunk_by_time([_events([1])], -5))
