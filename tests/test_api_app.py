"""The app around the API: pages, transmitter status, settings, optional routers, CLI, demo."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from eventocc.server import demo
from eventocc.server.__main__ import parse_args, settings_from_args
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


@pytest.mark.parametrize(
    "report", [{"frame_index": -1}, {"refresh_hz": 0}, {"missed_refreshes": "many"}]
)
def test_bad_transmitter_status_is_422_and_keeps_the_last(client: TestClient, report: dict) -> None:
    client.post("/api/transmitter/status", json={"frame_index": 7})
    assert client.post("/api/transmitter/status", json=report).status_code == 422
    assert client.get("/api/transmitter/status").json()["frame_index"] == 7


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
