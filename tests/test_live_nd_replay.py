"""The neuromorphic-drivers live path on a recording replayed as an EVK4 (``nd-replay:``): its
pace, its USB ring's overflows, the backlog skipped undecoded when the receiver falls behind,
the sensor's rate limiter; then the whole chain, through the daemon (and the real CLI and
server) into a decoded message."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from eventocc.occ.report import HealthReport, MessageReport
from eventocc.receiver.calibration import save_calibration
from eventocc.receiver.events import concat, make_events
from eventocc.receiver.io import read_events, write_events
from eventocc.receiver.live.controls import CameraSettings
from eventocc.receiver.live.daemon import Daemon, OutputFolder
from eventocc.receiver.live.nd_camera import NdCamera
from eventocc.receiver.live.nd_replay import RawReplay
from eventocc.receiver.live.sources import MAX_LAG_S
from eventocc.receiver.live.virtual_camera import default_camera
from eventocc.receiver.pipeline.receiver import MessageOutput
from tests.screen import SCREEN_MESSAGE, ReportSink, screen_receiver

ROOT = Path(__file__).resolve().parent.parent
SPACING_US = 10


def steady_recording(path: Path, seconds: int) -> Path:
    """A steady 100 k events/s (one every 10 us) on a 64x48 sensor, as EVT 3.0."""
    t = np.arange(0, seconds * 1_000_000, SPACING_US)
    events = make_events(t, t // SPACING_US % 64, t // 640 % 48, t // SPACING_US % 2)
    write_events(path, [events], width=64, height=48)
    return path


@pytest.fixture
def steady(tmp_path) -> Path:
    return steady_recording(tmp_path / "steady.raw", 3)


def test_the_replay_serves_every_event_at_the_recordings_pace(steady, wall) -> None:
    replay = RawReplay(steady, clock=wall.clock, sleep=wall.sleep)
    got, delays = [], []
    with replay as device:
        for status, packet in device:
            got.append(packet.polarity_events)
            delays.append(status.delay())
            assert packet.polarity_events_overflow_indices is None
    t = concat_t(got)
    assert np.array_equal(t, np.arange(0, 3_000_000, SPACING_US))
    assert wall.now - 100.0 == pytest.approx(3.0, abs=0.002), "3 s of events take 3 s"
    assert max(delays) < 0.002 and replay.decoded == 3000, "one 1 ms buffer per packet"


def concat_t(packets: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([p["t"] for p in packets]).astype(np.int64)


def test_a_full_usb_ring_loses_buffers_and_the_packets_say_where(steady, wall) -> None:
    """A consumer that takes 20 ms per packet, a ring of 4 buffers of 1 ms: most buffers are
    lost, each loss marked where it happened, and the camera adds up the event time lost."""
    replay = RawReplay(steady, ring_length=4, clock=wall.clock, sleep=wall.sleep)
    camera = NdCamera(replay)
    got = []
    for chunk in camera.chunks():
        got.append(chunk)
        wall.sleep(0.020)
    t = concat(got)["t"]
    gaps = np.diff(t)
    assert replay.dropped_packets > 2000 and replay.overflow()
    report = camera.camera_report()
    assert report.usb_overflows == np.count_nonzero(gaps > SPACING_US) > 100
    assert report.usb_lost_s == pytest.approx(gaps[gaps > SPACING_US].sum() / 1e6)
    assert replay.decoded + replay.dropped_packets == 3000


def test_a_receiver_behind_skips_the_backlog_undecoded_and_stays_live(tmp_path, wall) -> None:
    """A receiver at half real time over 10 s: the backlog grows to a second, then the driver
    drops it without decoding it, and the receiver goes on from what comes now."""
    replay = RawReplay(
        steady_recording(tmp_path / "10s.raw", 10), clock=wall.clock, sleep=wall.sleep
    )
    camera = NdCamera(replay)
    lags = []
    for chunk in camera.chunks():
        wall.sleep(2 * (int(chunk["t"][-1]) - int(chunk["t"][0]) + SPACING_US) / 1e6)
        lags.append(wall.now - 100.0 - int(chunk["t"][-1]) / 1e6)
    assert camera.skips >= 4 and max(lags) <= MAX_LAG_S + 0.15, "the lag stays bounded"
    cleared = 10_000 - replay.decoded - replay.dropped_packets
    assert cleared > 4000 and replay.dropped_packets == 0, "skipped in the driver, not lost"
    assert camera.speed is not None and 0.4 < camera.speed < 0.6, "half the events are kept"


def test_the_sensors_rate_limiter_thins_each_period(steady, wall) -> None:
    replay = RawReplay(steady, clock=wall.clock, sleep=wall.sleep)
    camera = NdCamera(replay, CameraSettings(max_event_rate=40_000, rate_period_us=1000))
    t = concat(list(camera.chunks()))["t"]
    per_period = np.bincount(t // 1000)
    assert per_period.max() == 40 and per_period.min() == 40, "100 per ms thinned to 40"
    assert np.diff(t).max() <= 3 * SPACING_US, "spread over the period, not its start"


# --- the whole chain ----------------------------------------------------------------------


def test_the_daemon_decodes_a_replayed_evk4_as_it_decodes_the_file(
    screen_recording, tmp_path
) -> None:
    offline = screen_receiver()  # also loads the pipeline's compiled kernels before the clock runs
    outputs = [o for c in read_events(screen_recording / "events.raw") for o in offline.push(c)]
    assert [o.message.data for o in outputs if isinstance(o, MessageOutput)] == [SCREEN_MESSAGE]

    # At a quarter of real time: the daemon decodes what the live path delivers, however
    # busy this machine is (keeping up is the business of the skipping tests).
    slow = 4.0
    device = RawReplay(
        screen_recording / "events.raw",
        readings=(38.25, 1500),
        clock=lambda: time.monotonic() / slow,
        sleep=lambda seconds: time.sleep(seconds * slow),
    )
    sink = ReportSink()
    daemon = Daemon(NdCamera(device), screen_receiver(), sink, OutputFolder(tmp_path / "out"))
    summary = daemon.run()
    (message,) = sink.of(MessageReport)
    assert message.data == SCREEN_MESSAGE and message.name == "replayed.txt"
    assert summary.events == sum(len(c) for c in read_events(screen_recording / "events.raw"))
    cameras = [h.camera for h in sink.of(HealthReport)]
    assert cameras and all(c is not None for c in cameras)
    assert (cameras[-1].temperature_c, cameras[-1].illuminance) == (38.25, 1500)
    assert cameras[-1].usb_overflows == 0 and cameras[-1].max_event_rate == 100e6


def test_receive_from_nd_replay_reaches_the_server(screen_recording, serve_app, tmp_path) -> None:
    """The real CLI on a cold start: whatever the pipeline's first second costs, the live
    path skips what waits and the message still arrives."""
    base_url, _ = serve_app()
    command = [sys.executable, "-m", "eventocc.receiver.cli", "receive"]
    command += ["--source", f"nd-replay:{screen_recording / 'events.raw'}"]
    command += ["--calibration", str(screen_recording / "camera.yaml"), "--cells", "16"]
    command += ["--profile", "robust", "--server", base_url, "--out", str(tmp_path / "out")]
    command += ["--max-event-rate", "50e6"]
    done = subprocess.run(
        command,
        cwd=ROOT,
        env={**os.environ, "NUMBA_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "message 'replayed.txt' complete" in done.stderr
    with urllib.request.urlopen(f"{base_url}/api/receptions", timeout=10) as response:
        receptions = json.load(response)["receptions"]
    assert [r["name"] for r in receptions] == ["replayed.txt"]
    health = json.loads((tmp_path / "out" / "health.json").read_text())
    assert health["camera"]["max_event_rate"] == 50e6 and health["camera"]["usb_overflows"] == 0


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--bias", "diff_on"], "write NAME=VALUE"),
        (["--bias", "diff_up=3"], "no bias diff_up; its biases: pr, fo"),
        (["--bias", "diff_on=5"], "a recording keeps the biases it was recorded with"),
        (["--max-event-rate", "-5"], "max_event_rate must be a positive number"),
        (["--camera-config", "missing.yaml"], "camera config missing.yaml: cannot read it"),
    ],
)
def test_receive_says_what_to_fix_in_the_camera_controls(
    steady, tmp_path, capsys, options, message
) -> None:
    from eventocc.receiver.cli import main

    save_calibration(default_camera(), tmp_path / "camera.yaml")
    source = ["--source", f"nd-replay:{steady}", "--calibration", str(tmp_path / "camera.yaml")]
    assert main(["receive", *source, "--out", str(tmp_path), *options]) == 2
    assert message in capsys.readouterr().err


def test_a_camera_config_file_sets_the_limiter_and_biases(tmp_path) -> None:
    from eventocc.receiver.live.controls import load_camera_settings

    path = tmp_path / "camera.yaml"
    path.write_text("max_event_rate: 20e6\nrate_period_us: 200\nbiases: {diff_off: -4}\n")
    settings = load_camera_settings(path)
    assert (settings.max_event_rate, settings.events_per_period) == (2e7, 4000)
    assert dict(settings.biases) == {"diff_off": -4}
    path.write_text("max_event_rate: null\nrate: 5\n")
    with pytest.raises(Exception, match=r"unknown setting\(s\) rate; use biases"):
        load_camera_settings(path)
