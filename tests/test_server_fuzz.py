"""A fuzz of every input the server takes, drawn from its own schemas: each REST operation of
its OpenAPI document, and the reports of ``/ws/receiver`` and statuses of ``/ws/transmitter``
from their pydantic schemas, each value sometimes pushed past its bounds or swapped for any
JSON at all. No answer may be a 500, the log may hold no traceback, every answer must be JSON
a browser can parse, and a receiver that behaves loses no report meanwhile."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from typing import Any
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import TypeAdapter
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from eventocc.occ.report import Hello, Report, public_receiver_id
from eventocc.server.api.schemas import TransmitterStatus
from eventocc.server.app import create_app
from eventocc.server.settings import Settings
from tests.live_clients import Dashboard, ServerLog, envelope, pose, strict_json, ws_url

JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=12,
)
"""Any JSON value, NaN and the infinities among them (``json.dumps`` writes them)."""
NASTY_TEXT = st.sampled_from(
    ["", "[" * 100_000, '{"seq": ' * 50_000, "NaN", "\x00", "日本語", "a\r\nb", "\u202e"]
)


def from_schema(schema: dict, defs: dict) -> st.SearchStrategy:
    """Values of a JSON schema as pydantic writes them (the subset it uses), each sometimes
    pushed just past a bound: what the schema allows, and what is one step outside it."""
    if "$ref" in schema:
        return from_schema(defs[schema["$ref"].rsplit("/", 1)[1]], defs)
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return st.one_of([from_schema(option, defs) for option in schema[key]])
    if "const" in schema:
        return st.just(schema["const"])
    if "enum" in schema:
        return st.sampled_from(schema["enum"])
    kind = schema.get("type")
    if kind in ("integer", "number"):
        low = schema.get("minimum", schema.get("exclusiveMinimum"))
        high = schema.get("maximum", schema.get("exclusiveMaximum"))
        edges = [v + d for v in (low, high) if v is not None for d in (-1, 0, 1)]
        if kind == "integer":
            inside = st.integers(low, high)
            return inside | st.sampled_from(edges or [0]) if edges else inside
        inside = st.floats(low, high, allow_nan=False, allow_infinity=False)
        return inside | st.sampled_from(edges) if edges else inside
    if kind == "string":
        if "pattern" in schema:
            return st.from_regex(schema["pattern"], fullmatch=True) | st.text(max_size=16)
        return st.text(max_size=40)
    if kind == "boolean":
        return st.booleans()
    if kind == "null":
        return st.none()
    if kind == "array":
        return st.tuples(*(from_schema(item, defs) for item in schema["prefixItems"])).map(list)
    if kind == "object":
        properties = schema["properties"]
        required = set(schema.get("required", ())) | {
            name for name, p in properties.items() if "const" in p
        }
        return st.fixed_dictionaries(
            {name: from_schema(properties[name], defs) for name in required},
            optional={
                name: from_schema(p, defs) for name, p in properties.items() if name not in required
            },
        )
    return JSON_VALUES


def broken(values: st.SearchStrategy[dict]) -> st.SearchStrategy[Any]:
    """A schema's objects, as they are, with one field replaced by any JSON, or not objects."""

    def replace_one(value: dict, data: st.DataObject) -> dict:
        if not value:
            return value
        field = data.draw(st.sampled_from(sorted(value)))
        return {**value, field: data.draw(JSON_VALUES)}

    swapped = st.tuples(values, st.data()).map(lambda pair: replace_one(*pair))
    return st.one_of(values, swapped, JSON_VALUES)


def schema_of(adapter: TypeAdapter) -> st.SearchStrategy:
    schema = adapter.json_schema()
    return from_schema(schema, schema.get("$defs", {}))


REPORTS = broken(schema_of(TypeAdapter(Report)))
STATUSES = broken(schema_of(TypeAdapter(TransmitterStatus)))


def frame_text(value: Any) -> str:
    return json.dumps(value)  # NaN and the infinities as the literals JSON does not have


# --- REST ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One app for every example (state carries over, as on a live server); an exception in
    it fails the example (``raise_server_exceptions``)."""
    settings_ = Settings(data_dir=tmp_path_factory.mktemp("data"), max_upload_bytes=4096)
    with TestClient(create_app(settings_)) as client:
        uploads = [client.post("/api/messages", json={"text": text}) for text in ("a", "b")]
        client.message_ids = [u.json()["id"] for u in uploads]  # some examples delete them
        yield client


def operations(client: TestClient) -> list[tuple[str, str, dict]]:
    document = client.app.openapi()
    return [
        (method.upper(), path, operation)
        for path, methods in document["paths"].items()
        for method, operation in methods.items()
    ]


@st.composite
def requests(draw: st.DrawFn, client: TestClient) -> dict:
    """One request to one operation, its parameters and body drawn from the OpenAPI document."""
    document = client.app.openapi()
    defs = document["components"]["schemas"]
    method, path, operation = draw(st.sampled_from(operations(client)))
    query = {}
    for parameter in operation.get("parameters", []):
        values = from_schema(parameter["schema"], defs) | st.text(max_size=12)
        if parameter["in"] == "path":
            value = draw(st.sampled_from(client.message_ids) | values)
            path = path.replace(f"{{{parameter['name']}}}", quote(str(value), safe=""))
        elif draw(st.booleans()):
            query[parameter["name"]] = draw(values)
    request: dict = {"method": method, "url": path, "params": query, "headers": {}}
    content = operation.get("requestBody", {}).get("content", {})
    if content:
        media_type = draw(st.sampled_from([*content, "text/plain"]))
        schema = content.get(media_type, {}).get("schema", {})
        if media_type == "multipart/form-data":
            name = draw(st.text(max_size=12))
            request["files"] = {draw(st.sampled_from(["file", "f"])): (name, draw(st.binary()))}
        elif media_type == "application/json":
            body = draw(
                broken(from_schema(schema, defs)) if "properties" in schema else JSON_VALUES
            )
            request["content"] = draw(st.just(frame_text(body)) | NASTY_TEXT)
            request["headers"]["Content-Type"] = media_type
        else:
            request["content"] = draw(st.binary(max_size=512))
            request["headers"]["Content-Type"] = media_type
    origin = draw(st.sampled_from([None, "http://testserver", "http://evil.example", "null"]))
    if origin:
        request["headers"]["Origin"] = origin
    return request


@settings(
    max_examples=400,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_rest_fuzz_answers_no_500_and_only_json_a_browser_parses(
    client: TestClient, data: st.DataObject
) -> None:
    request = data.draw(requests(client))
    response = client.request(**request)
    assert response.status_code < 500, (request, response.text)
    if response.content and response.headers.get("content-type", "").startswith("application/json"):
        strict_json(response.content)


# --- websockets --------------------------------------------------------------------------------
class Bystander:
    """A receiver that behaves, and a dashboard, beside the fuzz: the receiver's every report
    must be acknowledged and kept, and the dashboard must get only JSON a browser parses."""

    def __init__(self, base_url: str) -> None:
        self._connections = contextlib.ExitStack()
        self.receiver = self._connections.enter_context(connect(ws_url(base_url, "/ws/receiver")))
        self.receiver.send(Hello(receiver_id="bystander").model_dump_json())
        self.receiver.recv(5)  # welcome
        self.sent = 0
        self.dashboard = Dashboard(base_url)

    def report(self) -> None:
        self.sent += 1
        self.receiver.send(envelope(self.sent, pose(self.sent)))
        assert json.loads(self.receiver.recv(10)) == {"type": "ack", "seq": self.sent}

    def close(self) -> None:
        self._connections.close()
        self.dashboard.close()


def exchange(url: str, first: str | bytes, then: list[str | bytes]) -> None:
    """Send the frames, then read what the server answers until it closes or goes quiet."""
    with connect(url, max_size=None) as ws:
        try:
            for frame in [first, *then]:
                ws.send(frame)
            while True:
                ws.recv(0.2)
        except (ConnectionClosed, TimeoutError):
            pass


RECEIVER_FRAMES = st.one_of(
    st.builds(lambda seq, report: frame_text({"seq": seq, "report": report}),
              st.none() | st.integers(min_value=-2, max_value=2**64) | JSON_VALUES, REPORTS),
    JSON_VALUES.map(frame_text),
    NASTY_TEXT,
    st.binary(max_size=16),
)  # fmt: skip
HELLOS = st.one_of(
    st.builds(lambda rid: Hello(receiver_id=rid).model_dump_json(), st.text(min_size=1)),
    JSON_VALUES.map(frame_text),
    NASTY_TEXT,
    st.binary(max_size=8),
)


@pytest.fixture(scope="module")
def live_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Any]]:
    from eventocc.server.demo import bound_url, start_server

    settings_ = Settings(data_dir=tmp_path_factory.mktemp("live"), port=0)
    server, thread = start_server(settings_)
    yield bound_url(server), server.config.app
    server.should_exit = True
    thread.join(10)


@pytest.fixture(scope="module")
def bystander(live_server) -> Iterator[Bystander]:
    base_url, app = live_server
    watcher = Bystander(base_url)
    with ServerLog() as server_log:
        yield watcher
    watcher.close()
    assert server_log.errors() == [], "\n".join(server_log.errors())
    assert (watcher.dashboard.unparsable, watcher.dashboard.closed_with) == (0, None)
    kept = app.state.live.receptions.poses(public_receiver_id("bystander"))
    assert [row[0] for row in kept] == list(range(1, watcher.sent + 1))


@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(hello=HELLOS, frames=st.lists(RECEIVER_FRAMES, max_size=4))
def test_receiver_socket_fuzz_harms_no_other_receiver(
    live_server, bystander: Bystander, hello: str | bytes, frames: list
) -> None:
    base_url, _ = live_server
    exchange(ws_url(base_url, "/ws/receiver"), hello, frames)
    bystander.report()


@settings(
    max_examples=100,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(frames=st.lists(STATUSES.map(frame_text) | NASTY_TEXT | st.binary(max_size=8), min_size=1))
def test_transmitter_socket_fuzz_keeps_only_statuses_receivers_follow(
    live_server, bystander: Bystander, frames: list
) -> None:
    base_url, app = live_server
    exchange(ws_url(base_url, "/ws/transmitter"), frames[0], frames[1:])
    kept = app.state.live.transmitter
    if kept is not None:
        TransmitterStatus.model_validate(kept.model_dump())
    bystander.report()


def test_the_fuzz_reached_the_dashboard(bystander: Bystander) -> None:
    """Runs after the fuzz of this module (pytest keeps file order)."""
    assert bystander.sent > 0 and bystander.dashboard.updates
