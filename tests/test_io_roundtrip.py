"""Every writable format gives back exactly the events written."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eventocc.receiver.events import concat, make_events
from eventocc.receiver.io import WRITE_FORMATS, read_events, write_events
from eventocc.receiver.io.dat import MAX_T as DAT_MAX_T
from eventocc.receiver.io.prophesee_raw import EVT2_MAX_T, EVT3_MAX_T
from eventocc.receiver.io.text import MAX_T as TEXT_MAX_T

WIDTH, HEIGHT = 64, 48
MAX_T = {
    "evt2": EVT2_MAX_T,
    "evt3": EVT3_MAX_T,
    "dat": DAT_MAX_T,
    "text": TEXT_MAX_T,
    "npz": 1 << 62,
    "hdf5": 1 << 62,
}
SPAN = 1 << 22  # events cluster within ~4 s so dense TIME_HIGH words stay few


@st.composite
def event_arrays(draw, max_t: int) -> np.ndarray:
    n = draw(st.integers(0, 40))
    base = draw(st.sampled_from([0, max_t - SPAN, (1 << 24) - 3000]) | st.integers(0, max_t - SPAN))
    # Few distinct offsets, so many events share a timestamp.
    offsets = draw(
        st.lists(st.sampled_from([0, 1, 4095, 4096, 70_000, SPAN]), min_size=n, max_size=n)
        | st.lists(st.integers(0, SPAN), min_size=n, max_size=n)
    )
    t = np.sort(base + np.array(offsets, dtype=np.int64))
    x = draw(st.lists(st.integers(0, WIDTH - 1), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, HEIGHT - 1), min_size=n, max_size=n))
    p = draw(st.lists(st.booleans(), min_size=n, max_size=n))
    return make_events(t, x, y, p)


@pytest.mark.parametrize("fmt", WRITE_FORMATS)
def test_round_trip(fmt, tmp_path_factory):
    @settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(events=event_arrays(MAX_T[fmt]), split=st.integers(0, 40))
    def check(events, split):
        path = tmp_path_factory.mktemp(fmt) / "events"
        written = write_events(
            path, [events[:split], events[split:]], format=fmt, width=WIDTH, height=HEIGHT
        )
        stream = read_events(path, format="raw" if fmt.startswith("evt") else fmt)
        assert (stream.width, stream.height) == (WIDTH, HEIGHT)
        back = concat(stream)
        assert written == len(events)
        np.testing.assert_array_equal(back, events)

    check()


def test_evt3_crosses_the_24_bit_wrap_many_times(tmp_path):
    t = np.arange(0, 3 * (1 << 24) + 5000, 999_983, dtype=np.int64)
    events = make_events(t, t % WIDTH, t % HEIGHT, t % 2)
    write_events(tmp_path / "w.raw", events, width=WIDTH, height=HEIGHT)
    np.testing.assert_array_equal(concat(read_events(tmp_path / "w.raw")), events)


def test_evt3_small_step_back_between_chunks(tmp_path):
    first = make_events([10_000, 10_020], [1, 2], [1, 1], [1, 0])
    second = make_events([10_010, 20_000], [3, 4], [2, 2], [1, 1])  # 10 us back, as sensors do
    write_events(tmp_path / "b.raw", [first, second], width=WIDTH, height=HEIGHT)
    np.testing.assert_array_equal(concat(read_events(tmp_path / "b.raw")), concat([first, second]))


def test_unsorted_chunk_is_written_in_time_order(tmp_path):
    events = make_events([30, 10, 20], [1, 2, 3], [0, 0, 0], [1, 1, 0])
    for fmt in WRITE_FORMATS:
        write_events(tmp_path / "u", events, format=fmt, width=WIDTH, height=HEIGHT)
        back = concat(read_events(tmp_path / "u", format="raw" if fmt[:3] == "evt" else fmt))
        assert back["t"].tolist() == [10, 20, 30] and back["x"].tolist() == [2, 3, 1]
