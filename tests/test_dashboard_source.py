"""The dashboard says when the receiver's event source falls behind real time (a virtual camera
or a receiver on a slow machine), in headless Chromium fed by a stand-in receiver over the real
websocket."""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from websockets.sync.client import ClientConnection, connect

from eventocc.occ.report import CameraReport, HealthReport, Hello, TrackingState

pytestmark = pytest.mark.browser


@contextmanager
def receiver_socket(base_url: str) -> Iterator[ClientConnection]:
    # The sync client: Playwright's sync API already runs an event loop in this thread.
    with connect("ws" + base_url.removeprefix("http") + "/ws/receiver") as ws:
        ws.send(Hello(receiver_id="rx-slow").model_dump_json())
        ws.recv()  # welcome
        yield ws


def send_health(
    ws: ClientConnection, speed: float | None, camera: CameraReport | None = None
) -> None:
    health = HealthReport(
        cpu_load=0.9,
        events_per_s=1e6,
        state=TrackingState.TRACKING,
        source_speed=speed,
        camera=camera,
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


def test_dashboard_shows_the_cameras_readings_and_usb_losses(serve_app, browser, artifacts):
    from playwright.sync_api import expect

    base_url, _ = serve_app()
    page = browser.new_page(viewport={"width": 1100, "height": 760})
    page.goto(f"{base_url}/dashboard")
    expect(page.locator("#connection")).to_have_text("live")
    camera = page.locator("#camera")
    evk4 = CameraReport(
        temperature_c=38.25, illuminance=1500, illuminance_unit="count", max_event_rate=1e8
    )
    lossy = evk4.model_copy(update={"usb_overflows": 3, "usb_lost_s": 0.0123})
    metavision = CameraReport(temperature_c=41, illuminance=250, illuminance_unit="lux")
    with receiver_socket(base_url) as ws:
        for report, shown, state in [
            (evk4, "38.3 °C, light sensor 1500, limit 100.0 Mev/s", "live"),
            (lossy, "limit 100.0 Mev/s, USB lost packets 3x (12 ms of events)", "behind"),
            (metavision, "41.0 °C, 250 lux, no rate limit", "live"),
            (None, "–", "live"),
        ]:
            send_health(ws, 1.0, report)
            expect(camera).to_contain_text(shown)
            expect(camera).to_have_attribute("data-state", state)
            if report is lossy:
                page.screenshot(path=str(artifacts / "dashboard-camera.png"), full_page=True)
