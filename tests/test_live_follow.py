"""The receiver daemon (real CLI, virtual camera, real server) follows the transmitter when it
switches to a message with other link settings, unless ``--profile/--cells`` pin them; a live
camera's daemon follows the page through ``ScreenWatch``."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from eventocc.occ.profiles import LinkSettings
from eventocc.receiver.live.screen import ScreenWatch, TransmitterClient
from tests.live_clients import post_json

ROOT = Path(__file__).resolve().parent.parent


def play(base_url: str, message: dict, refresh_hz: float = 60.0) -> None:
    """Report what a transmitter page showing ``message`` would report."""
    status = {"message_id": message["id"], "profile": message["profile"], "playing": True}
    post_json(
        base_url,
        "/api/transmitter/status",
        {**status, "cells": message["cells"], "frame_index": 0, "refresh_hz": refresh_hz},
    )


class DaemonProcess:
    """``eventocc-receiver receive`` on the virtual camera, its log read as it comes."""

    def __init__(self, base_url: str, out: Path, *options: str) -> None:
        command = [sys.executable, "-m", "eventocc.receiver.cli", "receive", "--source", "sim:"]
        command += ["--motion", "static"]  # quick to lock on each stream it follows
        command += ["--server", base_url, "--out", str(out), *options]
        self.process = subprocess.Popen(
            command,
            cwd=ROOT,
            env={**os.environ, "NUMBA_NUM_THREADS": "1"},
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stderr:
            self.lines.append(line)

    def wait_for(self, text: str, timeout_s: float = 60.0) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in self.lines:
                if text in line:
                    return line
            if self.process.poll() is not None:
                break
            time.sleep(0.1)
        raise AssertionError(f"the daemon never logged {text!r}:\n{''.join(self.lines)}")

    def stop(self) -> str:
        self.process.send_signal(signal.SIGTERM)
        self.process.wait(60)
        self._reader.join(10)
        return "".join(self.lines)


@pytest.mark.parametrize("pinned", [(), ("--cells", "16")])
def test_daemon_rebuilds_its_receiver_when_the_transmitter_switches(
    serve_app, tmp_path, pinned: tuple[str, ...]
) -> None:
    base_url, _ = serve_app()
    robust = post_json(base_url, "/api/messages?name=a.txt&profile=robust&cells=16", {"text": "a"})
    fast = post_json(base_url, "/api/messages?name=b.txt&profile=fast&cells=12", {"text": "b"})
    play(base_url, robust)
    daemon = DaemonProcess(base_url, tmp_path / "out", *pinned)
    try:
        daemon.wait_for("robust with 16 cells at 60 Hz")
        daemon.wait_for(f"watching message {robust['id']}")
        play(base_url, fast, refresh_hz=143.9)  # a 144 Hz page's measured rate
        daemon.wait_for(f"watching message {fast['id']} (fast, 12 cells, 143.9 Hz)")
        if pinned:
            daemon.wait_for("sends fast with 12 cells at 144 Hz but the receiver is pinned")
        cells = 16 if pinned else 12
        daemon.wait_for(f"switched to fast with {cells} cells at 144 Hz: rebuilding")
    finally:
        log = daemon.stop()
    assert daemon.process.returncode == 0, log


def test_screen_watch_follows_the_page_and_survives_an_absent_server(serve_app, caplog) -> None:
    base_url, _ = serve_app()
    watch = ScreenWatch(TransmitterClient(base_url), LinkSettings("paper", 8), every_s=0.05)
    assert watch.link == LinkSettings("robust", 16), "nothing plays: the server's defaults"
    watch.start()
    try:
        fast = post_json(base_url, "/api/messages?name=b.txt&profile=fast&cells=12", {"text": "b"})
        play(base_url, fast, refresh_hz=143.9)
        deadline = time.monotonic() + 10
        while watch.link != LinkSettings("fast", 12, 144) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert watch.link == LinkSettings("fast", 12, 144)
    finally:
        watch.stop()

    nobody = ScreenWatch(TransmitterClient("http://127.0.0.1:9"), LinkSettings("paper", 8))
    assert nobody.link == LinkSettings("paper", 8)
    assert "assuming" in caplog.text and "until it answers" in caplog.text


def test_receive_waits_for_a_server_that_is_down_at_its_start(serve_app, tmp_path) -> None:
    with socket.socket() as sock:  # a free port, nobody listening yet
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    base_url = f"http://127.0.0.1:{port}"
    daemon = DaemonProcess(base_url, tmp_path / "out")
    try:
        daemon.wait_for("assuming robust with 16 cells at 60 Hz until it answers")
        daemon.wait_for("virtual camera waiting: server unreachable")
        daemon.wait_for("retrying in 0.", timeout_s=10)  # the publisher backs off
        serve_app(port=port)
        message = post_json(
            base_url, "/api/messages?name=a.txt&profile=fast&cells=12", {"text": "a"}
        )
        play(base_url, message)
        daemon.wait_for(f"watching message {message['id']} (fast, 12 cells, 60.0 Hz)")
        daemon.wait_for("switched to fast with 12 cells at 60 Hz: rebuilding")
        daemon.wait_for(f"connected to ws://127.0.0.1:{port}/ws/receiver")
    finally:
        log = daemon.stop()
    assert daemon.process.returncode == 0, log
