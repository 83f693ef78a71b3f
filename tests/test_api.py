"""REST API of the transmit service: messages, their storage, and every bad-input path."""

from __future__ import annotations

import hashlib
from pathlib import Path
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eventocc.occ.profiles import DEFAULT_PROFILE
from eventocc.occ.stream import StreamEncoder
from eventocc.server.app import create_app
from eventocc.server.settings import Settings

RAW = {"Content-Type": "application/octet-stream"}
CAP = 4096


def make_client(data_dir: Path, **options) -> TestClient:
    return TestClient(create_app(Settings(data_dir=data_dir, max_upload_bytes=CAP, **options)))


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    return make_client(tmp_path)


def upload(client: TestClient, data: bytes, query: str = "", **headers: str) -> dict:
    response = client.post(f"/api/messages{query}", content=data, headers={**RAW, **headers})
    assert response.status_code == 201, response.text
    return response.json()


def stored_state(client: TestClient) -> tuple[list[dict], int]:
    return client.get("/api/messages").json()["messages"], client.app.state.store.blob_count()


# --- uploads ---------------------------------------------------------------------------------
def test_raw_upload_returns_the_message_facts(client: TestClient) -> None:
    data = b"hello, event camera"
    response = client.post(
        "/api/messages?name=hi.txt&profile=paper&cells=8", content=data, headers=RAW
    )
    assert response.status_code == 201
    facts = response.json()
    assert response.headers["Location"] == f"/api/messages/{facts['id']}"
    assert facts["name"] == "hi.txt"
    assert facts["size"] == len(data)
    assert facts["sha256"] == hashlib.sha256(data).hexdigest()
    assert (facts["profile"], facts["cells"]) == ("paper", 8)
    encoder = StreamEncoder(data, name="hi.txt", profile="paper", cells=8)
    assert facts["frames_per_loop"] == encoder.cycle
    assert facts["bits_per_frame"] == 64
    assert facts["bit_rate_60hz"] == pytest.approx(64 * 30)  # data frame + blank frame
    assert facts["created"].endswith("Z") or "+00:00" in facts["created"]


def test_fast_profile_sends_data_on_almost_every_refresh(client: TestClient) -> None:
    facts = upload(client, b"x" * 100, "?profile=fast&cells=16")
    assert facts["bit_rate_60hz"] == 256 * 60 * 31 / 32  # one refresh in 32 is a key frame


def test_one_bit_rate_per_profile_and_cells_whatever_the_message(client: TestClient) -> None:
    rates = {
        upload(client, b"y" * size, "?profile=fast&cells=12")["bit_rate_60hz"]
        for size in (1, 100, 1_000, 4_000)
    }
    (rate,) = rates
    assert rate == round(rate, 1)
    listed = client.get("/api/messages").json()["messages"]
    assert {m["bit_rate_60hz"] for m in listed} == {rate}
    assert all(isinstance(m["frames_per_loop"], int) for m in listed)
    schema = client.get("/openapi.json").json()["components"]["schemas"]["MessagePublic"]
    assert schema["properties"]["frames_per_loop"]["type"] == "integer"
    assert "null" not in schema["properties"]["frames_per_loop"]["description"]


def test_defaults_come_from_settings(tmp_path: Path) -> None:
    client = make_client(tmp_path, default_cells=12)
    facts = upload(client, b"abc")
    assert (facts["profile"], facts["cells"], facts["name"]) == (DEFAULT_PROFILE, 12, "message.bin")


def test_multipart_upload_keeps_the_file_name(client: TestClient) -> None:
    response = client.post("/api/messages", files={"file": ("report.pdf", b"%PDF-1.7 ...")})
    assert response.status_code == 201
    assert response.json()["name"] == "report.pdf"
    download = client.get(f"/api/messages/{response.json()['id']}/content")
    assert download.content == b"%PDF-1.7 ..."
    assert download.headers["content-disposition"] == (
        "attachment; filename=\"report.pdf\"; filename*=UTF-8''report.pdf"
    )


def test_json_upload_stores_utf8_text(client: TestClient) -> None:
    response = client.post("/api/messages", json={"text": "grüße 👋"})
    assert response.status_code == 201
    facts = response.json()
    assert facts["name"] == "message.txt"
    assert client.get(f"/api/messages/{facts['id']}/content").content == "grüße 👋".encode()


@pytest.mark.parametrize(
    "name",
    [
        "\U0001f468\u200d\U0001f469\u200d\U0001f467.txt",
        "\u0645\u06cc\u200c\u062e\u0648\u0627\u0647\u0645",
        "é" * 127 + "a",
    ],
)
def test_names_may_hold_joiners_and_fill_255_bytes(client: TestClient, name: str) -> None:
    assert upload(client, b"x", f"?name={quote(name)}")["name"] == name


def test_name_loses_any_directory_part(client: TestClient) -> None:
    assert upload(client, b"x", "?name=../../etc/passwd")["name"] == "passwd"
    assert upload(client, b"x", "?name=C:%5Cdocs%5Cnote.txt")["name"] == "note.txt"


def test_same_bytes_make_distinct_messages_sharing_one_blob(client: TestClient) -> None:
    first, second = upload(client, b"same bytes"), upload(client, b"same bytes", "?cells=20")
    assert first["id"] != second["id"]
    assert first["sha256"] == second["sha256"]
    assert client.app.state.store.blob_count() == 1
    assert client.delete(f"/api/messages/{first['id']}").status_code == 204
    assert client.get(f"/api/messages/{second['id']}/content").content == b"same bytes"
    assert client.delete(f"/api/messages/{second['id']}").status_code == 204
    assert client.app.state.store.blob_count() == 0


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(min_size=1, max_size=CAP))
def test_any_bytes_round_trip(client: TestClient, data: bytes) -> None:
    facts = upload(client, data)
    assert client.get(f"/api/messages/{facts['id']}/content").content == data


# --- reading and deleting ----------------------------------------------------------------------
def test_list_read_and_delete(client: TestClient) -> None:
    older, newer = upload(client, b"one"), upload(client, b"two")
    listed = client.get("/api/messages").json()["messages"]
    assert [m["id"] for m in listed] == [newer["id"], older["id"]]  # newest first
    assert client.get(f"/api/messages/{older['id']}").json() == older
    assert client.delete(f"/api/messages/{older['id']}").status_code == 204
    assert client.get(f"/api/messages/{older['id']}").status_code == 404
    assert [m["id"] for m in client.get("/api/messages").json()["messages"]] == [newer["id"]]


@pytest.mark.parametrize("suffix", ["", "/content", "/frames"])
def test_unknown_id_is_404(client: TestClient, suffix: str) -> None:
    response = client.get(f"/api/messages/0123456789ab{suffix}")
    assert response.status_code == 404
    assert response.json()["detail"] == "no message with id '0123456789ab'"


def test_delete_unknown_id_is_404(client: TestClient) -> None:
    assert client.delete("/api/messages/0123456789ab").status_code == 404


def test_malformed_id_is_422(client: TestClient) -> None:
    response = client.get("/api/messages/not-an-id")
    assert response.status_code == 422
    assert response.json()["detail"][0]["loc"] == ["path", "message_id"]


@pytest.mark.parametrize("read", ["content", "frames?count=1"])
def test_a_message_deleted_while_it_is_read_is_404(
    client: TestClient, monkeypatch: pytest.MonkeyPatch, read: str
) -> None:
    facts = upload(client, b"going, going")
    store = client.app.state.store
    look_up = store.get

    def deleted_right_after_the_lookup(message_id: str):
        message = look_up(message_id)
        store.delete(message_id)
        return message

    monkeypatch.setattr(store, "get", deleted_right_after_the_lookup)
    response = client.get(f"/api/messages/{facts['id']}/{read}")
    assert response.status_code == 404
    assert response.json()["detail"] == f"message {facts['id']!r} has been deleted"


def test_messages_survive_a_restart(tmp_path: Path) -> None:
    facts = upload(make_client(tmp_path), b"persistent")
    reopened = make_client(tmp_path)
    assert reopened.get(f"/api/messages/{facts['id']}").json() == facts
    assert reopened.get(f"/api/messages/{facts['id']}/content").content == b"persistent"


# --- bad input ---------------------------------------------------------------------------------
def detail(response) -> str:
    body = response.json()["detail"]
    return body if isinstance(body, str) else " ".join(e["msg"] for e in body)


BAD_UPLOADS = {
    "raw over the cap": ({"content": b"x" * (CAP + 1), "headers": RAW}, 413, "upload limit"),
    "json over the cap": ({"json": {"text": "x" * (CAP + 1)}}, 413, "upload limit"),
    "multipart over the cap": ({"files": {"file": ("a", b"x" * (CAP + 1))}}, 413, "upload limit"),
    "empty raw body": ({"content": b"", "headers": RAW}, 422, "empty"),
    "empty text": ({"json": {"text": ""}}, 422, "empty"),
    "empty file": ({"files": {"file": ("a", b"")}}, 422, "empty"),
    "malformed json": (
        {"content": b'{"text": "x"', "headers": {"Content-Type": "application/json"}},
        422,
        'send JSON like {"text": "..."}',
    ),
    "json without text": ({"json": {"txt": "x"}}, 422, "text: Field required"),
    "json text not a string": ({"json": {"text": 5}}, 422, "text: Input should be a valid string"),
    "multipart without file": (
        {"data": {"other": "x"}, "files": {"f": ("a", b"x")}},
        422,
        "'file'",
    ),
    "multipart file as a plain field": (
        {"files": {"file": ("", b"abc")}},  # httpx sends no filename for ""
        422,
        "the form's 'file' part is a plain field",
    ),
    "multipart with no file chosen": (
        {
            "content": b'--B\r\nContent-Disposition: form-data; name="file"; filename=""\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n\r\n--B--\r\n",
            "headers": {"Content-Type": "multipart/form-data; boundary=B"},
        },
        422,
        "no file was chosen",
    ),
    "no content type": ({"content": b"x"}, 415, "send one of application/octet-stream"),
    "text/plain": ({"content": b"x", "headers": {"Content-Type": "text/plain"}}, 415, "text/plain"),
}
BAD_OPTIONS = {
    "unknown profile": ("?profile=turbo", "Input should be 'paper', 'robust' or 'fast'"),
    "cells too few": ("?cells=7", "greater than or equal to 8"),
    "cells too many": ("?cells=129", "less than or equal to 128"),
    "cells not a number": ("?cells=many", "valid integer"),
    "empty name": ("?name=", "bad message name"),
    "name of dots": ("?name=..", "bad message name"),
    "name with a control character": ("?name=a%0Ab", "bad message name"),
    "name with a C1 control": ("?name=a%C2%85b.txt", "U+0085"),
    "name that shows reversed": ("?name=evil%E2%80%AEtxt.exe", "U+202E (RIGHT-TO-LEFT OVERRIDE)"),
    "name with a zero-width space": ("?name=a%E2%80%8Bb.txt", "U+200B (ZERO WIDTH SPACE)"),
    "name with a line separator": ("?name=a%E2%80%A8b.txt", "U+2028 (LINE SEPARATOR)"),
    "name over 255 bytes": ("?name=" + "%C3%A9" * 128, "it is 256 bytes of UTF-8"),
    "payload too small for the profile": ("?profile=robust&cells=8", "use more cells"),
    "paper cells not a multiple of 4": ("?profile=paper&cells=10", "multiple of 4"),
}


@pytest.mark.parametrize("case", BAD_UPLOADS.values(), ids=BAD_UPLOADS.keys())
def test_bad_upload_is_refused_with_a_reason(client: TestClient, case: tuple) -> None:
    request, status, reason = case
    response = client.post("/api/messages", **request)
    assert response.status_code == status
    assert reason in detail(response)


@pytest.mark.parametrize("case", BAD_OPTIONS.values(), ids=BAD_OPTIONS.keys())
def test_bad_option_is_refused_with_a_reason(client: TestClient, case: tuple) -> None:
    query, reason = case
    response = client.post(f"/api/messages{query}", content=b"x", headers=RAW)
    assert response.status_code == 422
    assert reason in detail(response)


def test_chunked_upload_over_the_cap_is_refused(client: TestClient) -> None:
    def chunks():
        for _ in range(CAP // 1000 + 1):
            yield b"x" * 1000

    assert client.post("/api/messages", content=chunks(), headers=RAW).status_code == 413


def test_failed_requests_change_nothing(client: TestClient) -> None:
    kept = upload(client, b"keep me")
    before = stored_state(client)
    for request, _, _ in BAD_UPLOADS.values():
        client.post("/api/messages", **request)
    for query, _ in BAD_OPTIONS.values():
        client.post(f"/api/messages{query}", content=b"keep me", headers=RAW)
    client.delete("/api/messages/0123456789ab")
    assert stored_state(client) == before
    assert client.get(f"/api/messages/{kept['id']}/content").content == b"keep me"


# --- write token -------------------------------------------------------------------------------
def test_writes_need_the_token_when_one_is_set(tmp_path: Path) -> None:
    client = make_client(tmp_path, token="s3cret")
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic s3cret"}):
        response = client.post("/api/messages", content=b"x", headers={**RAW, **headers})
        assert response.status_code == 401
        assert "Bearer <token>" in response.json()["detail"]
    facts = upload(client, b"x", Authorization="Bearer s3cret")
    assert client.get(f"/api/messages/{facts['id']}").status_code == 200  # reads stay open
    assert client.delete(f"/api/messages/{facts['id']}").status_code == 401
    assert client.get(f"/api/messages/{facts['id']}").status_code == 200
    delete = client.delete(
        f"/api/messages/{facts['id']}", headers={"Authorization": "Bearer s3cret"}
    )
    assert delete.status_code == 204


def test_profiles_lists_what_an_upload_may_choose(tmp_path: Path) -> None:
    body = (
        make_client(tmp_path, default_profile="paper", default_cells=24).get("/api/profiles").json()
    )
    assert body == {
        "profiles": ["paper", "robust", "fast"],
        "default_profile": "paper",
        "default_cells": 24,
        "min_cells": 8,
        "max_cells": 128,
    }


# --- other sites' pages ------------------------------------------------------------------------
EVIL = {"Origin": "http://evil.example"}


def test_pages_of_other_sites_cannot_change_anything(client: TestClient) -> None:
    kept = upload(client, b"keep me")
    before = stored_state(client)
    writes = [
        client.post("/api/messages", content=b"x", headers={**RAW, **EVIL}),
        client.post("/api/messages", files={"file": ("a.txt", b"x")}, headers={**EVIL}),
        client.delete(f"/api/messages/{kept['id']}", headers=EVIL),
        client.post("/api/transmitter/status", json={"frame_index": 1}, headers=EVIL),
        client.post("/api/messages", content=b"x", headers={**RAW, "Origin": "null"}),
    ]
    for response in writes:
        assert response.status_code == 403
        assert "a page of" in response.json()["detail"]
    assert stored_state(client) == before
    assert client.get("/api/messages", headers=EVIL).status_code == 200, "reads stay open"


def test_the_servers_own_pages_and_programs_may_write(client: TestClient) -> None:
    own = {"Origin": "http://testserver"}  # the Host TestClient sends
    assert upload(client, b"from the page", **own)["size"] == 13
    assert upload(client, b"from curl")["size"] == 9


def test_an_allowed_origin_may_write(tmp_path: Path) -> None:
    client = make_client(tmp_path, allowed_origins=["https://screens.example"])
    assert upload(client, b"x", Origin="https://screens.example")["size"] == 1
    response = client.post("/api/messages", content=b"x", headers={**RAW, **EVIL})
    assert response.status_code == 403
