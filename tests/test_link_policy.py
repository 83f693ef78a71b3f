"""The closed loop's controller, on made-up receiver reports."""

from __future__ import annotations

import math

import pytest

from eventocc.occ.link_policy import (
    CELLS_LADDER,
    FrameSample,
    LinkChoice,
    LinkMeter,
    LinkPolicy,
    px_at,
    start_choice,
)
from eventocc.occ.profiles import get_profile


def run(
    policy: LinkPolicy,
    current: LinkChoice,
    seconds: float,
    *,
    t0: float = 0.0,
    px_at_16: float | None = 20.0,
    passed: float = 1.0,
    ber: float = 0.0,
    margin: float | None = 2.0,
    readout: float | None = 0.3,
    flow: float = 0.1,
    read: bool = True,
) -> tuple[LinkChoice, list[tuple[str, LinkChoice]], float]:
    """Feed ``seconds`` of reports at 60 Hz, following each decision as a page would; the
    camera sees ``px_at_16`` pixels per cell at N = 16. Returns the settings at the end, each
    change's reason and settings, and the end time."""
    meter = LinkMeter(current, policy.display_hz, t0)
    t, step, reasons = t0, 1 / policy.display_hz, []
    sent, frames = 0.0, 0
    while t < t0 + seconds:
        t += step
        rate = current.frame_hz(policy.display_hz) * get_profile(current.profile).data_share
        sent += rate * step
        if read and sent >= 1.0:
            sent -= 1.0
            frames += 1
            ok = math.floor(frames * passed) > math.floor((frames - 1) * passed)
            px = None if px_at_16 is None else px_at(px_at_16, 16, current.cells)
            meter.add(FrameSample(t, ok, ber if ok else None, px, readout, flow, margin))
        decision = policy.decide(
            current, meter.window(t), meter.window(t, policy.config.loss_window_s), t
        )
        if decision.changed:
            reasons.append((decision.reason, decision.choice))
            current = decision.choice
            meter = LinkMeter(current, policy.display_hz, t)
    return current, reasons, t


def test_it_starts_where_any_camera_reads() -> None:
    assert start_choice(60.0) == LinkChoice("robust", 16, 1)
    assert start_choice(240.0) == LinkChoice("robust", 16, 4)
    assert start_choice(144.0) == LinkChoice("robust", 16, 3)


def test_a_near_camera_climbs_to_what_its_pixels_allow_and_stays() -> None:
    policy = LinkPolicy()
    end, reasons, _ = run(policy, start_choice(60.0), 6.0, px_at_16=20.0)
    assert reasons and all(r.startswith("up") for r, _ in reasons)
    # fast needs 7 px and the margin: the largest N whose pixels per cell still allow it.
    need = policy.config.min_px["fast"] * policy.config.up_margin
    assert end.profile == "fast"
    assert px_at(20.0, 16, end.cells) >= need
    bigger = [n for n in CELLS_LADDER if n > end.cells]
    assert bigger and px_at(20.0, 16, bigger[0]) < need


def test_a_moving_camera_climbs_in_robust_only_and_a_swinging_one_not_at_all() -> None:
    end, reasons, _ = run(LinkPolicy(), start_choice(60.0), 6.0, px_at_16=20.0, flow=1.8)
    assert reasons and end.profile == "robust" and end.cells > 16
    end, reasons, _ = run(LinkPolicy(), start_choice(60.0), 3.0, px_at_16=20.0, flow=3.5)
    assert end == start_choice(60.0) and not reasons


def test_it_never_climbs_on_a_dirty_window() -> None:
    for kwargs in (
        {"passed": 0.8},
        {"margin": 1.1},
        {"px_at_16": None},
    ):
        end, reasons, _ = run(LinkPolicy(), start_choice(60.0), 3.0, **kwargs)
        assert end == start_choice(60.0) and not reasons, kwargs


def test_with_errors_it_climbs_only_where_cells_stay_well_above_what_they_need() -> None:
    policy = LinkPolicy()
    end, reasons, _ = run(policy, start_choice(60.0), 6.0, px_at_16=20.0, ber=0.006)
    assert reasons
    c = policy.config
    assert px_at(20.0, 16, end.cells) >= c.min_px[end.profile] * c.ber_px_margin
    clean, _, _ = run(LinkPolicy(), start_choice(60.0), 6.0, px_at_16=20.0)
    assert clean.payload_bps(60.0) > end.payload_bps(60.0)
    # Where no denser marker keeps that margin, it holds and says why.
    held, reasons, _ = run(LinkPolicy(), start_choice(60.0), 3.0, px_at_16=8.0, ber=0.006)
    assert held == start_choice(60.0) and not reasons


def test_the_frames_before_a_new_lock_are_not_losses() -> None:
    meter = LinkMeter(LinkChoice("robust", 16), 60.0, 0.0)
    for i in range(12):  # it locks 0.3 s after the change, then reads every data frame
        meter.add(FrameSample(0.3 + i / 30, True))
    window = meter.window(0.3 + 12 / 30)
    assert window.pass_share == pytest.approx(1.0, abs=0.1)
    assert window.span_s == pytest.approx(0.7)


def test_losses_step_down_at_once_and_the_failed_setting_waits() -> None:
    policy = LinkPolicy()
    good = LinkChoice("robust", 32)
    policy.worked.append(good)
    bad = LinkChoice("fast", 48)
    _, reasons, t = run(policy, bad, 1.0, passed=0.3, px_at_16=20.0)
    reason, choice = reasons[0]
    assert choice == good
    assert reason.startswith("down from fast N = 48: losses")
    assert policy.banned[bad][0] > t  # not tried again soon


@pytest.mark.parametrize(
    ("kwargs", "why"),
    [
        ({"ber": 0.02}, "BER"),
        ({"margin": 0.8}, "receiver behind"),
        ({"read": False}, "no frame read"),
    ],
)
def test_each_limit_steps_down(kwargs: dict, why: str) -> None:
    policy = LinkPolicy()
    end, reasons, _ = run(policy, LinkChoice("fast", 32), 0.6, **kwargs)
    assert end == start_choice(60.0)
    assert why in reasons[0][0]


def test_a_camera_moving_away_is_followed_down_by_its_pixels() -> None:
    """At N = 64 a camera that drops to 3.5 px per cell at N = 16 (it moved away) goes down
    to an N its pixels fit, not just one rung."""
    policy = LinkPolicy()
    policy.worked += [LinkChoice("robust", 16), LinkChoice("robust", 48)]
    end, reasons, _ = run(policy, LinkChoice("fast", 64), 0.5, px_at_16=8.0, passed=0.0)
    assert reasons[0][0].startswith("down from fast N = 64")
    assert px_at(8.0, 16, end.cells) >= 6.0
    assert end.cells < 48


def test_a_faster_display_offers_its_rate_unless_the_readout_is_full() -> None:
    end, _, _ = run(LinkPolicy(display_hz=120.0), start_choice(120.0), 3.0, px_at_16=30.0)
    assert end.hold == 1
    end, _, _ = run(
        LinkPolicy(display_hz=120.0), start_choice(120.0), 3.0, px_at_16=30.0, readout=0.95
    )
    assert end.hold == 2 and end.cells > 16


def test_settings_are_ranked_by_the_symbols_they_carry() -> None:
    # fast N = 24 shows more cells a second than robust N = 32, but carries fewer symbols.
    fast24, robust32 = LinkChoice("fast", 24), LinkChoice("robust", 32)
    assert fast24.cells**2 * 31 / 32 > robust32.cells**2 / 2
    assert robust32.payload_bps(60.0) > fast24.payload_bps(60.0)


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="paper"):
        LinkChoice("paper", 16)
    with pytest.raises(ValueError, match="cells"):
        LinkChoice("robust", 17)
    with pytest.raises(ValueError, match="hold"):
        LinkChoice("robust", 16, 0)
