"""Auto mode live, end to end: the real server's controller, a stand-in transmitter page that
follows its choice as the page does, and the receiver daemon (real CLI, real pipeline) on the
virtual camera, which simulates each packed segment the page reports. The settings step up from
N = 16, and the message, sent across the change, comes out verified."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.calibration import save_calibration
from eventocc.receiver.camera import CameraModel

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
MESSAGE = np.random.default_rng(3).integers(0, 256, 12_000, dtype=np.uint8).tobytes()


def call(base_url: str, method: str, path: str, body: bytes, content_type: str) -> dict:
    request = urllib.request.Request(
        base_url + path, data=body, headers={"Content-Type": content_type}, method=method
    )
    with urllib.request.urlopen(request, timeout=10) as response:
        return json.load(response)


class StandInPage:
    """What the transmitter page does in auto mode, without a browser: report the status four
    times a second and start a packed segment from the next unsent symbol at each choice."""

    def __init__(self, base_url: str, message_id: str) -> None:
        self.base_url, self.message_id = base_url, message_id
        self.segment = {"profile": "robust", "cells": 16, "symbol_start": 0}
        self.started = time.monotonic()
        self.segments: list[dict] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def frame_index(self) -> int:
        return int((time.monotonic() - self.started) * 60)

    def run(self) -> None:
        while not self.stop.wait(0.25):
            status = {
                "message_id": self.message_id,
                **self.segment,
                "packed": True,
                "hold": 1,
                "playing": True,
                "frame_index": self.frame_index(),
                "refresh_hz": 60.0,
            }
            reply = call(
                self.base_url,
                "POST",
                "/api/transmitter/status",
                json.dumps(status).encode(),
                "application/json",
            )
            choice = reply["link"]["choice"]
            if choice and (choice["profile"], choice["cells"]) != (
                self.segment["profile"],
                self.segment["cells"],
            ):
                shown = self.frame_index()
                old = StreamEncoder(
                    b"x", profile=self.segment["profile"], cells=self.segment["cells"], packed=True
                )
                self.segment = {
                    "profile": choice["profile"],
                    "cells": choice["cells"],
                    "symbol_start": self.segment["symbol_start"] + shown * old.symbols_per_frame,
                }
                self.segments.append(dict(self.segment))
                self.started = time.monotonic()


def test_auto_mode_steps_up_live_and_the_message_arrives(serve_app, tmp_path) -> None:
    # The virtual camera's sensor reads smaller cells than the EVK4 auto mode assumes.
    base_url, _ = serve_app(auto_min_px_robust=4.0, auto_min_px_fast=5.0)
    message = call(
        base_url,
        "POST",
        "/api/messages?name=auto.bin&profile=robust&cells=16",
        MESSAGE,
        "application/octet-stream",
    )
    call(base_url, "PUT", "/api/transmitter/mode", b'{"mode": "auto"}', "application/json")
    page = StandInPage(base_url, message["id"])
    page.thread.start()
    calibration = tmp_path / "camera.yaml"
    save_calibration(CameraModel.paper().binned(640, 360), calibration)  # ~10 px a cell at N = 16
    daemon = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "eventocc.receiver.cli",
            "receive",
            "--source",
            "sim:",
            "--motion",
            "static",
            "--calibration",
            str(calibration),
            "--server",
            base_url,
            "--out",
            str(tmp_path / "out"),
        ],
        cwd=ROOT,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
        stderr=subprocess.PIPE,
        text=True,
    )
    digest = hashlib.sha256(MESSAGE).hexdigest()
    try:
        deadline = time.monotonic() + 240
        received = []
        while time.monotonic() < deadline and not received:
            time.sleep(1)
            with urllib.request.urlopen(base_url + "/api/receptions") as response:
                received = [r for r in json.load(response)["receptions"] if r["sha256"] == digest]
        with urllib.request.urlopen(base_url + "/api/transmitter/mode") as response:
            mode = json.load(response)
    finally:
        page.stop.set()
        daemon.send_signal(signal.SIGTERM)
        _, log = daemon.communicate(timeout=60)
    assert received, f"no message; mode {mode}; daemon log:\n{log[-3000:]}"
    assert received[0]["verified"], received
    assert page.segments and page.segments[0]["cells"] > 16, (page.segments, mode["reason"])
    # The message came out after the change: its symbols spanned both segments.
    assert "rebuilding the receiver" in log
    assert mode["history"], mode
