"""Clients of the live routes for the tests that drive a real server over loopback: a
receiver's handshake and envelopes, REST calls, and the reports they send."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import threading
import time
import urllib.request

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as sync_connect

from eventocc.occ.report import (
    Hello,
    MessageReport,
    PoseReport,
    TrackingState,
    public_receiver_id,
)
from eventocc.occ.stream import ReceivedMessage

TOKEN = "s3cret-token"
RX_1 = public_receiver_id("rx-1")
"""What the server shows of the receiver whose secret id is ``rx-1``."""
TEXT = b"received over the air"


def wait_until(condition, timeout_s: float = 30.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def ws_url(base_url: str, path: str) -> str:
    return "ws" + base_url.removeprefix("http") + path


def get(base_url: str, path: str) -> bytes:
    with urllib.request.urlopen(base_url + path, timeout=5) as response:
        return response.read()


def post_json(base_url: str, path: str, body: dict) -> dict:
    request = urllib.request.Request(
        base_url + path,
        data=json.dumps(body).encode(),
        headers={"Content-Type": "application/json"},
        method="POST",
    )
    with urllib.request.urlopen(request, timeout=10) as response:
        return json.load(response)


def upload(base_url: str, data: bytes, name: str = "note.txt") -> dict:
    request = urllib.request.Request(
        f"{base_url}/api/messages?name={name}",
        data=data,
        headers={"Content-Type": "application/octet-stream", "Authorization": f"Bearer {TOKEN}"},
        method="POST",
    )
    with urllib.request.urlopen(request, timeout=5) as response:
        return json.load(response)


def message_report(data: bytes = TEXT, name: str = "note.txt") -> MessageReport:
    digest = hashlib.sha256(data).hexdigest()  # as the robust profile's sender sent it in-band
    return MessageReport.of(ReceivedMessage(name, data, digest, 7, "robust", digest))


def pose(t_us: int, verified: bool = True) -> PoseReport:
    return PoseReport(
        t_us=t_us,
        position=(0.1, 0.2, -0.5),
        quaternion_xyzw=(0.0, 0.0, 0.0, 1.0),
        state=TrackingState.TRACKING,
        verified=verified,
    )


def envelope(seq: int | None, report) -> str:
    return json.dumps({"seq": seq, "report": json.loads(report.model_dump_json())})


async def open_receiver(base_url: str, receiver_id: str = "rx-1", token: str | None = TOKEN):
    ws = await connect(ws_url(base_url, "/ws/receiver"))
    await ws.send(Hello(receiver_id=receiver_id, token=token).model_dump_json())
    return ws, json.loads(await ws.recv())


async def close_code(base_url: str, first: str, then: str | bytes | None = None) -> tuple[int, str]:
    async with connect(ws_url(base_url, "/ws/receiver")) as ws:
        await ws.send(first)
        if then is not None:
            await ws.recv()  # welcome
            await ws.send(then)
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                await asyncio.wait_for(ws.recv(), 5)
    return closed.value.rcvd.code, closed.value.rcvd.reason


class ServerLog(logging.Handler):
    """What the server logs while this is entered: uvicorn's log (which does not reach the
    root logger), asyncio's and ours."""

    LOGGERS = ("uvicorn.error", "asyncio", "eventocc")

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def __enter__(self) -> ServerLog:
        for name in self.LOGGERS:
            logging.getLogger(name).addHandler(self)
        return self

    def __exit__(self, *exc: object) -> None:
        for name in self.LOGGERS:
            logging.getLogger(name).removeHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def errors(self) -> list[str]:
        """Every record of a server error: a traceback or a message at level ERROR or above."""
        return [self.format(r) for r in self.records if r.exc_info or r.levelno >= logging.ERROR]


def strict_json(text: str | bytes) -> object:
    """``json.loads`` as a browser's ``JSON.parse``: NaN and Infinity are not JSON."""

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


class Dashboard:
    """A dashboard viewer reading in a thread, keeping what a browser's JSON.parse takes."""

    def __init__(self, base_url: str) -> None:
        self._connection = contextlib.ExitStack()
        self.socket = self._connection.enter_context(
            sync_connect(ws_url(base_url, "/ws/dashboard"), max_queue=None)
        )
        self.updates: list[dict] = []
        self.unparsable = 0
        self.closed_with: int | None = None
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for text in self.socket:
                try:
                    self.updates.append(strict_json(text))
                except ValueError:
                    self.unparsable += 1
        except ConnectionClosed as closed:
            self.closed_with = closed.rcvd.code if closed.rcvd else None

    def poses_since(self, mark: int) -> int:
        return sum(u["type"] == "pose" for u in self.updates[mark:])

    def close(self) -> None:
        self._connection.close()
        self._thread.join(10)
