"""A live source keeps a slow consumer within ``MAX_LAG_S`` of it by dropping what waits, and
never drops for a consumer that keeps up, whatever the camera's clock drift. A fake wall clock
runs the camera, its driver's queue and the consumer's work."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from eventocc.receiver.events import make_events
from eventocc.receiver.live.sources import MAX_LAG_S, StayLive, paced

CHUNK_US = 10_000
START = 100.0
"""The fake wall clock's time when the camera starts (the ``wall`` fixture's)."""


def camera_chunks(n: int, start_us: int = 0) -> list[np.ndarray]:
    t = [np.arange(start_us + k * CHUNK_US, start_us + (k + 1) * CHUNK_US, 100) for k in range(n)]
    zeros = np.zeros(len(t[0]), np.int64)
    return [make_events(ts, zeros, zeros, zeros + 1) for ts in t]


def driver(wall, n: int, clock_rate: float = 1.0):
    """A camera's driver, started at wall time ``START``: chunk k is complete (and returned at
    once when asked later) ``(k + 1) * span / clock_rate`` after it; asked earlier, it blocks
    until then."""
    for k, c in enumerate(camera_chunks(n, start_us=5_000_000)):
        wall.now = max(wall.now, START + (k + 1) * CHUNK_US / 1e6 / clock_rate)
        yield c


def consume(wall, chunks, cost: float, slow_from_s: float = 0.0):
    """The chunks a consumer that works ``cost`` chunk spans on each one (0.8 before
    ``slow_from_s`` of events) gets, and how far behind the camera each one was when it got
    it."""
    got, late = [], []
    for c in chunks:
        got.append(c)
        end_s = (int(c["t"][-1]) - 5_000_000 + 100) / 1e6
        late.append(wall.now - START - end_s)
        wall.sleep((cost if end_s >= slow_from_s else 0.8) * CHUNK_US / 1e6)
    return got, late


def test_a_consumer_that_keeps_up_gets_every_chunk(wall) -> None:
    live = StayLive(clock=wall.clock)
    got, late = consume(wall, live(driver(wall, 500)), 0.8)
    assert len(got) == 500 and live.dropped_events == 0 and live.skips == 0
    assert live.speed == 1.0
    assert max(late) < 0.001


def test_a_slow_consumer_drops_what_waits_and_stays_within_the_lag(wall, caplog) -> None:
    live = StayLive(clock=wall.clock)
    n = 1000  # 10 s of events, processed at half real time
    with caplog.at_level(logging.WARNING):
        got, late = consume(wall, live(driver(wall, n)), 2.0)
    assert max(late) <= MAX_LAG_S + 2 * CHUNK_US / 1e6, "the lag stays bounded"
    assert live.skips >= 4 and live.dropped_events == (n - len(got)) * len(got[0])
    assert 0.4 < live.speed < 0.6, "about half the events are kept"
    gaps = np.diff([int(c["t"][0]) for c in got])
    assert gaps.max() > MAX_LAG_S * 1e6 / 2, "the consumer sees the gap it skipped"
    assert "receiver at 0.50x real time" in caplog.text
    assert caplog.text.count("skipped ahead") == 1, "the note is not repeated every skip"


def test_a_backlog_before_the_first_chunk_is_not_taken_for_the_norm(wall) -> None:
    """The driver holds 0.6 s of events when first asked; the consumer catches up at 1.25x
    real time, then runs at half: the lag it is allowed is measured from the camera, not from
    the first chunk's lateness."""
    wall.now = START + 0.6
    live = StayLive(clock=wall.clock)
    _, late = consume(wall, live(driver(wall, 1500)), 2.0, slow_from_s=8.0)
    assert late[0] == pytest.approx(0.59) and live.skips >= 1
    assert max(late[800:]) <= MAX_LAG_S + 2 * CHUNK_US / 1e6


@pytest.mark.parametrize("clock_rate", [1 - 1e-3, 1 + 1e-3])
def test_clock_drift_does_not_read_as_a_growing_lag(wall, clock_rate) -> None:
    """A millisecond a second either way: ten times what a camera's crystal drifts. Over 20 min
    a lag tied once would grow past ``MAX_LAG_S``; at most one chunk goes when it does."""
    live = StayLive(clock=wall.clock)
    n = 120_000
    got, _ = consume(wall, live(driver(wall, n, clock_rate)), 0.7)
    assert n - len(got) <= 1 and live.skips <= 1


def test_a_recording_at_real_time_pace_skips_ahead_behind_a_slow_consumer(wall) -> None:
    live = StayLive(clock=wall.clock)
    chunks = paced(camera_chunks(600), clock=wall.clock, sleep=wall.sleep)
    got = []
    for c in live(chunks):
        got.append(c)
        wall.sleep(3 * CHUNK_US / 1e6)
    assert 150 < len(got) < 300 and live.skips >= 2
    # Without it the last chunk would come 12 s late; with it the wall clock ends near 6 s.
    assert wall.now - START < 6.0 + MAX_LAG_S + 0.1


def test_empty_chunks_pass_and_count_for_nothing(wall) -> None:
    live = StayLive(clock=wall.clock)
    empty = make_events(*(np.zeros(0, np.int64) for _ in range(4)))
    out = list(live([empty, *camera_chunks(2), empty]))
    assert [len(c) for c in out] == [0, 100, 100, 0] and live.speed is None
