"""The transmitter page in headless Chromium: every frame drawn exactly, once, in order."""

from __future__ import annotations

import base64
import json
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from eventocc.occ.marker import render
from eventocc.occ.stream import StreamEncoder
from eventocc.server.demo import bound_url, start_server
from eventocc.server.settings import Settings

pytestmark = pytest.mark.browser

MESSAGE = b"Motion-aware optical camera communication, drawn one refresh at a time. " * 4
CELL_PX = 10
CAPTURED = 36
STATE = "({...window.eventocc, captured: null})"
# Robust profile: even refreshes are data frames, so pause right after one is drawn.
PAUSE_ON_DATA_FRAME = """() => new Promise((resolve) => {
  const check = () => {
    if (window.eventocc.frameIndex % 2 === 1) resolve(window.eventocc.setPlaying(false));
    else requestAnimationFrame(check);
  };
  requestAnimationFrame(check);
})"""


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    server, thread = start_server(Settings(data_dir=tmp_path_factory.mktemp("data"), port=0))
    yield bound_url(server)
    server.should_exit = True
    thread.join(10)


def post_message(base_url: str, query: str) -> dict:
    request = urllib.request.Request(
        f"{base_url}/api/messages?{query}",
        data=MESSAGE,
        headers={"Content-Type": "application/octet-stream"},
        method="POST",
    )
    with urllib.request.urlopen(request) as response:
        return json.load(response)


def decode_capture(item: dict) -> np.ndarray:
    rgba = np.frombuffer(base64.b64decode(item["rgba"]), np.uint8)
    return rgba.reshape(item["height"], item["width"], 4)


def test_transmitter_draws_each_frame_pixel_exact_in_order(
    base_url: str, browser, artifacts: Path
) -> None:
    message = post_message(base_url, "name=page.txt&profile=robust&cells=16")
    url = f"{base_url}/transmitter?id={message['id']}&cell_px={CELL_PX}&capture={CAPTURED}"
    page = browser.new_page(viewport={"width": 960, "height": 600}, device_scale_factor=1)
    page.goto(url)
    page.wait_for_selector("#warning[open]")
    assert page.is_disabled("#play"), "must not start before the warning is acknowledged"
    page.click("#acknowledge")
    page.wait_for_function("!document.querySelector('#play').disabled")
    page.click("#play")
    page.wait_for_function(f"window.eventocc.captured.length >= {CAPTURED}", timeout=60_000)
    page.wait_for_timeout(1500)  # let the overlay and status report catch up
    captured = page.evaluate("window.eventocc.capturedBase64()")
    page.evaluate(PAUSE_ON_DATA_FRAME)
    state = page.evaluate(STATE)
    page.screenshot(path=artifacts / "transmitter.png")
    page.keyboard.press("Space")
    assert page.evaluate("window.eventocc.playing"), "space starts"
    page.keyboard.press("Space")
    assert not page.evaluate("window.eventocc.playing"), "space pauses"

    encoder = StreamEncoder(MESSAGE, name="page.txt", profile="robust", cells=16)
    assert [c["frameIndex"] for c in captured] == list(range(CAPTURED))
    for item in captured:
        expected = render(encoder.frame(item["frameIndex"]), CELL_PX)
        pixels = decode_capture(item)
        assert pixels.shape[:2] == expected.shape
        for channel in range(3):
            np.testing.assert_array_equal(
                pixels[..., channel], expected, err_msg=str(item["frameIndex"])
            )
        assert (pixels[..., 3] == 255).all()
    # Frames before and after the captured ones were drawn too, still one per refresh.
    assert state["drawn"] == list(range(state["drawn"][0], state["frameIndex"]))
    assert state["refreshHz"] > 0

    with urllib.request.urlopen(f"{base_url}/api/transmitter/status") as response:
        status = json.load(response)
    assert status["message_id"] == message["id"]
    assert status["cell_px"] == CELL_PX
    assert status["frame_index"] >= CAPTURED


def test_an_id_the_server_does_not_hold_plays_nothing_and_says_so(base_url: str, browser) -> None:
    post_message(base_url, "name=other.txt&profile=robust&cells=16")
    page = browser.new_page()
    page.goto(f"{base_url}/transmitter?id=0123456789ab")
    page.wait_for_selector("#error:not([hidden])")
    assert "no message 0123456789ab on this server" in page.text_content("#error")
    page.click("#acknowledge")
    assert page.is_disabled("#play"), "nothing to play"
    assert page.evaluate("window.eventocc.playing") is False
    page.close()


def test_a_closed_page_says_at_once_that_it_no_longer_plays(base_url: str, browser) -> None:
    """A camera watching the screen must not take a closed page for one still playing."""
    message = post_message(base_url, "name=closing.txt&profile=robust&cells=16")
    page = browser.new_page()
    page.goto(f"{base_url}/transmitter?id={message['id']}")
    page.click("#acknowledge")
    page.wait_for_function("!document.querySelector('#play').disabled")
    page.click("#play")
    page.wait_for_function("window.eventocc.frameIndex > 10")
    page.close()
    deadline = time.monotonic() + 0.8  # under the page's one-second report interval
    while time.monotonic() < deadline:
        with urllib.request.urlopen(f"{base_url}/api/transmitter/status") as response:
            status = json.load(response)
        if not status["playing"]:
            break
        time.sleep(0.05)
    assert status["message_id"] == message["id"] and not status["playing"]
