"""Hostile input to the live routes over real websockets: frames outside the protocol, numbers
JSON cannot hold, a receiver's identity claimed by another connection, bursts of reports.
None of it may answer with a traceback, reach the dashboards or touch another receiver."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import http.server
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect as sync_connect

from eventocc.occ.report import HealthReport, Hello, TrackingState, public_receiver_id
from eventocc.server.receptions import ReceptionStore
from tests.live_clients import (
    RX_1,
    TOKEN,
    Dashboard,
    ServerLog,
    close_code,
    envelope,
    get,
    open_receiver,
    pose,
    post_json,
    strict_json,
    wait_until,
    ws_url,
)

ROOT = Path(__file__).resolve().parent.parent

HELLO = Hello(receiver_id="rx-1", token=TOKEN).model_dump_json()
POSE = json.loads(pose(1).model_dump_json())


def pose_with(**fields: object) -> str:
    """A pose report's JSON with some fields replaced by raw JSON text."""
    text = json.dumps({"seq": 1, "report": {**POSE, **dict.fromkeys(fields, "@")}})
    for value in fields.values():
        text = text.replace('"@"', str(value), 1)
    return text


# --- frames outside the protocol ---------------------------------------------------------------
MALFORMED = {
    "binary frame": (b"\x00\x01", 1003, "not binary"),
    "200k nested brackets": ("[" * 200_000 + "]" * 200_000, 1007, "expected"),
    "seq past 64 bits": (envelope(2**63, pose(1)), 1007, "seq must be an integer"),
    "seq a boolean": (envelope(True, pose(1)), 1007, "seq must be an integer"),
    "seq a float": (envelope(1.0, pose(1)), 1007, "seq must be an integer"),
    "NaN in a pose": (pose_with(position="[NaN, 0, 0]"), 1007, "NaN is not JSON"),
    "Infinity in a pose": (pose_with(position="[0, -Infinity, 0]"), 1007, "is not JSON"),
    "a number past any float": (pose_with(position="[1e400, 0, 0]"), 1007, "out of range"),
}


@pytest.mark.parametrize("case", MALFORMED.values(), ids=MALFORMED.keys())
def test_a_frame_outside_the_protocol_closes_with_a_reason(serve_app, case) -> None:
    base_url, app = serve_app(token=TOKEN)
    frame, code, reason = case
    with ServerLog() as server_log:
        closed_with = asyncio.run(close_code(base_url, HELLO, frame))
    assert closed_with[0] == code and reason in closed_with[1]
    assert server_log.errors() == []
    assert app.state.live.receptions.poses(RX_1) == []


def test_a_number_past_64_bits_fails_the_schema_and_is_acked(serve_app) -> None:
    base_url, app = serve_app(token=TOKEN)

    async def scenario() -> dict:
        ws, _ = await open_receiver(base_url)
        await ws.send(pose_with(t_us=2**70))
        ack = json.loads(await ws.recv())
        await ws.close()
        return ack

    with ServerLog() as server_log:
        assert asyncio.run(scenario()) == {"type": "ack", "seq": 1}
    assert server_log.errors() == []
    assert app.state.live.reports_rejected == 1
    assert app.state.live.receptions.poses(RX_1) == []


def test_no_dashboard_ever_gets_a_number_json_cannot_hold(serve_app) -> None:
    base_url, _ = serve_app(token=TOKEN)
    hostile = [pose_with(position="[NaN, 0, 0]"), pose_with(quaternion_xyzw="[0, 0, 0, 1e999]")]

    async def scenario() -> list[object]:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            for frame in hostile:
                await close_code(base_url, HELLO, frame)
            ws, _ = await open_receiver(base_url)
            await ws.send(envelope(7, pose(7)))
            await ws.recv()
            await ws.close()
            updates = []
            while not updates or updates[-1].get("t_us") != 7:
                updates.append(strict_json(await asyncio.wait_for(dash.recv(), 5)))
            return updates

    updates = asyncio.run(scenario())
    assert [u["t_us"] for u in updates if u["type"] == "pose"] == [7]
    tum = get(base_url, f"/api/receivers/{RX_1}/trajectory").decode().splitlines()
    assert len(tum) == 2 and tum[1].startswith("0.000007 ")


def test_binary_frames_neither_break_the_transmitter_nor_the_dashboard_socket(serve_app) -> None:
    base_url, _ = serve_app()

    async def scenario() -> tuple[int, dict]:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            await dash.send(b"\x00")  # viewers send nothing we need: ignored
            async with connect(ws_url(base_url, "/ws/transmitter")) as tx:
                await tx.send(b"\x00")
                with pytest.raises(ConnectionClosed) as closed:
                    await asyncio.wait_for(tx.recv(), 5)
            async with connect(ws_url(base_url, "/ws/transmitter")) as tx:
                await tx.send(json.dumps({"frame_index": 3}))
            while (update := json.loads(await asyncio.wait_for(dash.recv(), 5)))["type"] != (
                "transmitter"
            ):
                pass
            return closed.value.rcvd.code, update

    with ServerLog() as server_log:
        code, update = asyncio.run(scenario())
    assert code == 1003 and update["frame_index"] == 3
    assert server_log.errors() == []


@pytest.mark.parametrize(
    "status",
    [
        {"profile": "bogus", "cells": 16},
        {"profile": "robust", "cells": 1},
        {"refresh_hz": 1e-9},
        {"profile": "robust", "cells": 8},
    ],
)
def test_a_status_no_receiver_can_follow_is_refused_over_the_websocket(serve_app, status) -> None:
    base_url, _ = serve_app()
    good = {"profile": "fast", "cells": 24, "refresh_hz": 60.0, "frame_index": 5}

    async def scenario() -> dict:
        async with connect(ws_url(base_url, "/ws/transmitter")) as tx:
            await tx.send(json.dumps(good))
            await tx.send(json.dumps(status))
            return json.loads(await asyncio.wait_for(tx.recv(), 5))

    with ServerLog() as server_log:
        error = asyncio.run(scenario())
    assert error["type"] == "error" and error["detail"][0]["msg"]
    latest = json.loads(get(base_url, "/api/transmitter/status"))
    assert {k: latest[k] for k in good} == good, "the last good status stands"
    assert server_log.errors() == []


# --- a receiver's identity ---------------------------------------------------------------------
def test_nothing_the_server_shows_holds_a_receivers_secret_id(serve_app) -> None:
    base_url, _ = serve_app(token=TOKEN)

    async def scenario() -> list[str]:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            ws, _ = await open_receiver(base_url, "secret-of-rx")
            await ws.send(envelope(1, pose(1)))
            await ws.recv()
            seen = [await asyncio.wait_for(dash.recv(), 5) for _ in range(2)]
            await ws.close()
            return seen

    seen = asyncio.run(scenario())
    public = public_receiver_id("secret-of-rx")
    assert public in seen[0] and public in seen[1]
    shown = "".join(seen) + get(base_url, f"/api/receivers/{public}/trajectory").decode()
    assert "secret-of-rx" not in shown + get(base_url, "/metrics").decode()


def test_a_receiver_seen_on_the_dashboard_cannot_be_spoken_for(serve_app) -> None:
    """The attack: read a receiver's id off the dashboard, connect with it and send seq 2^62,
    so that the server skips the victim's later reports as replays and tells the victim, when
    it reconnects, to delete its spool."""
    base_url, app = serve_app(token=TOKEN)
    receptions = app.state.live.receptions

    async def scenario() -> tuple[dict, int]:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            victim, _ = await open_receiver(base_url, "victims-secret")
            await victim.send(envelope(1, pose(1)))
            await victim.recv()
            while (update := json.loads(await asyncio.wait_for(dash.recv(), 5)))["type"] != "pose":
                pass
        attacker, _ = await open_receiver(base_url, update["receiver"])
        await attacker.send(envelope(2**62, pose(99)))
        await attacker.recv()
        await attacker.close()
        await victim.send(envelope(2, pose(2)))
        ack = json.loads(await victim.recv())
        await victim.close()
        again, welcome = await open_receiver(base_url, "victims-secret")
        await again.close()
        return ack, welcome["last_seq"]

    ack, last_seq = asyncio.run(scenario())
    assert ack == {"type": "ack", "seq": 2}
    assert last_seq == 2, "the victim keeps every report the server has not stored"
    assert [row[0] for row in receptions.poses(public_receiver_id("victims-secret"))] == [1, 2]


def test_a_restarted_receiver_takes_over_from_its_dead_connection(serve_app) -> None:
    """A receiver killed (-9) on a host that vanished leaves the server holding its old
    connection: the restarted receiver, which alone knows its secret id, must not wait for it."""
    base_url, app = serve_app(token=TOKEN)

    async def scenario() -> tuple[int, int, list[dict]]:
        old, _ = await open_receiver(base_url)
        await old.send(envelope(1, pose(1)))
        await old.recv()
        old.transport.pause_reading()  # the old daemon is gone: it never reads or sends again
        new, welcome = await open_receiver(base_url)
        await new.send(envelope(2, pose(2)))
        ack = json.loads(await new.recv())
        old.transport.resume_reading()
        with pytest.raises(ConnectionClosed) as closed:
            await old.send(envelope(99, pose(99)))  # too late: not stored
            while True:
                await asyncio.wait_for(old.recv(), 5)
        receivers = json.loads(get(base_url, "/healthz"))["receivers"]
        await new.close()
        return welcome["last_seq"], closed.value.rcvd.code, [ack, receivers]

    last_seq, old_code, (ack, receivers) = asyncio.run(scenario())
    assert (last_seq, old_code) == (1, 4409)
    assert ack == {"type": "ack", "seq": 2} and receivers == 1
    assert [row[0] for row in app.state.live.receptions.poses(RX_1)] == [1, 2]


def test_receivers_kept_under_their_secret_id_are_renamed_to_their_public_one(tmp_path) -> None:
    """Servers before public ids kept (and showed) receivers under the id they connect with."""
    path = tmp_path / "eventocc.db"
    ReceptionStore(path).close()
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version = 0")
        db.execute("INSERT INTO receivers VALUES ('old-rx', 'then', 'then', 41)")
        db.execute("INSERT INTO receiver_poses VALUES ('old-rx', 5, 0, 0, 0, 0, 0, 0, 1, 1)")
    db.close()
    store = ReceptionStore(path)
    public = public_receiver_id("old-rx")
    assert store.register(public) == 41, "the receiver goes on where it was"
    assert store.poses(public) == [(5, 0, 0, 0, 0, 0, 0, 1)]
    assert store.poses("old-rx") is None
    store.close()
    assert ReceptionStore(path).register(public) == 41, "renamed once, not again"


def test_the_trajectory_of_a_receiver_never_seen_is_404(serve_app) -> None:
    base_url, _ = serve_app()
    with pytest.raises(urllib.error.HTTPError) as missing:
        get(base_url, "/api/receivers/0123456789abcdef/trajectory")
    assert missing.value.code == 404
    assert "no receiver" in json.loads(missing.value.read())["detail"]


# --- bursts ------------------------------------------------------------------------------------
def test_a_burst_of_reports_evicts_no_healthy_dashboard(serve_app) -> None:
    base_url, app = serve_app(token=TOKEN)
    burst = 10_000
    health = [
        envelope(None, HealthReport(cpu_load=i, events_per_s=0, state=TrackingState.IDLE))
        for i in range(burst)
    ]

    async def scenario() -> float:
        async with connect(ws_url(base_url, "/ws/dashboard"), max_queue=None) as dash:
            ws, _ = await open_receiver(base_url)
            for text in health:  # all at once: the server finds them already buffered
                await ws.send(text)
            while (update := json.loads(await asyncio.wait_for(dash.recv(), 10))).get(
                "cpu_load"
            ) != burst - 1:
                pass
            await ws.close()
            return update["cpu_load"]

    assert asyncio.run(scenario()) == burst - 1
    assert app.state.live.hub.evicted == 0


# --- other sites' pages ------------------------------------------------------------------------
@pytest.mark.parametrize("path", ["/ws/receiver", "/ws/dashboard", "/ws/transmitter"])
def test_pages_of_other_sites_cannot_open_a_websocket(serve_app, path: str) -> None:
    base_url, _ = serve_app(token=TOKEN)

    async def handshake(origin: str | None) -> int:
        try:
            async with connect(ws_url(base_url, path), origin=origin):
                return 101
        except InvalidStatus as refused:
            return refused.response.status_code

    assert asyncio.run(handshake("http://evil.example")) == 403
    assert asyncio.run(handshake(base_url)) == 101, "the server's own pages"
    assert asyncio.run(handshake(None)) == 101, "programs, the receiver daemon among them"


ATTACK = """<!doctype html><script>
function opens(url, first) {
  return new Promise((resolve) => {
    const socket = new WebSocket(url);
    socket.onopen = () => {
      if (first) socket.send(first);
      setTimeout(() => resolve("open"), 200);
    };
    socket.onerror = () => resolve("refused");
  });
}

async function attack(target) {
  const form = new FormData();
  form.append("file", new Blob(["planted"]), "planted.txt");
  await fetch(`${target}/api/messages`, { method: "POST", mode: "no-cors", body: form });
  const ws = target.replace("http", "ws");
  const status = JSON.stringify({ profile: "fast", cells: 128, refresh_hz: 1000 });
  return [await opens(`${ws}/ws/transmitter`, status), await opens(`${ws}/ws/dashboard`)];
}
</script>"""


@pytest.mark.browser
def test_a_page_of_another_site_in_a_browser_changes_nothing(
    serve_app, browser, tmp_path: Path
) -> None:
    """What a page elsewhere can make a visitor's browser do without asking: upload by a
    ``no-cors`` fetch, post a status and read the dashboards over websockets."""
    base_url, app = serve_app()
    (tmp_path / "attack.html").write_text(ATTACK)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=tmp_path)
    elsewhere = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=elsewhere.serve_forever, daemon=True).start()
    try:
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{elsewhere.server_port}/attack.html")
        assert page.evaluate(f"attack({json.dumps(base_url)})") == ["refused", "refused"]
    finally:
        elsewhere.shutdown()
    assert app.state.store.messages() == []
    assert app.state.live.transmitter is None


# --- a hostile neighbour -----------------------------------------------------------------------
def attack(base_url: str, message_id: str, shown_id: str) -> None:
    """Items 1, 5, 7 and 8 of the hardening issue, one after the other, as fast as they go,
    whatever the server answers."""
    playing = {"message_id": message_id, "playing": True, "refresh_hz": 60.0}
    with sync_connect(ws_url(base_url, "/ws/transmitter")) as tx:
        tx.send(json.dumps({**playing, "profile": "robust", "cells": 8}))
    for bogus in ({"cells": 1}, {"refresh_hz": 1e-9}, {"profile": "bogus", "cells": 16}):
        with contextlib.suppress(urllib.error.HTTPError):
            post_json(base_url, "/api/transmitter/status", {**playing, **bogus})
    with sync_connect(ws_url(base_url, "/ws/receiver")) as rx:  # the victim's shown id
        rx.send(Hello(receiver_id=shown_id).model_dump_json())
        rx.recv(5)
        rx.send(envelope(2**62, pose(1)))
        for i in range(10_000):  # a burst
            health = HealthReport(cpu_load=i, events_per_s=0, state=TrackingState.IDLE)
            rx.send(envelope(None, health))
        rx.send(pose_with(position="[NaN, Infinity, 0]"))
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            while True:
                rx.recv(10)


def test_a_hostile_neighbour_stops_neither_a_streaming_receiver_nor_the_dashboards(
    serve_app, tmp_path: Path
) -> None:
    """The real receiver daemon on the virtual camera receives a message while another client
    sends bogus transmitter statuses, speaks with the daemon's shown id and seq 2^62, bursts
    10k reports and sends NaN: the message completes, the daemon runs on, and both dashboards
    keep receiving, only JSON a browser parses."""
    base_url, app = serve_app()  # no token: the attacker may connect receivers too
    text = "Delivered next door to a hostile neighbour. " * 32  # some seconds of frames
    message = post_json(base_url, "/api/messages?name=next-door.txt", {"text": text})
    post_json(
        base_url,
        "/api/transmitter/status",
        {"message_id": message["id"], "profile": message["profile"], "cells": message["cells"],
         "playing": True, "frame_index": 0, "refresh_hz": 60.0},
    )  # fmt: skip
    dashboards = [Dashboard(base_url), Dashboard(base_url)]
    daemon = subprocess.Popen(
        [sys.executable, "-m", "eventocc.receiver.cli", "receive", "--source", "sim:",
         "--motion", "static", "--server", base_url, "--out", str(tmp_path / "out")],
        cwd=ROOT,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip

    def received() -> bool:
        assert daemon.poll() is None, "the daemon stopped"
        return any(r.message_id == message["id"] for r in app.state.live.receptions.receptions())

    try:
        shown = dashboards[0].updates
        wait_until(lambda: any(u["type"] == "pose" for u in shown), 180, "the daemon's poses")
        victim = next(u["receiver"] for u in shown if u["type"] == "pose")
        mark = len(shown)
        assert not received(), "the attack comes while the message streams"
        attack(base_url, message["id"], victim)
        marks = [len(d.updates) for d in dashboards]
        wait_until(received, 180, "the message to complete")
        wait_until(
            lambda: all(d.poses_since(m) > 0 for d, m in zip(dashboards, marks, strict=True)), 30
        )
        assert daemon.poll() is None, "the daemon runs on"
    finally:
        daemon.send_signal(signal.SIGTERM)
        _, log = daemon.communicate(timeout=60)
        for dashboard in dashboards:
            dashboard.close()
    assert daemon.returncode == 0, log
    assert app.state.live.hub.evicted == 0
    assert [(d.closed_with, d.unparsable) for d in dashboards] == [(None, 0), (None, 0)]
    (reception,) = [r for r in app.state.live.receptions.receptions() if r.receiver == victim]
    assert reception.name == "next-door.txt" and reception.size == len(text)
    assert any(u["type"] == "reception" for u in shown[mark:])
