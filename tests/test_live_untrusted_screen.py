"""Whatever the server says its transmitter shows, a receiver daemon keeps running: link settings
it cannot be built for are refused where they are read, said in the log once, and the daemon
keeps the link it has. The server is a stand-in here, so it can say anything at all."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from eventocc.occ.profiles import LinkSettings
from eventocc.receiver.events import make_events
from eventocc.receiver.live.daemon import Daemon, LinkFollower, OutputFolder
from eventocc.receiver.live.screen import Idle, ScreenWatch, StatusError, TransmitterClient
from tests.test_live_follow import DaemonProcess

ROOT = Path(__file__).resolve().parent.parent
NOW = datetime.now(UTC).isoformat()
GOOD = {
    "message_id": "0123456789ab",
    "profile": "fast",
    "cells": 12,
    "playing": True,
    "frame_index": 0,
    "refresh_hz": 60.0,
    "received": NOW,
}
BOGUS = {**GOOD, "profile": "bogus"}


class StubServer:
    """An HTTP server on loopback answering each path with what ``routes`` holds now (404 for
    the others): it says whatever a test wants, as no real server would."""

    def __init__(self) -> None:
        self.routes: dict[str, bytes | Callable[[], bytes]] = {}
        routes = self.routes

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                if self.path == "/ws/receiver":  # hang up: the publisher retries, as for a restart
                    self.close_connection = True
                    return
                body = routes.get(self.path)
                if callable(body):
                    body = body()
                self.send_response(404 if body is None else 200)
                self.send_header("Content-Length", str(len(body or b"")))
                self.end_headers()
                self.wfile.write(body or b"")

            def log_message(self, *args) -> None:
                pass

        self.http = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.http.server_address[1]}"
        threading.Thread(  # a short poll: quick to shut down
            target=self.http.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
        ).start()

    def status(self, status: dict | str) -> None:
        """Say the transmitter shows ``status``; one received at ``NOW`` is stamped at each
        request, as from a page reporting all along (the module's ``NOW`` ages)."""
        body = status if isinstance(status, str) else json.dumps(status)
        self.routes["/api/transmitter/status"] = lambda: body.replace(
            NOW, datetime.now(UTC).isoformat()
        ).encode()


@pytest.fixture
def stub():
    server = StubServer()
    yield server
    server.http.shutdown()
    server.http.server_close()


@pytest.mark.parametrize(
    ("profile", "cells", "refresh_hz", "problem"),
    [
        ("bogus", 16, 60.0, "unknown link profile 'bogus'"),
        (None, 16, 60.0, "unknown link profile None"),
        (["robust"], 16, 60.0, "unknown link profile"),
        ("robust", 5, 60.0, "cells must be a whole number 8..128, got 5"),
        ("robust", 129, 60.0, "cells must be"),
        ("robust", "16", 60.0, "cells must be"),
        ("robust", True, 60.0, "cells must be"),
        ("robust", 16.0, 60.0, "cells must be"),
        ("robust", 16, 0.4, "refresh rate must be 1..1000 Hz"),
        ("robust", 16, 1000.6, "refresh rate must be"),
        ("robust", 16, float("inf"), "refresh rate must be"),
        ("robust", 16, float("nan"), "refresh rate must be"),
        ("robust", 16, "60", "refresh rate must be"),
    ],
)
def test_link_settings_only_hold_what_a_receiver_can_be_built_for(
    profile, cells, refresh_hz, problem: str
) -> None:
    with pytest.raises(ValueError, match=problem):
        LinkSettings(profile, cells, refresh_hz)


def test_link_settings_keep_whole_hertz() -> None:
    assert LinkSettings("paper", 8, 0.6).refresh_hz == 1.0
    assert str(LinkSettings("fast", 128, 143.9)) == "fast with 128 cells at 144 Hz"


@pytest.mark.parametrize(
    "status",
    [
        BOGUS,
        {**GOOD, "cells": 5},
        {**GOOD, "cells": 10**6},
        {**GOOD, "cells": "many"},
        {**GOOD, "profile": 7},
        {**GOOD, "refresh_hz": -1},
        {**GOOD, "refresh_hz": 1e300},
        '{"playing": true, "message_id": "0123456789ab", "profile": "robust", "cells": 16, '
        f'"refresh_hz": Infinity, "received": "{NOW}"}}',
        '{"playing": true, "message_id": "0123456789ab", "profile": "robust", "cells": 16, '
        f'"refresh_hz": NaN, "received": "{NOW}"}}',
        {**GOOD, "message_id": "../../api/messages"},
        {**GOOD, "frame_index": -1},
        {**GOOD, "frame_index": 10**30},
        {**GOOD, "received": "2026-01-01T00:00:00"},  # no time zone
        {**GOOD, "received": None},
        {key: value for key, value in GOOD.items() if key != "received"},
        [GOOD],
        "null",
        "not json at all",
    ],
)
def test_any_status_gives_a_showing_or_a_status_error(stub, status) -> None:
    stub.status(status)
    with pytest.raises(StatusError, match="what no receiver can read"):
        TransmitterClient(stub.url).showing()


def test_a_good_status_still_gives_what_the_page_shows(stub) -> None:
    stub.status({**GOOD, "refresh_hz": 143.9, "extra": "ignored"})
    showing = TransmitterClient(stub.url).showing()
    assert showing.link == LinkSettings("fast", 12, 144.0)
    assert (showing.message_id, showing.refresh_hz) == ("0123456789ab", 143.9)


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"playing": False}, "the transmitter page is paused"),
        ({"message_id": None}, "the transmitter page has no message to play"),
        (
            {"received": (datetime.now(UTC) - timedelta(seconds=120)).isoformat()},
            "no transmitter page plays (none reported for 90 s)",
        ),
    ],
)
def test_a_paused_or_closed_page_shows_the_camera_nothing(stub, change, reason) -> None:
    stub.status({**GOOD, **change})
    showing = TransmitterClient(stub.url).showing()
    assert showing == Idle(reason)


def listed(message_id: str, profile: str, cells: int) -> dict:
    return {"id": message_id, "name": f"{message_id}.txt", "profile": profile, "cells": cells}


def test_until_a_page_reports_the_stand_in_plays_not_the_newest_upload(stub) -> None:
    sample, newest = listed("sample", "robust", 16), listed("newest", "fast", 12)
    stub.routes["/api/messages"] = json.dumps({"messages": [newest, sample]}).encode()
    stub.routes["/api/messages/sample"] = json.dumps(sample).encode()
    assert TransmitterClient(stub.url).showing().message_id == "newest"
    showing = TransmitterClient(stub.url, stand_in="sample").showing()
    assert (showing.message_id, showing.link, showing.frame_now) == (
        "sample",
        LinkSettings("robust", 16),
        0,
    )
    gone = TransmitterClient(stub.url, stand_in="deleted").showing()
    assert gone == Idle("no page has reported and message deleted is gone")


def test_a_server_that_does_not_speak_http_reads_as_unreachable() -> None:
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()

        def answer_garbage() -> None:
            connection, _ = listener.accept()
            with connection:
                connection.recv(4096)
                connection.sendall(b"HELLO THERE\r\n\r\n")

        threading.Thread(target=answer_garbage, daemon=True).start()
        client = TransmitterClient(f"http://127.0.0.1:{listener.getsockname()[1]}")
        with pytest.raises(OSError, match="answered /api/transmitter/status wrongly"):
            client.showing()


def test_screen_watch_keeps_its_link_and_says_why_once(stub, caplog) -> None:
    stub.status(GOOD)
    watch = ScreenWatch(TransmitterClient(stub.url), LinkSettings("paper", 8))
    assert watch.link == LinkSettings("fast", 12)
    with caplog.at_level(logging.INFO, logger="eventocc.receiver.live.screen"):
        for status in (BOGUS, BOGUS, BOGUS, {**GOOD, "cells": 16}):
            stub.status(status)
            watch.poll()
            if status is BOGUS:
                assert watch.link == LinkSettings("fast", 12), "the link stays as it was"
    assert watch.link == LinkSettings("fast", 16), "and follows the page again"
    refusals = [r for r in caplog.records if "unknown link profile 'bogus'" in r.message]
    assert len(refusals) == 1, caplog.text
    assert "keeping fast with 12 cells at 60 Hz" in refusals[0].message
    assert "answers again" in caplog.text


def test_a_receiver_starts_on_its_fallback_when_the_status_is_unusable(stub, caplog) -> None:
    stub.status(BOGUS)
    fallback = LinkSettings("robust", 16)
    assert TransmitterClient(stub.url).link_settings(fallback) == fallback
    assert "unknown link profile 'bogus'" in caplog.text
    assert "fast; assuming robust with 16 cells at 60 Hz until it answers" in caplog.text


class CountingPipeline:
    cell_px = detection_failure = None

    def __init__(self) -> None:
        self.chunks = 0
        self.stream = self

    def push(self, chunk: np.ndarray) -> list:
        self.chunks += 1
        return []

    def finish(self) -> list:
        return []

    def progress(self) -> dict:
        return {}


class ScriptedScreen:
    def __init__(self, links: list[LinkSettings]) -> None:
        self.links = links
        self.width, self.height = 64, 48
        self.link: LinkSettings | None = None

    def chunks(self):
        for i, link in enumerate(self.links):
            self.link = link
            yield make_events([i * 1000, i * 1000 + 999], [1, 2], [3, 4], [1, 0])


def test_a_rebuild_that_fails_keeps_the_pipeline_and_says_so_once(tmp_path, caplog) -> None:
    """A live camera's daemon follows the page through ``ScreenWatch``; where the receiver
    cannot be built for what it shows, the daemon goes on with the one it has."""
    robust, fast = LinkSettings("robust", 16), LinkSettings("fast", 12)
    built: list[LinkSettings] = []

    def build(link: LinkSettings) -> CountingPipeline:
        if link == fast:
            raise ValueError("no receiver for this screen")
        built.append(link)
        return CountingPipeline()

    screen = ScriptedScreen([robust] * 2 + [fast] * 3 + [robust, LinkSettings("paper", 8)])
    follower = LinkFollower(build, screen, robust)
    first = follower.pipeline()
    daemon = Daemon(screen, first, sink=_Drop(), output=OutputFolder(tmp_path), follower=follower)
    with caplog.at_level(logging.INFO, logger="eventocc.receiver.live.daemon"):
        daemon.run()
    assert built == [robust, LinkSettings("paper", 8)]
    assert first.chunks == 6, "the first pipeline ran on through the link it could not follow"
    assert follower.receiving == LinkSettings("paper", 8)
    refusals = [r for r in caplog.records if "cannot build a receiver" in r.message]
    assert len(refusals) == 1, caplog.text
    assert "fast with 12 cells at 60 Hz (no receiver for this screen); keeping robust" in (
        refusals[0].message
    )


class _Drop:
    def publish(self, report, *, durable: bool) -> None:
        pass


def test_the_virtual_cameras_daemon_outlives_every_status(stub, tmp_path) -> None:
    """A status no receiver can read stopped every daemon at its start, with rc 2."""
    stub.routes["/api/messages/0123456789ab"] = b'{"name": "m.txt"}'
    stub.routes["/api/messages/0123456789ab/content"] = b"a message"
    stub.status(BOGUS)
    daemon = DaemonProcess(stub.url, tmp_path / "out")
    try:
        daemon.wait_for("virtual camera waiting: ")
        daemon.wait_for("unknown link profile 'bogus'")
        stub.status({**GOOD, "cells": 5})
        daemon.wait_for("cells must be a whole number 8..128, got 5")
        stub.status(GOOD)  # the page plays something it can read: it follows
        daemon.wait_for("watching message 0123456789ab (fast, 12 cells, 60.0 Hz)")
        daemon.wait_for("switched to fast with 12 cells at 60 Hz: rebuilding")
        stub.status({**GOOD, "refresh_hz": float("inf")})  # json.dumps writes Infinity
        daemon.wait_for("refresh rate must be 1..1000 Hz, got inf")
        time.sleep(2)  # the camera asks every second: each reason is said once
        assert daemon.process.poll() is None
    finally:
        log = daemon.stop()
    assert daemon.process.returncode == 0, log
    assert log.count("unknown link profile 'bogus'") == 2, log  # at the start, and the camera
    assert log.count("got inf") == 1, log
