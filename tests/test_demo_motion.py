"""``make demo``: its virtual camera is hand-held, so the dashboard sees the pose move; and
Ctrl-C stops all of it."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from websockets.sync.client import connect

from eventocc.receiver.live.virtual_camera import DISTANCE_M, default_camera
from eventocc.receiver.pipeline.config import ReceiverConfig

ROOT = Path(__file__).resolve().parent.parent
MOVING_WITHIN_S = 30.0
DECODED_WITHIN_S = 30.0
MIN_TRAVEL_M = 0.05
"""The gentle hand moves the camera this far within ``MOVING_WITHIN_S`` (29 cm in a run)."""
DEPTH_WANDER = 0.08
"""The hand-held path keeps the camera within this share of ``DISTANCE_M`` of the marker centre
(its depth wander); the sideways shift and the pose's own error add at most ``DISTANCE_SLACK_M``."""
DISTANCE_SLACK_M = 0.02


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def dashboard_poses(port: int, first_within_s: float, then_s: float) -> np.ndarray:
    """Positions of the pose updates a dashboard sees: from the first (which must come within
    ``first_within_s``) for ``then_s`` more."""
    deadline = time.monotonic() + 60.0
    while True:
        try:
            ws = connect(f"ws://127.0.0.1:{port}/ws/dashboard")
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)
    positions, until = [], time.monotonic() + first_within_s
    with ws:
        while time.monotonic() < until:
            try:
                update = json.loads(ws.recv(timeout=1.0))
            except TimeoutError:
                continue
            if update["type"] == "pose":
                if not positions:
                    until = time.monotonic() + then_s
                positions.append(update["position"])
    return np.array(positions).reshape(-1, 3)


@contextmanager
def running_demo(tmp_path: Path, port: int, **popen) -> Iterator[subprocess.Popen]:
    """``eventocc.server.demo`` in its own process group, killed whole at the end (anything of it
    left running, the demo or its receiver, would load the machine for the tests after it)."""
    demo = subprocess.Popen(
        [sys.executable, "-m", "eventocc.server.demo"],
        cwd=ROOT,
        env={**os.environ, "EVENTOCC_PORT": str(port), "EVENTOCC_DATA_DIR": str(tmp_path)},
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        **popen,
    )
    try:
        yield demo
    finally:
        with suppress(ProcessLookupError):  # nothing left of it
            os.killpg(demo.pid, signal.SIGKILL)
        demo.wait()


def stop(demo: subprocess.Popen, within_s: float = 60.0) -> str:
    """Ctrl-C the demo; its log once it exited, which it must within ``within_s``."""
    demo.send_signal(signal.SIGINT)
    try:
        _, log = demo.communicate(timeout=within_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the demo did not exit within {within_s:.0f} s of Ctrl-C")
    return log


def test_the_demo_shows_the_message_decoded_and_the_pose_moving(tmp_path) -> None:
    port = free_port()
    started = datetime.now(UTC)
    with running_demo(tmp_path, port, stdout=subprocess.DEVNULL) as demo:
        try:
            positions = dashboard_poses(port, first_within_s=60.0, then_s=MOVING_WITHIN_S)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/receptions") as response:
                receptions = json.load(response)["receptions"]
        finally:
            log = stop(demo)
    assert len(positions), f"no pose reached the dashboard:\n{log}"
    travel = np.linalg.norm(positions - positions[0], axis=1).max()
    assert travel >= MIN_TRAVEL_M, f"the camera stood still ({travel * 100:.1f} cm):\n{log}"
    size = ReceiverConfig(default_camera()).marker_size_m
    distance = np.linalg.norm(positions - [size / 2, size / 2, 0.0], axis=1)  # from the centre
    near, far = DISTANCE_M * (1 - DEPTH_WANDER), DISTANCE_M * (1 + DEPTH_WANDER)
    assert near - DISTANCE_SLACK_M <= distance.min() and distance.max() <= far + DISTANCE_SLACK_M
    assert np.median(distance) == pytest.approx(DISTANCE_M, abs=DISTANCE_SLACK_M)
    verified = [r for r in receptions if r["message_id"] is not None]
    assert verified, f"no verified message:\n{log}"
    took = datetime.fromisoformat(verified[0]["received"]) - started
    assert took.total_seconds() <= DECODED_WITHIN_S, f"decoded after {took}"


def test_ctrl_c_stops_the_demo_started_in_the_background(tmp_path) -> None:
    """A shell starts background jobs with SIGINT ignored; ``kill -INT`` must still stop the
    demo, and its receiver with it."""
    with running_demo(
        tmp_path,
        free_port(),
        stdout=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    ) as demo:
        for line in demo.stdout:
            if line.startswith("Ctrl-C to stop"):
                break
        log = stop(demo, within_s=30.0)
        assert demo.returncode == 0, log
        with pytest.raises(ProcessLookupError):  # nothing left in its process group
            os.killpg(demo.pid, 0)
