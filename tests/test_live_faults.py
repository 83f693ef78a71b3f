"""Faults over real websockets on loopback: the server or the daemon killed mid-stream (SIGKILL)
and restarted, and a daemon with the wrong token. Nothing durable may be lost or doubled."""

from __future__ import annotations

import hashlib
import json
import signal
import socket
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from eventocc.occ.report import MessageReport, PoseReport, TrackingState, public_receiver_id
from eventocc.occ.stream import ReceivedMessage
from eventocc.receiver.live.publisher import Publisher
from eventocc.receiver.live.spool import Spool
from tests.live_clients import wait_until

TOKEN = "fault-token"
ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def get_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.load(response)


class ServerProcess:
    """``eventocc-server`` as a child process that can be killed and started again."""

    def __init__(self, data_dir: Path, port: int) -> None:
        self.data_dir, self.port = data_dir, port
        self.url = f"http://127.0.0.1:{port}"
        self.process: subprocess.Popen | None = None

    def start(self) -> ServerProcess:
        command = [
            sys.executable,
            "-m",
            "server",
            "--port",
            str(self.port),
            "--data-dir",
            str(self.data_dir),
            "--token",
            TOKEN,
        ]
        self.process = subprocess.Popen(
            command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        wait_until(self.healthy, what="the server to start")
        return self

    def healthy(self) -> bool:
        try:
            return get_json(self.url + "/healthz")["status"] == "ok"
        except (OSError, urllib.error.URLError):
            return False

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)

    def receptions(self) -> list[dict]:
        return get_json(self.url + "/api/receptions?limit=1000")["receptions"]


@pytest.fixture
def server_process(tmp_path):
    server = ServerProcess(tmp_path / "server-data", free_port()).start()
    yield server
    if server.process.poll() is None:
        server.kill()


def message(i: int) -> MessageReport:
    data = f"message number {i}".encode()
    digest = hashlib.sha256(data).hexdigest()
    return MessageReport.of(ReceivedMessage(f"m{i}.txt", data, digest, i, "robust"))


def pose(t_us: int) -> PoseReport:
    return PoseReport(
        t_us=t_us,
        position=(0.0, 0.0, -1.0),
        quaternion_xyzw=(0, 0, 0, 1.0),
        state=TrackingState.TRACKING,
        verified=True,
    )


def test_server_killed_and_restarted_mid_stream_loses_nothing(server_process, tmp_path) -> None:
    spool = Spool(tmp_path / "rx" / "spool.db")
    publisher = Publisher(
        "ws" + server_process.url.removeprefix("http"), spool, token=TOKEN, backoff_s=(0.05, 0.5)
    ).start()
    try:
        for i in range(3):
            publisher.publish(message(i), durable=True)
            publisher.publish(pose(i * 10_000), durable=True)
        wait_until(lambda: len(spool) == 0, what="the first reports to be acknowledged")

        server_process.kill()
        for i in range(3, 6):  # the server is away: these wait in the spool
            publisher.publish(message(i), durable=True)
            publisher.publish(pose(i * 10_000), durable=True)
        wait_until(lambda: not publisher.stats.connected, what="the publisher to see it gone")
        assert len(spool) == 6

        server_process.start()
        wait_until(lambda: len(spool) == 0, what="the spool to drain after the restart")
    finally:
        publisher.close()
        spool.close()
    names = sorted(r["name"] for r in server_process.receptions())
    assert names == [f"m{i}.txt" for i in range(6)], "every message exactly once"
    assert publisher.stats.connections == 2
    with urllib.request.urlopen(
        f"{server_process.url}/api/receivers/{public_receiver_id(spool.receiver_id)}/trajectory"
    ) as response:
        rows = response.read().decode().splitlines()[1:]
    assert [row.split()[0] for row in rows] == [f"0.0{i}0000" for i in range(6)]


DAEMON_SCRIPT = """
import sys, time
from pathlib import Path
sys.path.insert(0, {tests!r})
from test_live_faults import message
from eventocc.receiver.live.publisher import Publisher
from eventocc.receiver.live.spool import Spool
from tests.live_clients import wait_until

spool = Spool(Path({out!r}) / "spool.db")
publisher = Publisher({url!r}, spool, token={token!r}, backoff_s=(0.05, 0.5)).start()
for i in range({first}, {first} + 1000):
    publisher.publish(message(i), durable=True)
    print(i, flush=True)  # on disk in the spool by now
    time.sleep(0.02)
"""


def start_daemon(url: str, out: Path, first: int) -> subprocess.Popen:
    script = DAEMON_SCRIPT.format(
        tests=str(ROOT / "tests"), out=str(out), url=url, token=TOKEN, first=first
    )
    return subprocess.Popen(
        [sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )


def read_published(daemon: subprocess.Popen, count: int) -> list[int]:
    return [int(daemon.stdout.readline()) for _ in range(count)]


def read_rest_after_kill(daemon: subprocess.Popen) -> list[int]:
    """Every number the killed daemon printed whole: each one was in its spool before the kill."""
    return [
        int(line) for line in daemon.stdout.read().splitlines(keepends=True) if line.endswith("\n")
    ]


def test_daemon_killed_and_restarted_keeps_server_state_and_its_spool(serve_app, tmp_path) -> None:
    base_url, app = serve_app(token=TOKEN)
    ws_url, out = "ws" + base_url.removeprefix("http"), tmp_path / "daemon"

    def stored() -> set[str]:
        return {r.name for r in app.state.live.receptions.receptions(1000)}

    first = start_daemon(ws_url, out, first=0)
    published = read_published(first, 15)
    # A loaded machine may take longer than those 15 messages to connect: the kill waits for the
    # first delivery, and still lands mid-stream, as the daemon publishes for 20 s.
    wait_until(lambda: bool(stored()), what="a first message to be stored")
    first.send_signal(signal.SIGKILL)  # some of its messages are not acknowledged yet
    first.wait(10)
    published += read_rest_after_kill(first)
    first.stdout.close()
    stored_before = stored()

    second = start_daemon(ws_url, out, first=1000)
    try:
        published += read_published(second, 5)
        expected = {f"m{i}.txt" for i in published}

        wait_until(lambda: expected <= stored(), what="every published message to be stored")
    finally:
        second.send_signal(signal.SIGKILL)
        second.wait(10)
        second.stdout.close()
    receptions = app.state.live.receptions.receptions(1000)
    assert stored_before <= {r.name for r in receptions}, "the server kept what it had"
    assert len({r.receiver for r in receptions}) == 1, "the restarted daemon is the same receiver"
    names = [r.name for r in receptions]
    assert len(names) == len(set(names)), "nothing stored twice"


def test_wrong_token_stops_the_publisher_for_good(serve_app, tmp_path, caplog) -> None:
    base_url, _ = serve_app(token=TOKEN)
    fatal = threading.Event()
    spool = Spool(tmp_path / "spool.db")
    publisher = Publisher(
        "ws" + base_url.removeprefix("http"),
        spool,
        token="wrong",
        backoff_s=(0.05, 0.1),
        on_fatal=fatal.set,
    ).start()
    try:
        assert fatal.wait(10)
        publisher._thread.join(10)  # its loop is closed now: publish and close must still work
        publisher.publish(message(1), durable=True)
        assert len(spool) == 1, "a report published after the refusal waits for the next run"
    finally:
        publisher.close(drain_timeout_s=0.5)
        spool.close()
    assert "the server refused our token" in str(publisher.error)
    assert publisher.stats.connections == 0


@pytest.mark.parametrize("url", ["http://localhost:8000", "localhost:8000"])
def test_publisher_needs_a_websocket_url(tmp_path, url: str) -> None:
    spool = Spool(tmp_path / "spool.db")
    with pytest.raises(ValueError, match="must start with ws:// or wss://"):
        Publisher(url, spool)
    spool.close()


def test_close_gives_up_on_an_absent_server(tmp_path) -> None:
    # A close that waited for the server forever would hang here (the suite's timeout).
    spool = Spool(tmp_path / "spool.db")
    publisher = Publisher(f"ws://127.0.0.1:{free_port()}", spool, backoff_s=(0.05, 0.1)).start()
    publisher.publish(message(1), durable=True)
    publisher.close(drain_timeout_s=0.5)
    assert not publisher.stats.connected
    assert len(spool) == 1, "undelivered reports stay in the spool for the next run"
    spool.close()
