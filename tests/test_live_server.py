"""The live routes over real websockets and a real uvicorn server: handshake, acks, storage,
refusals, fan-out, REST for receptions, health and metrics."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import http.client
import json
import os
import socket
import sqlite3
import urllib.error
import urllib.request

import pytest
from websockets.asyncio.client import connect

from eventocc.occ.report import Hello, SurfaceReport
from eventocc.server.receptions import SCHEMA, ReceptionStore
from eventocc.server.settings import MIB
from tests.live_clients import (
    RX_1,
    TEXT,
    TOKEN,
    close_code,
    envelope,
    get,
    message_report,
    open_receiver,
    pose,
    upload,
    wait_until,
    ws_url,
)


@pytest.mark.parametrize(
    ("token", "reason"), [(None, "missing or wrong token"), ("wrong", "missing or wrong token")]
)
def test_receiver_without_the_right_token_is_refused(serve_app, token, reason, caplog) -> None:
    base_url, _ = serve_app(token=TOKEN)
    hello = Hello(receiver_id="intruder", token=token).model_dump_json()
    assert asyncio.run(close_code(base_url, hello)) == (4401, reason)
    assert "refused /ws/receiver" in caplog.text


@pytest.mark.parametrize("first", ["not json", '{"type": "pose"}', '{"type": "hello"}'])
def test_malformed_handshake_is_refused(serve_app, first: str) -> None:
    base_url, _ = serve_app(token=TOKEN)
    code, reason = asyncio.run(close_code(base_url, first))
    assert code == 4400 and reason.startswith("expected a Hello report first")


@pytest.mark.parametrize("frame", ["[1, 2]", '{"report": {}}', '{"seq": -3, "report": {}}'])
def test_a_report_outside_its_envelope_closes_the_connection(serve_app, frame: str) -> None:
    base_url, _ = serve_app(token=TOKEN)
    hello = Hello(receiver_id="rx", token=TOKEN).model_dump_json()
    code, reason = asyncio.run(close_code(base_url, hello, frame))
    assert code == 1007 and "expected" in reason


def test_finished_message_is_stored_verified_acked_and_downloadable(serve_app) -> None:
    base_url, _ = serve_app(token=TOKEN)
    uploaded = upload(base_url, TEXT)

    async def scenario() -> list[dict]:
        ws, welcome = await open_receiver(base_url)
        assert welcome == {"type": "welcome", "last_seq": 0}
        await ws.send(envelope(1, message_report()))
        await ws.send(envelope(1, message_report()))  # replayed from a spool: stored once
        acks = [json.loads(await ws.recv()) for _ in range(2)]
        await ws.close()
        return acks

    assert asyncio.run(scenario()) == [{"type": "ack", "seq": 1}] * 2
    receptions = json.loads(get(base_url, "/api/receptions"))["receptions"]
    assert len(receptions) == 1
    (reception,) = receptions
    assert reception["sha256"] == hashlib.sha256(TEXT).hexdigest()
    assert reception["message_id"] == uploaded["id"] and reception["verified"] is True
    assert reception["receiver"] == RX_1 and reception["name"] == "note.txt"
    assert get(base_url, reception["url"]) == TEXT
    assert json.loads(get(base_url, f"/api/receptions/{reception['id']}"))["size"] == len(TEXT)


DOWNLOAD_NAMES = {
    "日本語.txt": 'attachment; filename="___.txt"; '
    "filename*=UTF-8''%E6%97%A5%E6%9C%AC%E8%AA%9E.txt",
    'a".txt': "attachment; filename=\"a_.txt\"; filename*=UTF-8''a%22.txt",
    "x\r\nSet-Cookie: y=1": 'attachment; filename="x__Set-Cookie: y=1"; '
    "filename*=UTF-8''x%0D%0ASet-Cookie%3A%20y%3D1",
    "100%\\ sure": "attachment; filename=\"100__ sure\"; filename*=UTF-8''100%25%5C%20sure",
}


def test_a_reception_downloads_under_any_name_a_receiver_sends(serve_app) -> None:
    """RFC 6266: the exact name in ``filename*``, an ASCII stand-in in ``filename``; and one
    keep-alive connection serves every download."""
    base_url, _ = serve_app(token=TOKEN)

    async def send_receptions() -> None:
        ws, _ = await open_receiver(base_url)
        for seq, name in enumerate(DOWNLOAD_NAMES, 1):
            await ws.send(envelope(seq, message_report(name.encode(), name)))
            await ws.recv()
        await ws.close()

    asyncio.run(send_receptions())
    receptions = json.loads(get(base_url, "/api/receptions"))["receptions"]
    connection = http.client.HTTPConnection(base_url.removeprefix("http://"), timeout=5)
    for reception in receptions:
        connection.request("GET", reception["url"])
        response = connection.getresponse()
        assert response.read() == reception["name"].encode()
        assert response.headers["Content-Disposition"] == DOWNLOAD_NAMES[reception["name"]]
    connection.close()


def test_reconnecting_receiver_learns_what_was_stored(serve_app) -> None:
    base_url, _ = serve_app(token=TOKEN)

    async def scenario() -> int:
        ws, _ = await open_receiver(base_url)
        for seq in (1, 2, 3):
            await ws.send(envelope(seq, pose(seq * 10_000)))
            await ws.recv()
        await ws.close()
        ws, welcome = await open_receiver(base_url)
        await ws.close()
        return welcome["last_seq"]

    assert asyncio.run(scenario()) == 3
    tum = get(base_url, f"/api/receivers/{RX_1}/trajectory").decode().splitlines()
    assert tum[1:] == [
        f"0.0{i}0000 0.100000000 0.200000000 -0.500000000 0.000000000 0.000000000 "
        "0.000000000 1.000000000"
        for i in (1, 2, 3)
    ]


def test_report_failing_the_schema_is_rejected_counted_and_acked(serve_app, caplog) -> None:
    base_url, _ = serve_app(token=TOKEN)
    bad = {
        "type": "message",
        "stream_id": 1,
        "name": "x",
        "size": 3,
        "sha256": "0" * 64,
        "data_b64": base64.b64encode(b"abc").decode(),
        "profile": "robust",
    }

    async def scenario() -> dict:
        ws, _ = await open_receiver(base_url)
        await ws.send(json.dumps({"seq": 1, "report": bad}))
        ack = json.loads(await ws.recv())
        await ws.close()
        return ack

    assert asyncio.run(scenario()) == {"type": "ack", "seq": 1}
    assert json.loads(get(base_url, "/api/receptions"))["receptions"] == []
    assert "eventocc_reports_rejected_total 1" in get(base_url, "/metrics").decode()
    assert "does not match sha256" in caplog.text


def test_dashboards_see_receivers_poses_and_receptions(serve_app) -> None:
    base_url, _ = serve_app(token=TOKEN)

    async def scenario() -> list[dict]:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            ws, _ = await open_receiver(base_url)
            await ws.send(envelope(1, pose(5)))
            await ws.send(envelope(2, message_report()))
            await ws.send(
                envelope(None, SurfaceReport(t_us=5, width=2, height=1, pixels_b64="AP8="))
            )
            seen = []
            while not seen or seen[-1]["type"] != "surface":
                seen.append(json.loads(await asyncio.wait_for(dash.recv(), 5)))
            await ws.close()
            return seen

    seen = asyncio.run(scenario())
    kinds = [update["type"] for update in seen]
    assert kinds == ["receivers", "pose", "reception", "surface"]
    assert seen[0]["receivers"] == [{"receiver": RX_1, "version": 1}]
    assert "token" not in json.dumps(seen[0]), "a receiver's token must never reach viewers"
    assert "rx-1" not in json.dumps(seen), "nor its secret id"
    assert seen[1]["receiver"] == RX_1 and seen[1]["position"] == [0.1, 0.2, -0.5]
    assert seen[2]["url"].startswith("/api/receptions/")
    assert seen[2]["stream_id"] == 7, "so the dashboards end that stream's progress bar"


def test_transmitter_socket_and_rest_status_are_one_state(serve_app) -> None:
    base_url, _ = serve_app()
    status = {
        "message_id": "0123456789ab",
        "profile": "robust",
        "cells": 16,
        "playing": True,
        "frame_index": 42,
        "refresh_hz": 59.9,
        "missed_refreshes": 3,
    }

    async def scenario() -> dict:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            async with connect(ws_url(base_url, "/ws/transmitter")) as tx:
                await tx.send(json.dumps(status))
                await tx.send(json.dumps({"frame_index": -1}))
                error = json.loads(await tx.recv())
                assert error["type"] == "error"
            while True:
                update = json.loads(await asyncio.wait_for(dash.recv(), 5))
                if update["type"] == "transmitter":
                    return update

    update = asyncio.run(scenario())
    assert update["frame_index"] == 42 and update["missed_refreshes"] == 3
    rest = json.loads(get(base_url, "/api/transmitter/status"))
    assert rest["frame_index"] == 42 and rest["received"] == update["received"]


def test_a_status_posted_over_rest_reaches_the_dashboards(serve_app) -> None:
    base_url, _ = serve_app()
    status = {"message_id": "0123456789ab", "profile": "fast", "cells": 12, "frame_index": 7}

    async def scenario() -> dict:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:
            request = urllib.request.Request(
                f"{base_url}/api/transmitter/status",
                data=json.dumps(status).encode(),
                headers={"Content-Type": "application/json"},
            )
            await asyncio.to_thread(urllib.request.urlopen, request)
            while True:
                update = json.loads(await asyncio.wait_for(dash.recv(), 5))
                if update["type"] == "transmitter":
                    return update

    update = asyncio.run(scenario())
    assert (update["profile"], update["cells"], update["frame_index"]) == ("fast", 12, 7)


def test_a_stalled_dashboard_does_not_slow_the_others(serve_app) -> None:
    base_url, app = serve_app(token=TOKEN)
    hub = app.state.live.hub
    hub.evict_after = 50  # evict sooner than in production, to keep the test short
    # 300 updates of 65 kB, incompressible: far more than the kernel buffers can absorb.
    count, pixels = 300, base64.b64encode(os.urandom(256 * 192)).decode()
    surface = SurfaceReport(t_us=1, width=256, height=192, pixels_b64=pixels)

    async def scenario() -> int:
        stalled_sock = socket.socket()
        stalled_sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled_sock.connect(("127.0.0.1", int(base_url.rsplit(":", 1)[1])))
        stalled = await connect(ws_url(base_url, "/ws/dashboard"), sock=stalled_sock)
        stalled.transport.pause_reading()  # it never reads again
        async with connect(ws_url(base_url, "/ws/dashboard"), max_queue=None) as live:
            ws, _ = await open_receiver(base_url)
            got = 0
            for _ in range(count):  # lock-step: the live viewer is never behind by itself
                await ws.send(envelope(None, surface))
                while json.loads(await asyncio.wait_for(live.recv(), 5))["type"] != "surface":
                    pass
                got += 1
            await ws.close()
        stalled.transport.abort()
        return got

    assert asyncio.run(scenario()) == count
    assert hub.dropped >= hub.evict_after, "the stalled viewer was decimated first"
    assert hub.evicted == 1, "then dropped"


def test_uploads_share_one_memory_budget(serve_app) -> None:
    """Two uploads under way hold the whole budget: a third is refused (503) until they end,
    whatever its own size."""
    base_url, app = serve_app(max_upload_bytes=MIB, upload_budget_bytes=2 * MIB)
    budget = app.state.upload_budget
    host, port = base_url.removeprefix("http://").split(":")
    head = (
        "POST /api/messages HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n"
        f"Content-Length: {MIB}\r\n\r\n"
    ).encode()
    slow = [socket.create_connection((host, int(port)), timeout=10) for _ in range(2)]
    for sock in slow:
        sock.sendall(head + b"x" * 1000)  # and the rest later
    wait_until(lambda: budget.held == 2 * MIB)

    with pytest.raises(urllib.error.HTTPError) as refused:
        upload(base_url, b"small")
    assert refused.value.code == 503 and refused.value.headers["Retry-After"]
    assert "busy with other uploads" in json.loads(refused.value.read())["detail"]

    for sock in slow:
        sock.sendall(b"x" * (MIB - 1000))
        assert sock.recv(100).startswith(b"HTTP/1.1 201")
        sock.close()
    wait_until(lambda: budget.held == 0)
    assert upload(base_url, b"small")["size"] == 5


def test_websockets_are_not_compressed(serve_app) -> None:
    """Per-message deflate would cost the server one zlib stream per viewer for small JSON."""
    base_url, _ = serve_app()

    async def scenario() -> str | None:
        async with connect(ws_url(base_url, "/ws/dashboard")) as dash:  # offers deflate
            return dash.response.headers.get("Sec-WebSocket-Extensions")

    assert asyncio.run(scenario()) is None


def test_health_and_metrics(serve_app) -> None:
    base_url, _ = serve_app()
    assert json.loads(get(base_url, "/healthz")) == {
        "status": "ok",
        "receivers": 0,
        "dashboards": 0,
    }
    metrics = get(base_url, "/metrics").decode()
    for name in (
        "eventocc_receivers_connected",
        "eventocc_frames_decoded_total",
        "eventocc_goodput_bits_per_second",
        "eventocc_dashboard_clients",
    ):
        assert f"# TYPE {name} " in metrics and f"\n{name} 0" in metrics


def test_unknown_and_malformed_reception_ids(serve_app) -> None:
    base_url, _ = serve_app()
    with pytest.raises(urllib.error.HTTPError) as missing:
        get(base_url, "/api/receptions/0123456789ab")
    assert missing.value.code == 404
    with pytest.raises(urllib.error.HTTPError) as malformed:
        get(base_url, "/api/receptions/nope")
    assert malformed.value.code == 422


def test_store_refuses_bytes_that_do_not_match_their_digest(tmp_path) -> None:
    store = ReceptionStore(tmp_path / "db.sqlite")
    store.register("rx")
    with pytest.raises(ValueError, match="does not match its sha256"):
        store.add(
            receiver="rx",
            seq=1,
            name="x",
            data=b"abc",
            claimed_sha256="0" * 64,
            goodput_bps=None,
            message_id=None,
        )
    assert store.receptions() == [] and store.register("rx") == 0


def test_store_keeps_whether_the_sender_checked_the_bytes(tmp_path) -> None:
    path = tmp_path / "db.sqlite"
    with sqlite3.connect(path) as db:  # a database from before the column
        db.executescript(SCHEMA.replace("    verified   INTEGER,\n", ""))
        db.execute("INSERT INTO receivers VALUES ('rx', 'now', 'now', 1)")
        db.execute(
            "INSERT INTO receptions (id, receiver, seq, name, sha256, size, received, data) "
            "VALUES ('000000000001', 'rx', 1, 'old', ?, 1, '2026-01-01T00:00:00+00:00', x'61')",
            (hashlib.sha256(b"a").hexdigest(),),
        )
    store = ReceptionStore(path)
    for seq, verified in ((2, True), (3, False)):
        data = bytes([seq])
        store.add(
            receiver="rx",
            seq=seq,
            name=str(seq),
            data=data,
            claimed_sha256=hashlib.sha256(data).hexdigest(),
            goodput_bps=None,
            message_id=None,
            verified=verified,
        )
    assert {r.name: r.verified for r in store.receptions()} == {
        "old": None,
        "2": True,
        "3": False,
    }


def test_the_trajectory_holds_verified_poses_unless_all_are_asked_for(serve_app) -> None:
    base_url, _ = serve_app(token=TOKEN)

    async def scenario() -> None:
        ws, _ = await open_receiver(base_url)
        for seq, (t_us, verified) in enumerate([(1_000, False), (2_000, True), (3_000, True)], 1):
            await ws.send(envelope(seq, pose(t_us, verified=verified)))
            await ws.recv()  # stored, then acked
        await ws.close()

    asyncio.run(scenario())
    times = lambda text: [line.split()[0] for line in text.decode().splitlines()[1:]]  # noqa: E731
    trajectory = f"/api/receivers/{RX_1}/trajectory"
    assert times(get(base_url, trajectory)) == ["0.002000", "0.003000"]
    assert times(get(base_url, trajectory + "?all=true")) == ["0.001000", "0.002000", "0.003000"]
    assert times(get(base_url, trajectory + "?all=false")) == ["0.002000", "0.003000"]


def test_poses_kept_before_the_verified_flag_are_kept_as_tentative(tmp_path) -> None:
    path = tmp_path / "db.sqlite"
    with sqlite3.connect(path) as db:  # a database from before the column
        db.executescript(SCHEMA.replace("    verified INTEGER,\n", ""))
        db.execute("PRAGMA user_version = 1")  # receivers already under their public id
        db.execute("INSERT INTO receivers VALUES ('rx', 'now', 'now', 1)")
        db.execute("INSERT INTO receiver_poses VALUES ('rx', 5, 0, 0, 0, 0, 0, 0, 1)")
    db.close()
    store = ReceptionStore(path)
    store.add_poses("rx", 2, [(6, 1, 0, 0, 0, 0, 0, 1)], verified=True)
    store.add_poses("rx", 3, [(7, 2, 0, 0, 0, 0, 0, 1)], verified=False)
    assert [row[0] for row in store.poses("rx")] == [6]
    assert [row[0] for row in store.poses("rx", tentative=True)] == [5, 6, 7]
    store.close()
