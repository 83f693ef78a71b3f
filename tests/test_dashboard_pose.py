"""The dashboard's pose, frame and message views in headless Chromium, fed by a stand-in receiver
over the real websocket: the 3-D view and orientation, tentative against verified poses, the
decoded cells, what the camera sees while it cannot lock, and progress bars that end with their
message."""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from pydantic import BaseModel
from websockets.sync.client import ClientConnection, connect

from eventocc.occ.report import (
    CellsReport,
    HealthReport,
    Hello,
    PoseReport,
    ProgressReport,
    TrackingState,
)
from tests.live_clients import message_report

pytestmark = pytest.mark.browser


@contextmanager
def receiver_socket(base_url: str) -> Iterator[ClientConnection]:
    # The sync client: Playwright's sync API already runs an event loop in this thread.
    with connect("ws" + base_url.removeprefix("http") + "/ws/receiver") as ws:
        ws.send(Hello(receiver_id="rx-pose").model_dump_json())
        ws.recv()  # welcome
        yield ws


def send(ws: ClientConnection, report: BaseModel, seq: int | None = None) -> None:
    ws.send(json.dumps({"seq": seq, "report": json.loads(report.model_dump_json())}))


def open_dashboard(serve_app, browser):
    from playwright.sync_api import expect

    base_url, _ = serve_app()
    page = browser.new_page(viewport={"width": 1200, "height": 1000})
    page.goto(f"{base_url}/dashboard")
    expect(page.locator("#connection")).to_have_text("live")
    return base_url, page


def test_a_progress_bar_ends_with_its_message_even_when_unnamed(serve_app, browser) -> None:
    """The stream's metadata (its name) had not decoded when the last progress report went out,
    so the bar is "stream 7": the finished message must still remove it."""
    from playwright.sync_api import expect

    base_url, page = open_dashboard(serve_app, browser)
    bars = page.locator("#progress li")
    with receiver_socket(base_url) as ws:
        send(ws, ProgressReport(stream_id=7, symbols_held=5, symbols_needed=8))
        expect(bars).to_have_count(1)
        expect(bars.first).to_contain_text("stream 7: 5/8 symbols")
        send(ws, message_report(), seq=1)  # stream 7, named "note.txt"
        expect(page.locator("#receptions li")).to_contain_text("note.txt")
        expect(bars).to_have_count(0)


def pose_report(t_us: int, yaw_deg: float, verified: bool) -> PoseReport:
    half = math.radians(yaw_deg) / 2  # about the marker's z axis
    return PoseReport(
        t_us=t_us,
        position=(0.136 + 0.1 * math.sin(t_us / 2e5), 0.136, -0.8),
        quaternion_xyzw=(0.0, 0.0, math.sin(half), math.cos(half)),
        state=TrackingState.TRACKING,
        verified=verified,
    )


def pixels_of(page, canvas: str, rgb: tuple[int, int, int]) -> int:
    """Pixels of ``canvas`` within a few levels of ``rgb`` (lines are anti-aliased)."""
    return page.evaluate(
        """([id, rgb]) => {
            const c = document.getElementById(id);
            const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
            let n = 0;
            for (let i = 0; i < d.length; i += 4) {
              if (d[i + 3] > 200 && rgb.every((v, k) => Math.abs(d[i + k] - v) < 12)) n++;
            }
            return n;
        }""",
        [canvas, list(rgb)],
    )


TENTATIVE_RGB, VERIFIED_RGB = (0xF0, 0xA0, 0x4B), (0x5F, 0xB3, 0xFF)


def test_the_3d_view_shows_orientation_and_tentative_then_verified_poses(
    serve_app, browser, artifacts
) -> None:
    from playwright.sync_api import expect

    base_url, page = open_dashboard(serve_app, browser)
    status = page.locator("#pose-status")
    with receiver_socket(base_url) as ws:
        for i in range(20):
            send(ws, pose_report(10_000 * i, 30.0, verified=False), seq=i + 1)
        expect(status).to_have_text("tentative: no frame has proven the lock yet")
        expect(page.locator("#orientation")).to_have_text("roll +0.0° pitch +0.0° yaw +30.0°")
        expect(page.locator("#quaternion")).to_have_text("q (x y z w) 0.000 0.000 0.259 0.966")
        expect(page.locator("#pose-lag")).to_contain_text("ms behind the quickest pose")
        assert pixels_of(page, "scene-view", TENTATIVE_RGB) > 50, "a tentative frustum, in orange"
        assert pixels_of(page, "scene-view", VERIFIED_RGB) == 0
        for i in range(20, 40):
            send(ws, pose_report(10_000 * i, -45.0, verified=True), seq=i + 1)
        expect(status).to_have_text("verified")
        expect(page.locator("#orientation")).to_have_text("roll +0.0° pitch +0.0° yaw -45.0°")
        assert pixels_of(page, "scene-view", VERIFIED_RGB) > 50, "the verified frustum, in blue"
        assert pixels_of(page, "scene-view", TENTATIVE_RGB) > 0, "the trail's tentative part"
        send(ws, decoded_cells())
        send(ws, cannot_lock())
        expect(page.locator("#cells-caption")).to_contain_text("1 cell corrected")
        expect(page.locator("#sight")).to_contain_text("camera sees ~2.4 px per cell")
        page.screenshot(path=str(artifacts / "dashboard-pose.png"), full_page=True)


def decoded_cells() -> CellsReport:
    bits = np.eye(4, dtype=bool)
    corrected = np.zeros((4, 4), bool)
    corrected[0, 1] = True
    pack = lambda a: base64.b64encode(np.packbits(a.reshape(-1)).tobytes()).decode()  # noqa: E731
    return CellsReport(
        t_us=5, frame_index=3, cells=4, bits_b64=pack(bits), corrected_b64=pack(corrected)
    )


def cannot_lock() -> HealthReport:
    return HealthReport(
        cpu_load=0.5,
        events_per_s=2e5,
        state=TrackingState.SCANNING,
        px_per_cell=2.4,
        detection_failure="spatial: no inner-locator 'L' found (score 0.12)",
    )


def test_the_decoded_cells_show_the_corrected_ones(serve_app, browser) -> None:
    from playwright.sync_api import expect

    base_url, page = open_dashboard(serve_app, browser)
    with receiver_socket(base_url) as ws:
        send(ws, decoded_cells())
        expect(page.locator("#cells-caption")).to_have_text(
            "frame #3, 4x4 cells: decoded, 1 cell corrected (red)"
        )
        cell = lambda row, col: page.evaluate(  # noqa: E731
            """([r, c]) => Array.from(document.getElementById("cells-view").getContext("2d")
                .getImageData(c * 64 + 32, r * 64 + 32, 1, 1).data.slice(0, 3))""",
            [row, col],
        )
        assert cell(0, 1) == [0xFF, 0x5A, 0x5A], "corrected: red"
        assert cell(0, 0) == [0xE6, 0xE8, 0xEE], "a 1: white"
        assert cell(1, 0) == [0x1B, 0x1E, 0x27], "a 0: dark"
        send(ws, decoded_cells().model_copy(update={"corrected_b64": None}))
        expect(page.locator("#cells-caption")).to_contain_text("not decoded on its own")


def test_while_it_cannot_lock_the_dashboard_says_what_the_camera_sees(serve_app, browser):
    from playwright.sync_api import expect

    base_url, page = open_dashboard(serve_app, browser)
    sight = page.locator("#sight")
    with receiver_socket(base_url) as ws:
        send(ws, cannot_lock())
        expect(sight).to_have_text(
            "camera sees ~2.4 px per cell; fewer than the 4 px per cell the receiver is tested "
            "at: move closer or send fewer cells; cannot lock: spatial: no inner-locator 'L' "
            "found (score 0.12)"
        )
        expect(sight).to_have_attribute("data-state", "behind")
        locked = cannot_lock().model_copy(
            update={"px_per_cell": 9.0, "detection_failure": None, "state": TrackingState.TRACKING}
        )
        send(ws, locked)
        expect(sight).to_have_text("camera sees ~9.0 px per cell")
        expect(sight).to_have_attribute("data-state", "live")
