"""The transmitter page in auto mode, in headless Chromium: it takes up the server's choice at
once, as a new packed segment that goes on from the symbols it already sent."""

from __future__ import annotations

import base64
import json
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from eventocc.occ.link_policy import LinkChoice
from eventocc.occ.marker import render
from eventocc.occ.stream import StreamEncoder
from eventocc.server.demo import bound_url, start_server
from eventocc.server.settings import Settings
from tests.live_clients import upload

pytestmark = pytest.mark.browser

MESSAGE = b"A transmitter that adapts to the camera watching it. " * 20
CELL_PX = 6
VIEWPORT = {"width": 960, "height": 600}
CANVAS_PIXELS = """([side, cellPx]) => {
  const canvas = document.getElementById("marker");
  const size = side * cellPx;
  const x = Math.floor((canvas.width - size) / 2), y = Math.floor((canvas.height - size) / 2);
  const rgba = canvas.getContext("2d").getImageData(x, y, size, size).data;
  let binary = "";
  for (let i = 0; i < rgba.length; i += 0x8000) {
    binary += String.fromCharCode(...rgba.subarray(i, i + 0x8000));
  }
  return btoa(binary);
}"""


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, object]]:
    server, thread = start_server(Settings(data_dir=tmp_path_factory.mktemp("data"), port=0))
    yield bound_url(server), server.config.app
    server.should_exit = True
    thread.join(10)


def get(base_url: str, path: str) -> dict:
    with urllib.request.urlopen(base_url + path) as response:
        return json.load(response)


def wait_for_status(base_url: str, predicate, timeout_s: float = 20.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = get(base_url, "/api/transmitter/status")
        if predicate(status):
            return status
        time.sleep(0.1)
    raise AssertionError(f"the page never reported what was expected; last: {status}")


def play_in_auto(base_url: str, browser, name: str, data: bytes):
    """Upload ``data`` as ``name`` and play it on a transmitter page in auto mode."""
    message = upload(base_url, data, name)  # robust, N = 16: the defaults
    page = browser.new_page(viewport=VIEWPORT, device_scale_factor=1)
    page.goto(f"{base_url}/transmitter?id={message['id']}&cell_px={CELL_PX}&mode=auto")
    page.click("#acknowledge")
    page.wait_for_function("!document.querySelector('#play').disabled")
    page.click("#play")
    return page


def test_the_page_follows_the_servers_choice_without_restarting_the_message(
    served, browser, artifacts: Path
) -> None:
    base_url, app = served
    page = play_in_auto(base_url, browser, "auto.txt", MESSAGE)

    # It starts where any camera reads, packed, and the server says so.
    first = wait_for_status(
        base_url, lambda s: s["packed"] and s["cells"] == 16 and s["frame_index"] > 20
    )
    assert first["profile"] == "robust" and first["symbol_start"] == 0
    assert get(base_url, "/api/transmitter/mode")["mode"] == "auto"
    assert page.is_disabled("#cells"), "in auto the server chooses"

    # The server chooses denser settings: the page takes them up at its next report.
    app.state.live.link.choose(LinkChoice("fast", 32), "a test said so", time.monotonic())
    second = wait_for_status(
        base_url, lambda s: s["cells"] == 32 and s["profile"] == "fast" and s["frame_index"] > 5
    )
    # N = 16 frames carry one symbol each: the new segment starts past every one shown.
    assert second["packed"] and second["symbol_start"] >= first["frame_index"]
    assert page.evaluate("window.eventocc.segments") == 2
    assert "a test said so" in page.text_content("#auto-reason")

    # What is on screen is the packed stream from that symbol on.
    page.evaluate("window.eventocc.setPlaying(false)")
    shown = page.evaluate("window.eventocc.drawn.at(-1)")
    encoder = StreamEncoder(
        MESSAGE,
        name="auto.txt",
        profile="fast",
        cells=32,
        packed=True,
        symbol_start=second["symbol_start"],
    )
    side = encoder.geometry.side
    rgba = np.frombuffer(base64.b64decode(page.evaluate(CANVAS_PIXELS, [side, CELL_PX])), np.uint8)
    pixels = rgba.reshape(side * CELL_PX, side * CELL_PX, 4)[..., 0]
    np.testing.assert_array_equal(pixels, render(encoder.frame(shown), CELL_PX))
    page.screenshot(path=artifacts / "transmitter-auto.png")

    # Back to fixed from the page: the server hears of it, the page sends unpacked again.
    page.select_option("#mode", "fixed")
    page.wait_for_function("window.eventocc.link && window.eventocc.link.mode === 'fixed'")
    assert get(base_url, "/api/transmitter/mode")["mode"] == "fixed"
    assert not page.is_disabled("#cells")
    page.close()


def test_a_held_frame_stays_up_for_its_refreshes_and_the_rate_reported_is_the_frames(
    served, browser
) -> None:
    base_url, app = served
    page = play_in_auto(base_url, browser, "held.txt", MESSAGE[::-1])
    wait_for_status(base_url, lambda s: s["packed"] and s["frame_index"] > 10)
    app.state.live.link.choose(LinkChoice("robust", 16, hold=2), "held", time.monotonic())
    held = wait_for_status(base_url, lambda s: s["hold"] == 2 and s["frame_index"] > 30)
    display_hz = page.evaluate("window.eventocc.refreshHz")
    assert held["refresh_hz"] == pytest.approx(display_hz / 2, rel=0.05)
    # Each frame drawn once, and held: frames advance at half the refresh rate.
    t0, k0 = time.monotonic(), page.evaluate("window.eventocc.frameIndex")
    page.wait_for_timeout(1000)
    frames_per_s = (page.evaluate("window.eventocc.frameIndex") - k0) / (time.monotonic() - t0)
    assert frames_per_s == pytest.approx(display_hz / 2, rel=0.2)
    drawn = page.evaluate("window.eventocc.drawn")
    assert drawn[-20:] == list(range(drawn[-20], drawn[-20] + 20))
    page.select_option("#mode", "fixed")
    page.wait_for_function("window.eventocc.link && window.eventocc.link.mode === 'fixed'")
    page.close()
