"""``make demo`` run again on a data folder holding other uploads: its virtual camera still
shows the sample, which the dashboard sees verified; and a transmitter page that pauses (or is
closed: it reports itself paused as it goes) leaves the receiver idle, saying why, not
"tracking" with a frozen pose; it receives again once the page plays."""

from __future__ import annotations

import json
import subprocess
import time
import urllib.request
from pathlib import Path

from websockets.sync.client import connect

from eventocc.server import demo
from eventocc.server.settings import Settings
from tests.test_demo_motion import free_port, running_demo, stop

VERIFIED_WITHIN_S = 120.0
"""Generous: the tests share the machine (the first-run benchmark measures it)."""


def upload_a_larger_message(data_dir: Path) -> str:
    """What an earlier demo run left behind: an upload newer than the sample."""
    settings = Settings(data_dir=data_dir, port=0)
    server, thread = demo.start_server(settings)
    try:
        base_url = demo.bound_url(server)
        demo.upload_sample(base_url, settings)
        request = urllib.request.Request(
            f"{base_url}/api/messages?name=large.bin",
            data=json.dumps({"text": "x" * 200_000}).encode(),
            headers={"Content-Type": "application/json"},
            method="POST",
        )
        with urllib.request.urlopen(request) as response:
            return json.load(response)["id"]
    finally:
        server.should_exit = True
        thread.join(10)


def post_status(port: int, status: dict) -> None:
    request = urllib.request.Request(
        f"http://127.0.0.1:{port}/api/transmitter/status",
        data=json.dumps(status).encode(),
        headers={"Content-Type": "application/json"},
        method="POST",
    )
    urllib.request.urlopen(request).close()


def wait_for(ws, wanted, within_s: float) -> dict | None:
    """The first dashboard update for which ``wanted`` holds, within ``within_s``."""
    until = time.monotonic() + within_s
    while time.monotonic() < until:
        try:
            update = json.loads(ws.recv(timeout=1.0))
        except TimeoutError:
            continue
        if wanted(update):
            return update
    return None


def test_a_restarted_demo_shows_the_sample_and_a_paused_page_leaves_it_idle(tmp_path) -> None:
    large_id = upload_a_larger_message(tmp_path)
    port = free_port()
    with running_demo(tmp_path, port, stdout=subprocess.PIPE) as running:
        lines = [running.stdout.readline() for _ in range(2)]
        sample_id = lines[1].rsplit("id=", 1)[1].strip()
        assert sample_id != large_id
        try:
            with connect(f"ws://127.0.0.1:{port}/ws/dashboard") as ws:
                verified = wait_for(
                    ws,
                    lambda u: u["type"] == "reception" and u["message_id"] is not None,
                    VERIFIED_WITHIN_S,
                )
                assert verified is not None, "no message verified"
                assert verified["message_id"] == sample_id, "it watched another upload"
                facts = f"http://127.0.0.1:{port}/api/messages/{sample_id}"
                with urllib.request.urlopen(facts) as response:
                    sample = json.load(response)
                page = {"message_id": sample_id, "profile": sample["profile"]}
                page["cells"] = sample["cells"]
                post_status(port, {**page, "playing": False})
                idle = wait_for(ws, lambda u: u["type"] == "health" and u["state"] == "idle", 30.0)
                assert idle is not None, "the receiver did not go idle for a paused page"
                assert idle["waiting"] == "the transmitter page is paused"
                post_status(port, {**page, "playing": True, "frame_index": 0})
                live = wait_for(ws, lambda u: u["type"] == "health" and u["waiting"] is None, 30)
                assert live is not None and live["state"] != "idle"
        finally:
            log = stop(running)
    assert "virtual camera waiting: the transmitter page is paused" in log
