"""``/api/messages/{id}/frames``: packed full-marker cell matrices, exactly the encoder's frames."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from eventocc.occ.stream import StreamEncoder
from eventocc.server.api.frames import MAX_BATCH, pack_frames
from eventocc.server.app import create_app
from eventocc.server.settings import Settings

MESSAGE = b"frames for the transmitter page " * 8


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    return TestClient(create_app(Settings(data_dir=tmp_path)))


def upload(client: TestClient, query: str) -> str:
    response = client.post(
        f"/api/messages{query}",
        content=MESSAGE,
        headers={"Content-Type": "application/octet-stream"},
    )
    assert response.status_code == 201, response.text
    return response.json()["id"]


def unpack(body: bytes, side: int, count: int) -> np.ndarray:
    """The documented client-side unpacking of a frames response."""
    bits = np.unpackbits(np.frombuffer(body, np.uint8).reshape(count, -1), axis=1)
    return bits[:, : side * side].reshape(count, side, side).astype(bool)


@pytest.mark.parametrize(
    ("profile", "cells", "start", "count"),
    [("paper", 8, 0, 5), ("robust", 16, 3, 17), ("fast", 12, 40, 9), ("robust", 12, 1000, 3)],
)
def test_frames_unpack_to_the_encoders_frames(
    client: TestClient, profile: str, cells: int, start: int, count: int
) -> None:
    message_id = upload(client, f"?name=f.bin&profile={profile}&cells={cells}")
    response = client.get(f"/api/messages/{message_id}/frames?start={start}&count={count}")
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/octet-stream"
    encoder = StreamEncoder(MESSAGE, name="f.bin", profile=profile, cells=cells)
    side = encoder.geometry.side
    assert int(response.headers["X-Frame-Side"]) == side
    assert int(response.headers["X-Frame-Start"]) == start
    assert int(response.headers["X-Frame-Count"]) == count
    assert int(response.headers["X-Frame-Bytes"]) == -(-side * side // 8)
    assert len(response.content) == count * -(-side * side // 8)
    np.testing.assert_array_equal(
        unpack(response.content, side, count), encoder.frames(start, count)
    )


def test_profile_and_cells_can_be_overridden_per_request(client: TestClient) -> None:
    message_id = upload(client, "?name=f.bin&profile=robust&cells=16")
    response = client.get(f"/api/messages/{message_id}/frames?count=4&profile=paper&cells=12")
    encoder = StreamEncoder(MESSAGE, name="f.bin", profile="paper", cells=12)
    side = int(response.headers["X-Frame-Side"])
    assert side == encoder.geometry.side
    np.testing.assert_array_equal(unpack(response.content, side, 4), encoder.frames(0, 4))


def test_sequential_batches_reuse_one_encoder(client: TestClient) -> None:
    message_id = upload(client, "")
    for start in (0, 60, 120):
        assert client.get(f"/api/messages/{message_id}/frames?start={start}").status_code == 200
    info = client.app.state.encoders.get.cache_info()
    assert (info.misses, info.hits) == (1, 2)


def test_pack_frames_is_msb_first_and_pads_each_frame() -> None:
    frames = np.zeros((2, 3, 3), dtype=bool)
    frames[0, 0, 0] = True  # first cell -> top bit of byte 0
    frames[1, 2, 2] = True  # ninth cell -> top bit of the frame's second byte
    assert pack_frames(frames) == bytes([0x80, 0x00, 0x00, 0x80])


def test_combination_the_link_refuses_is_422(client: TestClient) -> None:
    message_id = upload(client, "?profile=robust&cells=16")
    response = client.get(f"/api/messages/{message_id}/frames?profile=paper&cells=10")
    assert response.status_code == 422
    assert "multiple of 4" in response.json()["detail"]


@pytest.mark.parametrize(
    ("query", "reason"),
    [
        ("start=-1", "greater than or equal to 0"),
        ("start=x", "valid integer"),
        ("count=0", "greater than or equal to 1"),
        (f"count={MAX_BATCH + 1}", f"less than or equal to {MAX_BATCH}"),
        ("profile=turbo", "Input should be 'paper', 'robust' or 'fast'"),
        ("cells=200", "less than or equal to 128"),
    ],
)
def test_bad_frame_query_is_422(client: TestClient, query: str, reason: str) -> None:
    message_id = upload(client, "")
    response = client.get(f"/api/messages/{message_id}/frames?{query}")
    assert response.status_code == 422
    assert reason in response.json()["detail"][0]["msg"]


def test_frames_format_is_documented_in_openapi(client: TestClient) -> None:
    operation = client.get("/openapi.json").json()["paths"]["/api/messages/{message_id}/frames"]
    ok = operation["get"]["responses"]["200"]
    assert "application/octet-stream" in ok["content"]
    assert "MSB first" in ok["description"] and "X-Frame-Side" in ok["description"]


def test_the_server_serves_frames_without_the_receivers_compiler(tmp_path: Path) -> None:
    """Encoding needs no Reed-Solomon corrector: the server never loads numba (~100 MiB of
    resident memory with LLVM) nor anything of the receiver."""
    script = f"""
import sys
from fastapi.testclient import TestClient
from eventocc.server.app import create_app
from eventocc.server.settings import Settings
client = TestClient(create_app(Settings(data_dir={str(tmp_path)!r})))
binary = {{"Content-Type": "application/octet-stream"}}
for profile in ("paper", "robust", "fast"):
    url = f"/api/messages?profile={{profile}}&cells=16"
    id = client.post(url, content=b"x" * 300, headers=binary).json()["id"]
    assert client.get(f"/api/messages/{{id}}/frames?count=8").status_code == 200
print(sorted({{m.split(".")[0] for m in sys.modules}} & {{"numba", "llvmlite", "receiver"}}))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
