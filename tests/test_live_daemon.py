"""The receiver daemon without the network: sources, pacing, the spool, and what it reports."""

from __future__ import annotations

import base64
import hashlib
import re
import sys

import numpy as np
import pytest

from eventocc.occ.profiles import LinkSettings
from eventocc.occ.report import (
    CellsReport,
    FrameStats,
    HealthReport,
    MessageReport,
    PoseReport,
    SurfaceReport,
    TrackingState,
)
from eventocc.occ.stream import ReceivedMessage, StreamDecoder, StreamEncoder
from eventocc.receiver.events import make_events
from eventocc.receiver.live.cameras import LiveCamera
from eventocc.receiver.live.daemon import Daemon, DaemonConfig, LinkFollower, OutputFolder
from eventocc.receiver.live.sources import MAX_LAG_S, LiveClock, SourceError, paced
from eventocc.receiver.live.spool import Spool
from eventocc.receiver.live.uri import open_source
from eventocc.receiver.pipeline.decoder import FrameRead
from eventocc.receiver.pipeline.receiver import (
    FrameOutput,
    MessageOutput,
    PoseEstimate,
    StateChange,
)
from eventocc.receiver.poses import make_pose, read_tum


class ListSink:
    def __init__(self) -> None:
        self.reports: list[tuple[object, bool]] = []

    def publish(self, report, *, durable: bool) -> None:
        self.reports.append((report, durable))

    def of(self, kind: type) -> list:
        return [r for r, _ in self.reports if isinstance(r, kind)]


class ScriptedStream:
    def progress(self) -> dict[int, dict]:
        return {
            5: {"stream_id": 5, "symbols_held": 3, "symbols_needed": 9, "name": "a.txt", "size": 40}
        }


class ScriptedPipeline:
    """Stands in for the receiver pipeline: one pose per 250 us of events, a frame per chunk,
    and a message on the chunk given."""

    cell_px = 2.5
    detection_failure = "spatial: no inner-locator 'L' found (score 0.10)"

    def __init__(
        self, message_on_chunk: int = 3, name: str = "a.txt", proven_from_us: int = 0
    ) -> None:
        self.proven_from_us = proven_from_us
        """Poses from this time on come out verified, the earlier ones tentative."""
        self.stream = ScriptedStream()
        self.chunks = 0
        self.message_on_chunk = message_on_chunk
        self.name = name

    def push(self, chunk: np.ndarray) -> list:
        if not len(chunk):  # as the receiver: a heartbeat of no events changes nothing
            return []
        self.chunks += 1
        t0, t1 = int(chunk["t"][0]), int(chunk["t"][-1])
        out: list = [StateChange(t0, "tracking", "marker detected")] if self.chunks == 1 else []
        out += [
            PoseEstimate(t, make_pose(np.eye(3), [t * 1e-6, 0.0, -1.0]), t >= self.proven_from_us)
            for t in range(t0, t1, 250)
        ]
        bits = np.eye(4, dtype=np.uint8)
        corrected = np.zeros((4, 4), bool)
        corrected[0, 1] = True
        out.append(
            FrameOutput(
                FrameRead(self.chunks, t1, bits, np.full((4, 4), 0.9), 0.8, len(chunk)),
                True,
                corrected=corrected,
            )
        )
        if self.chunks == self.message_on_chunk:
            data = b"the scripted message"
            digest = hashlib.sha256(data).hexdigest()
            out.append(MessageOutput(t1, ReceivedMessage(self.name, data, digest, 5, "robust")))
        return out

    def finish(self) -> list:
        return []


class ListSource:
    def __init__(self, chunks: list[np.ndarray], width: int = 64, height: int = 48) -> None:
        self.width, self.height = width, height
        self._chunks = chunks

    def chunks(self):
        return iter(self._chunks)


class WatchingSource(ListSource):
    """A source that knows what the screen sends (``link``, one per chunk) and its ``speed``."""

    def __init__(self, chunks: list[np.ndarray], links: list[LinkSettings], speed=None) -> None:
        super().__init__(chunks)
        self.links, self.speed = links, speed
        self.link: LinkSettings | None = None

    def chunks(self):
        for events, link in zip(self._chunks, self.links, strict=True):
            self.link = link
            yield events


ROBUST_16, FAST_12 = LinkSettings("robust", 16), LinkSettings("fast", 12)


def chunk(t0_us: int, t1_us: int, n: int = 200, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(t0_us, t1_us, n).astype(np.int64)
    return make_events(t, rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n))


def run_daemon(
    tmp_path, chunks: list[np.ndarray], pipeline: ScriptedPipeline | None = None, **config
) -> tuple[Daemon, ListSink]:
    sink = ListSink()
    daemon = Daemon(
        ListSource(chunks),
        pipeline or ScriptedPipeline(),
        sink,
        OutputFolder(tmp_path / "out"),
        DaemonConfig(**config),
    )
    daemon.run()
    return daemon, sink


def test_poses_are_decimated_for_the_server_and_kept_in_full_in_the_file(tmp_path) -> None:
    chunks = [chunk(i * 10_000, (i + 1) * 10_000 - 1) for i in range(10)]  # 0.1 s
    daemon, sink = run_daemon(tmp_path, chunks, pose_hz=100.0)
    sent = sink.of(PoseReport)
    assert [p.t_us for p in sent] == list(range(0, 100_000, 10_000))
    assert all(durable for r, durable in sink.reports if isinstance(r, PoseReport))
    t_us, T = read_tum(tmp_path / "out" / "trajectory.tum")
    assert len(t_us) == daemon.summary.poses == 400, "the file keeps every pose"
    assert np.allclose(T[:, 0, 3], t_us * 1e-6)
    assert sent[3].position == pytest.approx((0.03, 0.0, -1.0))


def test_tentative_poses_are_flagged_and_kept_out_of_the_trajectory(tmp_path) -> None:
    chunks = [chunk(i * 10_000, (i + 1) * 10_000 - 1) for i in range(10)]
    daemon, sink = run_daemon(tmp_path, chunks, ScriptedPipeline(proven_from_us=50_000))
    sent = sink.of(PoseReport)
    assert [p.verified for p in sent] == [p.t_us >= 50_000 for p in sent]
    assert {p.verified for p in sent} == {True, False}
    t_all, _ = read_tum(tmp_path / "out" / "trajectory_all.tum")
    t_verified, T = read_tum(tmp_path / "out" / "trajectory.tum")
    assert len(t_all) == daemon.summary.poses == 400
    assert list(t_verified) == [t for t in t_all if t >= 50_000] and len(t_verified) == 200
    assert np.allclose(T[:, 0, 3], t_verified * 1e-6)


def test_a_read_frames_cells_go_out_packed_a_few_times_a_second(tmp_path) -> None:
    chunks = [chunk(i * 10_000, (i + 1) * 10_000 - 1) for i in range(10)]
    daemon, sink = run_daemon(tmp_path, chunks, news_hz=1e-3)  # at most one in 1000 s
    (cells,) = sink.of(CellsReport)
    assert daemon.summary.frames == 10, "every frame read, one shown"
    assert (cells.cells, cells.frame_index, cells.t_us) == (4, 1, 9_999)
    unpack = lambda b64: np.unpackbits(np.frombuffer(base64.b64decode(b64), np.uint8))  # noqa: E731
    assert np.array_equal(unpack(cells.bits_b64).reshape(4, 4), np.eye(4))
    assert np.flatnonzero(unpack(cells.corrected_b64)).tolist() == [1]
    assert not any(durable for r, durable in sink.reports if isinstance(r, CellsReport))


def test_health_says_what_the_camera_sees_and_why_it_cannot_lock(tmp_path) -> None:
    daemon = Daemon(ListSource([]), ScriptedPipeline(), ListSink(), OutputFolder(tmp_path))
    daemon.state = TrackingState.SCANNING
    daemon.publish_news(None)
    daemon.state = TrackingState.TRACKING
    daemon.publish_news(None)
    scanning, tracking = daemon.sink.of(HealthReport)
    assert scanning.px_per_cell == tracking.px_per_cell == 2.5
    assert scanning.detection_failure == "spatial: no inner-locator 'L' found (score 0.10)"
    assert tracking.detection_failure is None, "a failure before the lock is history"


def test_finished_messages_are_saved_and_reported_durably(tmp_path) -> None:
    _, sink = run_daemon(tmp_path, [chunk(i * 1000, i * 1000 + 999) for i in range(4)])
    (report,) = sink.of(MessageReport)
    assert report.data == b"the scripted message" and report.name == "a.txt"
    assert (report, True) in sink.reports
    (saved,) = (tmp_path / "out" / "messages").iterdir()
    assert saved.read_bytes() == b"the scripted message" and saved.name.endswith("-a.txt")


LONG = "n" * 251 + ".txt"  # 255 bytes: legal, and 268 with the digest prefix


@pytest.mark.parametrize(
    ("name", "ending"),
    [
        (LONG, "n.txt"),
        ("n" * 243, "nnn"),
        ("é" * 127 + ".bin", "é.bin"),  # 258 bytes of UTF-8: cut between characters
        ("\U0001f600" * 63 + "x", "\U0001f600"),
        ("a\x00b\x1f.txt", "a_b_.txt"),
        ("../../etc/passwd", "-passwd"),
        ("..", "-message"),
        ("", "-message"),
    ],
)
def test_any_legal_message_name_is_saved(tmp_path, name: str, ending: str) -> None:
    chunks = [chunk(i * 1000, i * 1000 + 999) for i in range(4)]
    _, sink = run_daemon(tmp_path, chunks, ScriptedPipeline(name=name))
    assert sink.of(MessageReport)[0].name == name
    (saved,) = (tmp_path / "out" / "messages").iterdir()
    assert saved.read_bytes() == b"the scripted message"
    assert len(saved.name.encode()) <= 255 and saved.name.endswith(ending)


def test_a_message_that_cannot_be_saved_is_still_reported(tmp_path, caplog) -> None:
    """The server's copy goes first: a full disk (here, no folder to write to) loses nothing
    durable and stops nothing."""
    output = OutputFolder(tmp_path / "out")
    output.messages.rmdir()
    output.messages.write_text("not a folder")
    sink = ListSink()
    chunks = [chunk(i * 1000, i * 1000 + 999) for i in range(6)]
    daemon = Daemon(ListSource(chunks), ScriptedPipeline(), sink, output)
    daemon.run()
    assert [r.name for r in sink.of(MessageReport)] == ["a.txt"]
    assert daemon.summary.chunks == 6
    assert "message 'a.txt' complete (20 bytes), but not saved" in caplog.text


def test_news_is_ephemeral_and_well_formed(tmp_path) -> None:
    daemon, sink = run_daemon(tmp_path, [chunk(0, 9_999)], news_hz=1000.0)
    news = [r for r, durable in sink.reports if not durable]
    kinds = {type(r).__name__ for r in news}
    assert kinds == {"FrameStats", "ProgressReport", "HealthReport", "SurfaceReport", "CellsReport"}
    (surface,) = sink.of(SurfaceReport)
    pixels = np.frombuffer(base64.b64decode(surface.pixels_b64), np.uint8)
    assert pixels.size == 64 * 48 and pixels.max() == 255, "the newest event is at full white"
    assert sink.of(FrameStats)[0].confidence_mean == pytest.approx(0.9)
    assert sink.of(HealthReport)[-1].state == "idle", "the last health says the daemon stopped"
    assert daemon.summary.frames == 1


def test_the_thumbnail_fades_each_block_from_its_latest_event(tmp_path) -> None:
    daemon = Daemon(ListSource([]), ScriptedPipeline(), ListSink(), OutputFolder(tmp_path))
    tau = daemon.config.thumbnail_tau_us  # the 64x48 sensor: one pixel per thumbnail pixel
    t_now = 100_000
    # (1, 2) fired at t_now - tau, then earlier (sensors reorder); (5, 3) at t_now; (63, 47)
    # at t_now - 2 tau, then at t_now - tau.
    events = make_events(
        [t_now - tau, t_now - 2 * tau, t_now - 2 * tau, t_now - tau, t_now],
        [1, 1, 63, 63, 5],
        [2, 2, 47, 47, 3],
        np.ones(5, bool),
    )
    report = daemon.thumbnail(events)
    pixels = np.frombuffer(base64.b64decode(report.pixels_b64), np.uint8).reshape(48, 64)
    one_tau = round(255 * np.exp(-1))
    assert (pixels[3, 5], pixels[2, 1], pixels[47, 63]) == (255, one_tau, one_tau)
    assert np.count_nonzero(pixels) == 3


def test_spool_keeps_identity_and_numbers_across_restarts(tmp_path) -> None:
    spool = Spool(tmp_path / "spool.db")
    first_id = spool.receiver_id
    assert [spool.append(f'{{"n": {i}}}') for i in range(3)] == [1, 2, 3]
    spool.acknowledge(2)
    assert spool.pending() == [(3, '{"n": 2}')]
    spool.acknowledge(3)
    spool.close()
    again = Spool(tmp_path / "spool.db")
    assert again.receiver_id == first_id
    assert len(again) == 0 and again.append("{}") == 4, "numbers are never reused"


def test_paced_waits_for_the_wall_clock_to_catch_up() -> None:
    now = [100.0]
    waits: list[float] = []

    def sleep(s: float) -> None:
        waits.append(round(s, 6))
        now[0] += s

    chunks = [chunk(1_000_000, 1_010_000), chunk(1_010_001, 1_500_000)]
    assert len(list(paced(chunks, clock=lambda: now[0], sleep=sleep))) == 2
    assert waits == [0.01, 0.49]
    with pytest.raises(ValueError, match="speed must be positive"):
        list(paced(chunks, speed=0))


@pytest.mark.parametrize(
    ("uri", "message"),
    [
        ("file:/nonexistent/rec.raw", "no recording at /nonexistent/rec.raw"),
        ("usb:camera", "unknown source 'usb:camera': use sim:, file:PATH"),
        ("nd:", "needs the neuromorphic_drivers package; pip install 'eventocc[live-nd]'"),
        ("dv:", "pip install 'eventocc[live-dv]'"),
        ("metavision:", "install OpenEB or the Metavision SDK"),
    ],
)
def test_sources_say_what_to_fix(uri: str, message: str, monkeypatch) -> None:
    # The dev extra installs the live backends' packages: here each is taken away.
    for package in ("neuromorphic_drivers", "dv_processing", "metavision_core"):
        monkeypatch.setitem(sys.modules, package, None)
    with pytest.raises(SourceError, match=message.replace("[", r"\[").replace("]", r"\]")):
        open_source(uri)


@pytest.mark.parametrize("uri", ["nd:", "nd:00051234", "dv:"])
def test_a_live_source_without_a_camera_says_so(uri: str) -> None:
    with pytest.raises(SourceError, match=rf"live camera source {uri[:2]}: no camera opened \("):
        open_source(uri)


def test_virtual_camera_needs_an_http_url() -> None:
    with pytest.raises(SourceError, match="needs the server's http"):
        open_source("sim:", server_url="ws://localhost:8000")
    with pytest.raises(SourceError, match="unknown motion 'flying'"):
        open_source("sim:", server_url="http://localhost:8000", motion="flying")


@pytest.mark.parametrize(
    ("pinned", "built"),
    [
        ({}, [ROBUST_16, FAST_12]),
        ({"cells": 16}, [ROBUST_16, LinkSettings("fast", 16)]),
        ({"profile": "robust", "cells": 16}, [ROBUST_16]),
        ({"refresh_hz": 144.0}, [LinkSettings("robust", 16, 144), LinkSettings("fast", 12, 144)]),
    ],
)
def test_daemon_follows_the_transmitters_link_settings_unless_pinned(
    tmp_path, caplog, pinned: dict, built: list
) -> None:
    daemon, first, builds = follow(tmp_path, caplog, [ROBUST_16] * 3 + [FAST_12] * 3, **pinned)
    rebuilt = len(built) > 1
    assert builds == built
    assert daemon.summary.rebuilds == len(built) - 1
    assert first.chunks == (3 if rebuilt else 6), "the old pipeline stops"
    assert daemon.pipeline.chunks == 3 or not rebuilt
    assert ("rebuilding the receiver" in caplog.text) == rebuilt
    assert ("is pinned to" in caplog.text) == bool(pinned)


def test_daemon_follows_a_new_refresh_rate_but_not_its_wobble(tmp_path, caplog) -> None:
    measured = [59.9, 60.2, 60.0, 143.8, 144.3, 144.0]
    links = [LinkSettings("robust", 16, hz) for hz in measured]
    *_, builds = follow(tmp_path, caplog, links)
    assert builds == [ROBUST_16, LinkSettings("robust", 16, 144.0)]
    assert "robust with 16 cells at 144 Hz" in caplog.text


def follow(tmp_path, caplog, links: list[LinkSettings], build=None, **pinned):
    """Run a daemon whose source reports ``links``, one per chunk; return it, its first
    pipeline and the link settings of every pipeline built (by ``build``, if given)."""
    builds: list[LinkSettings] = []

    def scripted(link: LinkSettings) -> ScriptedPipeline:
        builds.append(link)
        return ScriptedPipeline(message_on_chunk=0) if build is None else build(link)

    chunks = [chunk(i * 1000, i * 1000 + 999) for i in range(len(links))]
    source = WatchingSource(chunks, links)
    follower = LinkFollower(scripted, source, links[0], **pinned)
    first = follower.pipeline()
    daemon = Daemon(source, first, ListSink(), OutputFolder(tmp_path / "out"), follower=follower)
    with caplog.at_level("INFO", logger="eventocc.receiver.live.daemon"):
        daemon.run()
    return daemon, first, builds


def test_without_a_follower_the_pipeline_stays_as_built(tmp_path) -> None:
    chunks = [chunk(i * 1000, i * 1000 + 999) for i in range(4)]
    pipeline = ScriptedPipeline()
    source = WatchingSource(chunks, [ROBUST_16] * 2 + [FAST_12] * 2)
    daemon = Daemon(source, pipeline, ListSink(), OutputFolder(tmp_path / "out"))
    daemon.run()
    assert daemon.pipeline is pipeline and pipeline.chunks == 4


@pytest.mark.parametrize("speed", [0.4, None])
def test_health_carries_the_sources_speed(tmp_path, speed) -> None:
    source = WatchingSource([chunk(0, 9_999)], [ROBUST_16], speed=speed)
    sink = ListSink()
    Daemon(source, ScriptedPipeline(), sink, OutputFolder(tmp_path / "out")).run()
    assert {h.source_speed for h in sink.of(HealthReport)} == {speed}


class SlowPipeline(ScriptedPipeline):
    """Takes twice a chunk's span of the fake wall clock to push it: a receiver at half real
    time."""

    def __init__(self, wall) -> None:
        super().__init__()
        self.wall = wall

    def push(self, chunk: np.ndarray) -> list:
        self.wall.sleep(2 * (int(chunk["t"][-1]) - int(chunk["t"][0]) + 1) / 1e6)
        return super().push(chunk)


def test_a_daemon_behind_a_live_camera_stays_live_and_says_so(tmp_path, caplog, wall) -> None:
    """3 s of a camera's 10 ms chunks, each returned when complete, on a fake wall clock."""
    start = wall.now

    def camera():
        for i in range(300):
            wall.now = max(wall.now, start + (i + 1) / 100)  # blocks until the chunk is done
            yield chunk(i * 10_000, (i + 1) * 10_000 - 1)

    pipeline, sink = SlowPipeline(wall), ListSink()
    source = LiveCamera(64, 48, camera(), clock=wall.clock)
    daemon = Daemon(source, pipeline, sink, OutputFolder(tmp_path / "out"))
    with caplog.at_level("WARNING", logger="eventocc.receiver.live.sources"):
        daemon.run()
    assert wall.now - start <= 3.0 + MAX_LAG_S + 0.02, "the lag stayed bounded"
    assert 100 <= pipeline.chunks <= 200, "about half of the chunks were pushed"
    assert re.search(r"receiver at 0\.[3-6]\dx real time: .* skipped ahead", caplog.text)
    speeds = [h.source_speed for h in sink.of(HealthReport) if h.source_speed is not None]
    assert speeds and all(0.3 < v < 0.7 for v in speeds)


def test_live_clock_says_how_late_and_what_is_due_now() -> None:
    now = [10.0]
    clock = LiveClock(clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    with pytest.raises(RuntimeError, match=r"start\(\) must be called first"):
        clock.wait(0)
    clock.start(1_000_000)
    assert clock.wait(1_250_000) == 0.0 and now[0] == 10.25, "early: it sleeps"
    now[0] += 0.5
    assert clock.wait(1_300_000) == pytest.approx(0.45), "late: it says by how much"
    assert clock.now_us() == 1_750_000


class PausingSource(ListSource):
    """A virtual camera whose screen is paused between two stretches of events: it yields empty
    heartbeats and says why (``waiting``) meanwhile."""

    def __init__(self) -> None:
        super().__init__([])
        self.waiting: str | None = None

    def chunks(self):
        yield chunk(0, 9_999)
        self.waiting = "the transmitter page is paused"
        yield chunk(0, 0, n=0)
        self.waiting = None
        yield chunk(10_000, 19_999)


def test_a_source_with_nothing_to_show_makes_the_daemon_idle_and_say_why(tmp_path) -> None:
    source, sink = PausingSource(), ListSink()
    daemon = Daemon(
        source, ScriptedPipeline(), sink, OutputFolder(tmp_path / "out"), DaemonConfig(news_hz=1e6)
    )
    states = []
    for events in source.chunks():
        daemon.process(events)
        states.append(daemon.state)
    assert states == [TrackingState.TRACKING, TrackingState.IDLE, TrackingState.SCANNING]
    waits = [(h.state, h.waiting) for h in sink.of(HealthReport)]
    assert (TrackingState.IDLE, "the transmitter page is paused") in waits
    assert waits[-1] == (TrackingState.SCANNING, None), "not a frozen 'tracking'"


def test_a_long_reason_to_wait_is_cut_to_fit_the_report(tmp_path) -> None:
    source, sink = PausingSource(), ListSink()
    daemon = Daemon(source, ScriptedPipeline(), sink, OutputFolder(tmp_path / "out"))
    source.waiting = "the server says: " + "x" * 1000
    daemon.publish_news(None)
    (health,) = sink.of(HealthReport)
    assert health.waiting.startswith("the server says: xxx") and len(health.waiting) <= 300


def test_frame_reports_carry_what_auto_mode_chooses_from(tmp_path) -> None:
    chunks = [chunk(i * 1000, i * 1000 + 999) for i in range(3)]
    source = WatchingSource(chunks, [ROBUST_16] * 3)
    source.readout_events_per_s = 400_000.0
    follower = LinkFollower(lambda link: ScriptedPipeline(message_on_chunk=0), source, ROBUST_16)
    sink = ListSink()
    Daemon(
        source, follower.pipeline(), sink, OutputFolder(tmp_path / "out"), follower=follower
    ).run()
    frames = sink.of(FrameStats)
    assert frames
    last = frames[-1]
    assert (last.profile, last.cells, last.px_per_cell) == ("robust", 4, 2.5)
    assert last.passed is False and last.ber_before_fec is None  # no payload bits verified
    assert last.readout_share == pytest.approx(last.events_per_s / 400_000.0)
    assert last.realtime_margin is not None and last.realtime_margin > 0


def test_a_rebuilt_receiver_keeps_the_packed_symbols_it_holds(tmp_path, caplog) -> None:
    """The transmitter's auto mode moves from N = 16 to N = 32 mid-message: the receiver built
    for N = 32 goes on from what the N = 16 one collected."""
    message = bytes(range(256)) * 4
    first = StreamEncoder(message, name="m", cells=16, packed=True)
    decoders: list[StreamDecoder] = []

    def build(link: LinkSettings) -> ScriptedPipeline:
        pipeline = ScriptedPipeline(message_on_chunk=0)
        pipeline.stream = StreamDecoder(profile=link.profile, cells=link.cells)
        if not decoders:  # the first receiver read half the message's symbols at N = 16
            for k in range(0, 2 * len(message) // 12, 2):
                pipeline.stream.push(first.payload_bits(k))
        decoders.append(pipeline.stream)
        return pipeline

    links = [ROBUST_16] * 2 + [LinkSettings("robust", 32)] * 2
    daemon, _, _ = follow(tmp_path, caplog, links, build=build)
    assert daemon.summary.rebuilds == 1
    (held_before,) = [p["symbols_held"] for p in decoders[0].progress().values()]
    (held_after,) = [p["symbols_held"] for p in decoders[1].progress().values()]
    assert held_before > 0 and held_after == held_before
