"""End to end: upload over REST -> transmitter status -> the receiver daemon (real CLI, real
pipeline) on the virtual camera -> server -> the dashboard in headless Chromium."""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from eventocc.receiver.live.virtual_camera import DISTANCE_M

pytestmark = pytest.mark.browser

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "e2e-token"
TEXT = "Hello from the virtual event camera, through the whole live system!"


def request(base_url: str, path: str, body: dict, **headers: str) -> dict:
    req = urllib.request.Request(
        base_url + path,
        data=json.dumps(body).encode(),
        headers={"Content-Type": "application/json", **headers},
        method="POST",
    )
    with urllib.request.urlopen(req, timeout=10) as response:
        return json.load(response)


def test_uploaded_message_reaches_the_dashboard_verified_with_the_pose(
    serve_app, browser, artifacts, tmp_path
):
    from playwright.sync_api import expect

    base_url, _ = serve_app(token=TOKEN)
    message = request(
        base_url, "/api/messages?name=hello.txt", {"text": TEXT}, Authorization=f"Bearer {TOKEN}"
    )
    request(
        base_url,
        "/api/transmitter/status",
        {  # what a transmitter page would report
            "message_id": message["id"],
            "profile": message["profile"],
            "cells": message["cells"],
            "playing": True,
            "frame_index": 0,
            "refresh_hz": 60.0,
        },
    )
    daemon = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "eventocc.receiver.cli",
            "receive",
            "--source",
            "sim:",
            "--motion",
            "static",  # a still camera keeps up with real time: the goodput checked is the link's
            "--server",
            base_url,
            "--out",
            str(tmp_path / "out"),
        ],
        cwd=ROOT,
        env={**os.environ, "EVENTOCC_TOKEN": TOKEN, "NUMBA_NUM_THREADS": "1"},
        stderr=subprocess.PIPE,
        text=True,
    )
    digest = hashlib.sha256(TEXT.encode()).hexdigest()
    try:
        page = browser.new_page(viewport={"width": 1100, "height": 760})
        page.goto(f"{base_url}/dashboard")
        expect(page.locator("#connection")).to_have_text("live")
        row = page.locator(f'#receptions li[data-sha256="{digest}"]')
        expect(row).to_contain_text("hello.txt", timeout=180_000)
        expect(row).to_contain_text("matches upload")
        expect(row).to_contain_text("message at")  # its own rate, not the link's goodput
        expect(page.locator("#pose-readout")).to_contain_text("distance", timeout=30_000)
        expect(page.locator("#tracking-state")).to_have_text("tracking", timeout=30_000)
        # Verified frames keep flowing after the message completed: goodput is not zero.
        goodput = page.locator("#goodput-value")
        expect(goodput).to_have_text(re.compile(r"^[1-9][\d.]* kbit/s$"), timeout=30_000)
        page.wait_for_timeout(1500)  # let the sparklines take a few samples
        page.screenshot(path=str(artifacts / "dashboard.png"), full_page=True)
        readout = page.locator("#pose-readout").text_content()
        href = row.locator("a").get_attribute("href")
        # A transmitter page with nothing to play shows the camera nothing: idle, and why.
        paused = {"message_id": None, "playing": False}
        page.request.post(f"{base_url}/api/transmitter/status", data=paused)
        expect(page.locator("#tracking-state")).to_have_text(
            "idle: the transmitter page has no message to play", timeout=30_000
        )
    finally:
        daemon.send_signal(signal.SIGTERM)
        _, log = daemon.communicate(timeout=60)
    assert daemon.returncode == 0, log
    with urllib.request.urlopen(base_url + href) as response:
        assert response.read() == TEXT.encode()
    distance = float(readout.split("distance")[1].split()[0])
    # A still camera's PnP pose is within a centimetre (test_pipeline_e2e); the readout has two
    # decimals.
    assert distance == pytest.approx(DISTANCE_M, abs=0.015), (
        f"the virtual camera stands {DISTANCE_M} m away, the dashboard says {readout}"
    )
    assert (tmp_path / "out" / "messages" / f"{digest[:12]}-hello.txt").read_text() == TEXT
    assert "message 'hello.txt' complete" in log
