"""The app around the API: pages, transmitter status, settings, optional routers, CLI, demo."""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from eventocc.occ.profiles import DEFAULT_PROFILE, LinkSettings
from eventocc.occ.stream import StreamDecoder, StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.sim.display import Display
from eventocc.server import demo
from eventocc.server.__main__ import LOG_HANDLER, log_to_stderr, parse_args, settings_from_args
from eventocc.server.app import create_app
from eventocc.server.settings import MIB, Settings


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        yield client


# --- pages -------------------------------------------------------------------------------------
def test_index_links_every_page(client: TestClient) -> None:
    index = client.get("/")
    assert index.status_code == 200
    assert '<a href="/transmitter">transmitter</a>' in index.text


def test_pages_and_assets_are_served(client: TestClient) -> None:
    page = client.get("/transmitter")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert '<canvas id="marker"' in page.text
    script = client.get("/static/transmitter.js")
    assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    assert client.get("/static/style.css").status_code == 200
    assert client.get("/static/missing.js").status_code == 404


def test_the_site_has_an_icon_where_browsers_ask_for_it(client: TestClient) -> None:
    icon = client.get("/favicon.ico")
    assert icon.status_code == 200 and icon.headers["content-type"] == "image/svg+xml"
    assert icon.text.startswith("<svg")


def test_openapi_documents_every_upload_form_and_resolves_its_refs(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    upload = schema["paths"]["/api/messages"]["post"]["requestBody"]["content"]
    assert set(upload) == {"application/octet-stream", "multipart/form-data", "application/json"}
    refs = re.findall(r'"\$ref": "#/components/schemas/([^"]+)"', json.dumps(schema))
    assert set(refs) <= set(schema["components"]["schemas"])


# --- transmitter status ------------------------------------------------------------------------
def test_transmitter_status_round_trip(client: TestClient) -> None:
    missing = client.get("/api/transmitter/status")
    assert missing.status_code == 404
    assert missing.json()["detail"] == "no transmitter has reported yet"
    report = {
        "message_id": "0123456789ab",
        "playing": True,
        "frame_index": 120,
        "refresh_hz": 59.9,
        "missed_refreshes": 2,
    }
    posted = client.post("/api/transmitter/status", json=report)
    assert posted.status_code == 200
    latest = client.get("/api/transmitter/status").json()
    assert {k: latest[k] for k in report} == report
    assert latest["received"] == posted.json()["received"]
    assert client.app.state.live.transmitter.frame_index == 120


BAD_STATUSES = {
    "frame before the first": ('{"frame_index": -1}', "greater than or equal to 0"),
    "frame past the frames API": ('{"frame_index": 2147483648}', "less than or equal to"),
    "counter not a number": ('{"missed_refreshes": "many"}', "valid integer"),
    "unknown profile": ('{"profile": "bogus"}', "'paper', 'robust' or 'fast'"),
    "fewer cells than a marker has": ('{"cells": 1}', "greater than or equal to 8"),
    "more cells than a marker has": ('{"cells": 129}', "less than or equal to 128"),
    "cells the profile cannot use": ('{"profile": "robust", "cells": 8}', "use more cells"),
    "paper cells not whole bytes": ('{"profile": "paper", "cells": 10}', "multiple of 4"),
    "no refresh": ('{"refresh_hz": 0}', "greater than or equal to 1"),
    "refresh slower than any display": ('{"refresh_hz": 1e-9}', "greater than or equal to 1"),
    "refresh faster than any display": ('{"refresh_hz": 1e6}', "less than or equal to 1000"),
    "refresh not finite": ('{"refresh_hz": Infinity}', "finite number"),
    "message id not an id": ('{"message_id": "../../etc/passwd"}', "should match pattern"),
}


@pytest.mark.parametrize("case", BAD_STATUSES.values(), ids=BAD_STATUSES.keys())
def test_bad_transmitter_status_is_422_and_keeps_the_last(client: TestClient, case) -> None:
    body, reason = case
    good = {"profile": "fast", "cells": 24, "refresh_hz": 120.0, "frame_index": 7}
    client.post("/api/transmitter/status", json=good)
    response = client.post(
        "/api/transmitter/status", content=body, headers={"Content-Type": "application/json"}
    )
    assert response.status_code == 422
    assert reason in json.dumps(response.json()["detail"])
    latest = client.get("/api/transmitter/status").json()
    assert {k: latest[k] for k in good} == good


STATUS_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**40), max_value=2**40),
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from(["paper", "robust", "fast", "bogus", "", "0123456789ab"]),
)
STATUS_FIELDS = ["message_id", "profile", "cells", "refresh_hz", "frame_index", "playing"]


@settings(max_examples=150, deadline=None)
@given(status=st.dictionaries(st.sampled_from(STATUS_FIELDS), STATUS_VALUES))
def test_every_status_the_server_keeps_is_one_a_receiver_can_follow(
    tmp_path_factory: pytest.TempPathFactory, status: dict
) -> None:
    """What a receiver daemon builds from the status (``receiver.live.screen``) must never
    fail: one bad status would stop every receiver that follows the page."""
    with TestClient(create_app(Settings(data_dir=tmp_path_factory.mktemp("data")))) as client:
        if client.post("/api/transmitter/status", json=status).status_code != 200:
            assert client.get("/api/transmitter/status").status_code == 404
            return
        kept = client.get("/api/transmitter/status").json()
    profile, cells = kept["profile"] or DEFAULT_PROFILE, kept["cells"] or 16
    link = LinkSettings(profile, cells, kept["refresh_hz"] or 60.0)
    ReceiverConfig(
        CameraModel.paper(), cells=link.cells, profile=profile, refresh_hz=link.refresh_hz
    )
    StreamDecoder(profile=profile, cells=cells)
    Display(refresh_hz=kept["refresh_hz"] or 60.0)
    StreamEncoder(b"any message", profile=profile, cells=cells).frames(kept["frame_index"], 1)


# --- settings ----------------------------------------------------------------------------------
def test_settings_come_from_the_environment(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("EVENTOCC_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("EVENTOCC_MAX_UPLOAD_BYTES", "1024")
    monkeypatch.setenv("EVENTOCC_TOKEN", "abc")
    settings = Settings()
    assert (settings.data_dir, settings.max_upload_bytes) == (tmp_path, 1024)
    assert settings.token.get_secret_value() == "abc"
    assert settings.db_path == tmp_path / "eventocc.db"
    monkeypatch.delenv("EVENTOCC_MAX_UPLOAD_BYTES")
    assert Settings().max_upload_bytes == 64 * MIB


@pytest.mark.parametrize(
    ("options", "reason"),
    [
        (
            {"default_profile": "turbo"},
            "unknown profile 'turbo'; choose one of paper, robust, fast",
        ),
        ({"default_cells": 4}, "greater than or equal to 8"),
        ({"token": ""}, "token must not be empty"),
        ({"port": 70000}, "less than or equal to 65535"),
        ({"max_upload_bytes": 0}, "greater than or equal to 1"),
        (
            {"max_upload_bytes": 2 * MIB, "upload_budget_bytes": MIB},
            "must be at least max_upload_bytes",
        ),
    ],
)
def test_bad_settings_are_refused(options: dict, reason: str) -> None:
    with pytest.raises(ValidationError, match=reason):
        Settings(**options)


# --- console script and demo -------------------------------------------------------------------
def test_cli_options_override_the_environment(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("EVENTOCC_PORT", "9000")
    monkeypatch.setenv("EVENTOCC_HOST", "0.0.0.0")
    settings = settings_from_args(parse_args(["--port", "8123", "--data-dir", str(tmp_path)]))
    assert (settings.host, settings.port, settings.data_dir) == ("0.0.0.0", 8123, tmp_path)
    assert settings.token is None


def test_cli_refuses_bad_settings_with_a_message() -> None:
    with pytest.raises(SystemExit, match=r"(?s)bad settings.*port"):
        settings_from_args(parse_args(["--port", "99999"]))


def test_the_server_logs_its_own_info_lines_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """A reception's "verified" line reaches the server's log (docker compose logs shows it)."""
    logger = logging.getLogger("eventocc")
    monkeypatch.setattr(logger, "handlers", [])
    monkeypatch.setattr(logger, "level", logging.NOTSET)
    log_to_stderr()
    log_to_stderr()
    assert logger.handlers == [LOG_HANDLER]
    assert logging.getLogger("eventocc.server.api.receivers").isEnabledFor(logging.INFO)


def test_demo_serves_the_sample_and_reuses_it(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, port=0)
    server, thread = demo.start_server(settings)
    try:
        base_url = demo.bound_url(server)
        first = demo.upload_sample(base_url, settings)
        assert demo.upload_sample(base_url, settings)["id"] == first["id"]
        with urllib.request.urlopen(f"{base_url}/api/messages/{first['id']}/content") as response:
            assert response.read().decode() == demo.SAMPLE_TEXT
        with urllib.request.urlopen(f"{base_url}/api/messages") as response:
            assert len(json.load(response)["messages"]) == 1
    finally:
        server.should_exit = True
        thread.join(10)
    assert not thread.is_alive()


def test_demo_stopped_by_sigterm_stops_its_receiver_too(tmp_path: Path) -> None:
    root = Path(__file__).resolve().parent.parent
    demo_process = subprocess.Popen(
        [sys.executable, "-m", "eventocc.server.demo"],
        cwd=root,
        env={**os.environ, "EVENTOCC_PORT": "0", "EVENTOCC_DATA_DIR": str(tmp_path)},
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        for line in demo_process.stdout:
            if line.startswith("Ctrl-C to stop"):
                break
        children = Path(f"/proc/{demo_process.pid}/task/{demo_process.pid}/children")
        (receiver_pid,) = map(int, children.read_text().split())
        demo_process.send_signal(signal.SIGTERM)
        assert demo_process.wait(60) == 0
    finally:
        demo_process.kill()
    assert not Path(f"/proc/{receiver_pid}").exists(), "the receiver outlived the demo"


def test_a_port_left_in_time_wait_is_free_for_the_demo_again() -> None:
    """The demo restarted within a minute kept finding its port busy and moved to another."""
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        client = socket.create_connection(("127.0.0.1", port))
        served, _ = listener.accept()
        served.close()  # the server side closes first: its end waits in TIME_WAIT
        client.recv(1)
        client.close()
    assert demo.port_is_free("127.0.0.1", port)
