"""The dashboard shows what auto mode sends and why, in headless Chromium, with a stand-in
receiver sending frame reports over the real websocket to the real server's controller."""

from __future__ import annotations

import json
import time
import urllib.request

import pytest
from websockets.sync.client import connect

from eventocc.occ.link_policy import px_at
from eventocc.occ.report import FrameStats, Hello

pytestmark = pytest.mark.browser

PX_AT_16 = 20.0


def mode(base_url: str) -> dict:
    with urllib.request.urlopen(f"{base_url}/api/transmitter/mode") as response:
        return json.load(response)


def test_dashboard_shows_the_chosen_settings_why_and_the_goodput(serve_app, browser) -> None:
    from playwright.sync_api import expect

    base_url, _ = serve_app()
    request = urllib.request.Request(
        f"{base_url}/api/transmitter/mode",
        data=b'{"mode": "auto"}',
        headers={"Content-Type": "application/json"},
        method="PUT",
    )
    urllib.request.urlopen(request).close()
    page = browser.new_page()
    page.goto(f"{base_url}/dashboard")
    expect(page.locator("#connection")).to_have_text("live")
    expect(page.locator("#link-mode")).to_have_text("auto")
    expect(page.locator("#link-choice")).to_contain_text("robust, 16 cells")

    # A camera that reads every frame at 20 px per cell at N = 16: the server steps up.
    with connect("ws" + base_url.removeprefix("http") + "/ws/receiver") as ws:
        ws.send(Hello(receiver_id="rx-adapt").model_dump_json())
        ws.recv()  # welcome
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and mode(base_url)["choice"]["cells"] == 16:
            choice = mode(base_url)["choice"]
            for _ in range(3):
                report = FrameStats(
                    t_us=0,
                    frame_index=0,
                    bits_read=choice["cells"] ** 2,
                    confidence_mean=0.9,
                    events_per_s=1e6,
                    payload_bits=96,
                    profile=choice["profile"],
                    cells=choice["cells"],
                    passed=True,
                    ber_before_fec=0.0,
                    px_per_cell=px_at(PX_AT_16, 16, choice["cells"]),
                    realtime_margin=3.0,
                )
                ws.send(json.dumps({"seq": None, "report": json.loads(report.model_dump_json())}))
            time.sleep(0.1)
        chosen = mode(base_url)["choice"]
        assert chosen["cells"] > 16, "the controller never stepped up"
        expect(page.locator("#link-choice")).to_contain_text(f"{chosen['cells']} cells")
        expect(page.locator("#link-reason")).to_contain_text("up from robust N = 16")
        expect(page.locator("#link-goodput")).not_to_have_text("–")
        expect(page.locator("#link-served")).not_to_have_text("–")
