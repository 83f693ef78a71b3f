"""The dashboard says when the receiver's event source falls behind real time (a virtual camera
or a receiver on a slow machine), in headless Chromium fed by a stand-in receiver over the real
websocket."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from websockets.sync.client import ClientConnection, connect

from eventocc.occ.report import HealthReport, Hello, TrackingState

pytestmark = pytest.mark.browser


@contextmanager
def receiver_socket(base_url: str) -> Iterator[ClientConnection]:
    # The sync client: Playwright's sync API already runs an event loop in this thread.
    with connect("ws" + base_url.removeprefix("http") + "/ws/receiver") as ws:
        ws.send(Hello(receiver_id="rx-slow").model_dump_json())
        ws.recv()  # welcome
        yield ws


def send_health(ws: ClientConnection, speed: float | None) -> None:
    health = HealthReport(
        cpu_load=0.9, events_per_s=1e6, state=TrackingState.TRACKING, source_speed=speed
    )
    ws.send(json.dumps({"seq": None, "report": json.loads(health.model_dump_json())}))


def test_dashboard_shows_the_sources_speed(serve_app, browser) -> None:
    from playwright.sync_api import expect

    base_url, _ = serve_app()
    page = browser.new_page()
    page.goto(f"{base_url}/dashboard")
    expect(page.locator("#connection")).to_have_text("live")
    source = page.locator("#source-speed")
    with receiver_socket(base_url) as ws:  # open until the dashboard has shown each report
        for speed, shown, state in [
            (0.42, "source at 0.42x real time: skipping ahead to stay live", "behind"),
            (1.0, "keeps up with real time", "live"),
            (None, "live", "live"),
        ]:
            send_health(ws, speed)
            expect(source).to_have_text(shown)
            expect(source).to_have_attribute("data-state", state)
