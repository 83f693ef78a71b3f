"""The virtual camera as a live source, on a fake wall clock: it stays live when the simulation
falls behind real time (skips ahead, says so, reports its speed), and it follows the
transmitter to a new stream. And its simulator process, for real."""

from __future__ import annotations

import itertools
import logging
import os
import signal

import numpy as np
import pytest

from eventocc.occ.profiles import LinkSettings
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.events import make_events
from eventocc.receiver.live.screen import Showing
from eventocc.receiver.live.sources import LiveClock, SourceError
from eventocc.receiver.live.virtual_camera import (
    MAX_LAG_S,
    SimulatorInThread,
    SimulatorProcess,
    VirtualCamera,
)

CHUNK_US = 5_000
ROBUST_16 = LinkSettings("robust", 16)


def simulation_at(wall, speed: float):
    """Stands in for ``eventocc.receiver.sim.simulate``: each chunk costs ``1 / speed`` of its
    span."""

    def simulate(scene, duration_s: float, chunk_us: int):
        for t in itertools.count(0, chunk_us):
            wall.now += chunk_us / 1e6 / speed
            yield make_events(np.array([t, t + chunk_us - 1]), [1, 2], [3, 4], [1, 0])

    return simulate


@pytest.fixture
def camera(monkeypatch, wall):
    """``(camera, wall, showing)``: the camera watches ``showing[0]`` on the fake wall clock;
    set ``simulation_at(wall, speed)`` as ``eventocc.receiver.sim.simulate`` before reading
    chunks."""
    showing = [Showing("aaaaaaaaaaaa", ROBUST_16, 60.0, 0)]
    camera = VirtualCamera(
        "http://127.0.0.1:9",
        chunk_us=CHUNK_US,
        check_every_s=0.1,
        clock=LiveClock(clock=wall.clock, sleep=wall.sleep),
        simulator=SimulatorInThread(CHUNK_US),  # it calls the patched simulate
    )
    monkeypatch.setattr(camera.server, "showing", lambda: showing[0])
    monkeypatch.setattr(camera, "encoder", lambda showing: None)
    monkeypatch.setattr(camera, "scene", lambda encoder, showing: showing)
    return camera, wall, showing


def test_a_slow_simulation_skips_ahead_stays_live_and_says_so(camera, monkeypatch, caplog):
    camera, wall, _ = camera
    monkeypatch.setattr("eventocc.receiver.sim.simulate", simulation_at(wall, speed=0.4))
    late_s = []
    with caplog.at_level(logging.INFO, logger="eventocc.receiver.live.virtual_camera"):
        for events in itertools.islice(camera.chunks(), 2000):  # 10 s of events at most
            if camera.skips == 3:
                break
            late_s.append(wall.now - camera.clock.due_s(int(events["t"][-1])))
    assert camera.skips == 3
    assert camera.speed == pytest.approx(0.4, rel=0.05)
    assert max(late_s) <= MAX_LAG_S + CHUNK_US / 1e6 / 0.4 + 1e-6, "the lag stays bounded"
    assert "virtual camera at 0.40x real time" in caplog.text
    assert "skipped ahead 1 time(s)" in caplog.text
    assert caplog.text.count("cannot keep up") == 1, "the note is not repeated every skip"
    assert caplog.text.count("virtual camera watching") == 1, "a skip is not a new stream"


def test_event_time_jumps_to_the_wall_clock_at_a_skip(camera, monkeypatch):
    camera, wall, _ = camera
    monkeypatch.setattr("eventocc.receiver.sim.simulate", simulation_at(wall, speed=0.4))
    previous_end, gaps = 0, []
    for events in itertools.islice(camera.chunks(), 2000):
        if camera.skips == 2:
            break
        gaps.append(int(events["t"][0]) - previous_end)
        previous_end = int(events["t"][-1])
    jumps = [gap for gap in gaps[1:] if gap > CHUNK_US]
    assert len(jumps) == 1 and jumps[0] > 500_000, "the skipped time is not simulated"
    assert all(gap > 0 for gap in gaps[1:]), "time never runs backwards"


def test_a_skip_keeps_the_screens_timeline(camera, monkeypatch):
    # As for a real camera that dropped events: refresh k is still on screen from the same
    # time, so the receiver's frame clock holds across the gap.
    camera, wall, _ = camera
    monkeypatch.setattr("eventocc.receiver.sim.simulate", simulation_at(wall, speed=0.4))
    starts: list[int] = []
    monkeypatch.setattr(camera, "scene", lambda encoder, showing: starts.append(showing.frame_now))
    first_events: list[int] = []
    scenes_seen = 0
    for events in itertools.islice(camera.chunks(), 2000):
        if len(starts) > scenes_seen:
            scenes_seen = len(starts)
            first_events.append(int(events["t"][0]))
        if camera.skips == 3:
            break
    period_us = 1e6 / 60.0
    assert len(starts) == 4 and starts[0] == 0 and starts[-1] > 100
    for frame, t in zip(starts[1:], first_events[1:], strict=True):
        assert t - first_events[0] == pytest.approx(frame * period_us, abs=1.0)


def test_a_skip_keeps_the_hand_held_camera_on_its_path(camera, monkeypatch):
    # The pose goes on from where it was, so the receiver's tracker can keep its lock over the
    # gap (a wander restarted elsewhere looked like a jolt and lost it).
    camera, wall, _ = camera
    camera.motion = "handheld"
    monkeypatch.setattr("eventocc.receiver.sim.simulate", simulation_at(wall, speed=0.4))
    encoder = StreamEncoder(b"path", profile="robust", cells=16)
    scenes, chunks = [], [0]

    def scene(_, showing):
        scenes.append((VirtualCamera.scene(camera, encoder, showing), chunks[0]))
        return showing

    monkeypatch.setattr(camera, "scene", scene)
    for _ in itertools.islice(camera.chunks(), 2000):
        chunks[0] += 1
        if camera.skips == 2:
            break
    assert len(scenes) == 3
    for built, chunks_before in scenes:
        assert built.motion.start_s == pytest.approx(chunks_before * CHUNK_US / 1e6)
    assert scenes[-1][1] > 0 and len({built.motion.seed for built, _ in scenes}) == 1


def test_a_simulation_faster_than_real_time_is_paced_and_never_skips(camera, monkeypatch):
    camera, wall, _ = camera
    monkeypatch.setattr("eventocc.receiver.sim.simulate", simulation_at(wall, speed=3.0))
    for events in itertools.islice(camera.chunks(), 200):  # 1 s of events
        assert wall.now >= camera.clock.due_s(int(events["t"][-1])), "no chunk arrives early"
    assert camera.skips == 0 and camera.speed == 1.0
    assert wall.now == pytest.approx(100.0 + 1.0, abs=0.01)


def test_the_first_chunk_may_take_long_to_compile_and_is_not_late(camera, monkeypatch):
    camera, wall, _ = camera
    simulate = simulation_at(wall, speed=3.0)

    def compiling_first(scene, duration_s: float, chunk_us: int):
        wall.now += 20.0  # numba compiles the simulator's kernels on first use
        yield from simulate(scene, duration_s, chunk_us)

    monkeypatch.setattr("eventocc.receiver.sim.simulate", compiling_first)
    list(itertools.islice(camera.chunks(), 100))
    assert camera.skips == 0 and camera.speed == 1.0


def test_the_camera_follows_the_transmitter_to_another_stream(camera, monkeypatch, caplog):
    camera, wall, showing = camera
    monkeypatch.setattr("eventocc.receiver.sim.simulate", simulation_at(wall, speed=2.0))
    fast_12 = LinkSettings("fast", 12)
    links = []
    with caplog.at_level(logging.INFO, logger="eventocc.receiver.live.virtual_camera"):
        for i, _ in enumerate(itertools.islice(camera.chunks(), 100)):
            links.append(camera.link)
            if i == 30:
                showing[0] = Showing("bbbbbbbbbbbb", fast_12, 60.0, 500)
    assert links[0] == ROBUST_16 and links[-1] == fast_12
    switch = links.index(fast_12)
    assert 30 < switch <= 30 + 0.1e6 / CHUNK_US + 1, "noticed at the next check"
    assert "watching message bbbbbbbbbbbb (fast, 12 cells, 60.0 Hz) from frame 500" in caplog.text


def scene_of(message: bytes, start_refresh: int):
    camera = VirtualCamera("http://127.0.0.1:9")
    encoder = StreamEncoder(message, name="m.bin", profile="robust", cells=16)
    return camera.scene(encoder, Showing("cccccccccccc", ROBUST_16, 60.0, start_refresh))


def test_the_simulator_process_switches_scenes_dropping_what_it_ran_ahead_on() -> None:
    simulator = SimulatorProcess(CHUNK_US)
    try:
        first = list(itertools.islice(simulator.watch(scene_of(b"first", 0)), 4))
        big = os.urandom(300_000)  # its scene does not fit the pipe in one go
        second = list(itertools.islice(simulator.watch(scene_of(big, 600)), 2))
    finally:
        simulator.close()
    assert int(first[-1]["t"][-1]) >= 3 * CHUNK_US, "the first scene ran on"
    assert all(len(events) for events in first + second)
    assert int(second[-1]["t"][-1]) < 2 * CHUNK_US, "the second starts from its beginning"


class BrokenScene:
    def describe(self) -> dict:
        return {"not": "a scene"}


def test_a_dead_simulator_process_is_an_error_not_a_hang() -> None:
    simulator = SimulatorProcess(CHUNK_US)
    try:
        with pytest.raises(SourceError, match="the simulator process died"):
            next(simulator.watch(BrokenScene()))
    finally:
        simulator.close()


def test_a_simulator_process_stopped_by_a_signal_ends_the_camera_quietly() -> None:
    simulator = SimulatorProcess(CHUNK_US)
    try:
        events = simulator.watch(scene_of(b"first", 0))
        next(events)
        os.kill(simulator.pid, signal.SIGTERM)  # as a SIGTERM to the daemon's process group
        # It ends after the packets already in the pipe (small ones: several fit), where a
        # live simulator would go on for ever.
        assert len(list(itertools.islice(events, 200))) < 200
    finally:
        simulator.close()
