"""The transmitter's mode on the server: ``PUT /api/transmitter/mode``, the answer a page's
status report gets, and the choice among several receivers."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from eventocc.occ.link_policy import LinkChoice, px_at, start_choice
from eventocc.occ.profiles import get_profile
from eventocc.occ.report import FrameStats, Hello
from eventocc.server.app import create_app
from eventocc.server.link_mode import LIVE_POLICY, LinkMode
from eventocc.server.settings import Settings


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        yield client


def frame(choice: LinkChoice, px_at_16: float, passed: bool = True) -> FrameStats:
    return FrameStats(
        t_us=0,
        frame_index=0,
        bits_read=choice.cells**2,
        confidence_mean=0.9,
        events_per_s=1e6,
        payload_bits=96 if passed else 0,
        profile=choice.profile,
        cells=choice.cells,
        passed=passed,
        ber_before_fec=0.0 if passed else None,
        px_per_cell=px_at(px_at_16, 16, choice.cells),
        realtime_margin=2.0,
    )


def feed(mode: LinkMode, seconds: float, cameras: dict[str, float], t0: float = 0.0) -> float:
    """A report for every data frame served (30 a second for ``robust``, 58 for ``fast``) from
    each receiver, reading whatever is served; ``cameras``: each one's pixels per cell at
    N = 16."""
    t = t0
    while t < t0 + seconds:
        choice = mode.choice
        t += 1 / (choice.frame_hz(mode.display_hz) * get_profile(choice.profile).data_share)
        for receiver, px in cameras.items():
            mode.on_frame(receiver, frame(mode.choice, px), t)
    return t


def test_auto_serves_the_weakest_receiver_that_reads_the_link() -> None:
    mode = LinkMode()
    mode.set_mode("auto", None, 0.0)
    assert mode.choice == start_choice(60.0)
    feed(mode, 12.0, {"near": 24.0, "far": 9.0})
    assert mode.choice.cells > 16
    # What the far camera's pixels allow, not the near one's.
    need = mode.config.min_px[mode.choice.profile]
    assert px_at(9.0, 16, mode.choice.cells) >= need
    assert mode.served == "far"
    assert mode.history and mode.history[-1]["settings"] == str(mode.choice)


def test_a_pinned_receiver_sets_the_pace_and_a_silent_one_does_not_hold_it_down() -> None:
    mode = LinkMode()
    mode.set_mode("auto", "near", 0.0)
    feed(mode, 12.0, {"near": 24.0, "far": 9.0})
    assert mode.served == "near"
    need = mode.config.min_px[mode.choice.profile]
    assert px_at(9.0, 16, mode.choice.cells) < need <= px_at(24.0, 16, mode.choice.cells)

    unpinned = LinkMode()
    unpinned.set_mode("auto", None, 0.0)
    t = feed(unpinned, 12.0, {"near": 24.0})
    unpinned.on_frame("blind", frame(unpinned.choice, 24.0, passed=False), t)
    feed(unpinned, 3.0, {"near": 24.0}, t)
    assert unpinned.served == "near"


def test_a_receiver_that_hears_of_a_change_late_is_judged_from_its_first_frame() -> None:
    """The virtual camera looks at the page's status once a second, then locks again: frames
    of new settings start a second or more after a change, which is not a loss; the clean
    window is counted from the first of them."""
    mode = LinkMode()
    mode.set_mode("auto", None, 0.0)
    mode.on_frame("late", frame(LinkChoice("fast", 64), 24.0), 0.0)  # the settings before
    t = feed(mode, 1.2, {})
    feed(mode, 2.5, {"late": 24.0}, t)
    # Judged over the time since the change, 1.2 s of it silent, the window would not pass
    # 85% of the frames sent before 8 s.
    assert mode.choice.cells > 16, mode.reason


def test_a_receiver_that_never_reads_the_new_settings_steps_them_down() -> None:
    mode = LinkMode()
    mode.set_mode("auto", None, 0.0)
    t = feed(mode, 5.0, {"rx": 24.0})
    climbed = mode.choice
    assert climbed.cells > 16
    # From now on it reads nothing of what is sent; a report of the old settings comes late.
    mode.on_frame("rx", frame(start_choice(60.0), 24.0), t + 0.1)
    mode.decide(t + LIVE_POLICY.settle_s + LIVE_POLICY.lost_s)
    assert mode.choice.cells < climbed.cells and "no frame read" in mode.reason


def test_reports_of_the_settings_the_screen_left_are_ignored() -> None:
    mode = LinkMode()
    mode.set_mode("auto", None, 0.0)
    stale = LinkChoice("fast", 64)
    for i in range(300):
        mode.on_frame("rx", frame(stale, 24.0, passed=False), i / 30)
    assert mode.choice == start_choice(60.0)


def test_put_mode_auto_is_what_a_page_is_told(client: TestClient) -> None:
    assert client.get("/api/transmitter/mode").json()["mode"] == "fixed"
    done = client.put("/api/transmitter/mode", json={"mode": "auto"})
    assert done.status_code == 200
    assert done.json()["choice"] == {"profile": "robust", "cells": 16, "hold": 1, "frame_hz": 60.0}
    status = {"playing": True, "refresh_hz": 60.0, "profile": "robust", "cells": 16}
    reply = client.post("/api/transmitter/status", json={**status, "packed": True}).json()
    assert reply["link"]["mode"] == "auto" and reply["link"]["choice"]["cells"] == 16
    assert reply["packed"] is True
    client.put("/api/transmitter/mode", json={"mode": "fixed"})
    assert client.post("/api/transmitter/status", json=status).json()["link"]["choice"] is None


@pytest.mark.parametrize(
    ("body", "code", "says"),
    [
        ({"mode": "turbo"}, 422, "mode"),
        ({}, 422, "mode"),
        ({"mode": "auto", "speed": 3}, 422, "speed"),
        ({"mode": "auto", "pin": "not-an-id"}, 422, "pin"),
        ({"mode": "fixed", "pin": "0123456789abcdef"}, 422, "only auto mode"),
        ({"mode": "auto", "pin": "0123456789abcdef"}, 404, "no receiver 0123456789abcdef"),
    ],
)
def test_bad_mode_requests_are_refused_and_change_nothing(
    client: TestClient, body: dict, code: int, says: str
) -> None:
    client.put("/api/transmitter/mode", json={"mode": "auto"})
    before = client.get("/api/transmitter/mode").json()
    refused = client.put("/api/transmitter/mode", json=body)
    assert refused.status_code == code
    assert says in str(refused.json()["detail"])
    after = client.get("/api/transmitter/mode").json()
    assert {k: after[k] for k in ("mode", "pinned", "choice")} == {
        k: before[k] for k in ("mode", "pinned", "choice")
    }


def test_a_connected_receiver_can_be_pinned(client: TestClient) -> None:
    hello = Hello(receiver_id="secret-rx")
    with client.websocket_connect("/ws/receiver") as ws:
        ws.send_text(hello.model_dump_json())
        ws.receive_json()  # welcome
        done = client.put("/api/transmitter/mode", json={"mode": "auto", "pin": hello.public_id})
        assert done.status_code == 200 and done.json()["pinned"] == hello.public_id


def test_packed_frames_need_a_fountain_profile(client: TestClient) -> None:
    bad = client.post(
        "/api/transmitter/status", json={"profile": "paper", "cells": 16, "packed": True}
    )
    assert bad.status_code == 422


def test_frames_a_slow_source_skipped_are_not_counted_as_losses() -> None:
    """A virtual camera simulating at 0.5x real time shows the receiver half the frames."""
    climbed = {}
    for speed in (None, 0.5):
        mode = LinkMode()
        mode.set_mode("auto", None, 0.0)
        t, i = 0.0, 0
        while t < 6.0:
            t += 1 / 30
            i += 1
            if i % 10 < 5:  # 5 frames in 10 reach the receiver, every one of them passes
                mode.on_frame("sim", frame(mode.choice, 24.0), t)
                mode.on_health("sim", speed)
        climbed[speed] = mode.choice.cells > 16
    assert climbed == {None: False, 0.5: True}
