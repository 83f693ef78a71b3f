"""The closed loop's controller, on made-up receiver reports."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest

from eventocc.occ.link_policy import (
    CELLS_LADDER,
    EVK4_MIN_PX,
    FrameSample,
    LinkChoice,
    LinkMeter,
    LinkPolicy,
    LinkWindow,
    PolicyConfig,
    px_at,
    start_choice,
)
from eventocc.occ.profiles import get_profile

CAMERA_PX = {"robust": 6.0, "fast": 7.0}
"""What the made-up camera's cells need: the tests' figures are worked out for these."""


def camera_policy(display_hz: float = 60.0) -> LinkPolicy:
    return LinkPolicy(display_hz, PolicyConfig(min_px=CAMERA_PX))


def run(
    policy: LinkPolicy,
    current: LinkChoice,
    seconds: float,
    *,
    t0: float = 0.0,
    px_at_16: float | None = 20.0,
    passed: float | Callable[[float], float] = 1.0,
    ber: float | Callable[[float], float] = 0.0,
    margin: float | None = 2.0,
    readout: float | None = 0.3,
    flow: float = 0.1,
    read: bool = True,
    reads_down_to: dict[str, float] | None = None,
) -> tuple[LinkChoice, list[tuple[str, LinkChoice]], float]:
    """Feed ``seconds`` of reports at 60 Hz, following each decision as a page would; the
    camera sees ``px_at_16`` pixels per cell at N = 16. Returns the settings at the end, each
    change's reason and settings, and the end time. ``passed`` and ``ber``: a share and a BER,
    or one for each time. ``reads_down_to``: pixels per cell below which the camera passes no
    frame of a profile (None: it passes them at any size)."""
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
            share = passed(t) if callable(passed) else passed
            ok = math.floor(frames * share) > math.floor((frames - 1) * share)
            px = None if px_at_16 is None else px_at(px_at_16, 16, current.cells)
            if reads_down_to and px is not None and px < reads_down_to[current.profile]:
                ok = False
            b = ber(t) if callable(ber) else ber
            meter.add(FrameSample(t, ok, b if ok else None, px, readout, flow, margin))
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
    """A camera that reads every frame down to what the profiles need: the climb ends at the
    largest N whose pixels per cell still allow ``fast``, the last step a probe (the cells
    within ``up_margin`` of what they need), and no step fails."""
    policy = camera_policy()
    c = policy.config
    end, reasons, _ = run(policy, start_choice(60.0), 6.0, px_at_16=20.0, reads_down_to=CAMERA_PX)
    assert reasons and all(r.startswith(("up", "probe from")) for r, _ in reasons)
    assert end.profile == "fast"
    assert c.min_px["fast"] <= px_at(20.0, 16, end.cells) < c.min_px["fast"] * c.up_margin
    assert reasons[-1] == (reasons[-1][0], end) and reasons[-1][0].startswith("probe from")
    bigger = [n for n in CELLS_LADDER if n > end.cells]
    assert bigger and px_at(20.0, 16, bigger[0]) < c.min_px["fast"] * c.probe_margin


def test_a_probe_that_fails_goes_back_at_once_and_is_not_tried_again() -> None:
    """Cells predicted just below what ``fast`` needs with the margin: the step is probed; the
    camera reads nothing there, so the link goes back at once and stays, the
    failed probe remembered, until the camera comes closer."""
    policy = camera_policy()
    c = policy.config
    fast40 = LinkChoice("fast", 40)
    px16 = 19.2  # 7.7 px per cell at N = 40, 6.8 at N = 48: below the 7 fast needs
    assert c.probe_margin <= px_at(px16, 16, 48) / c.min_px["fast"] < 1.0
    end, reasons, t = run(policy, fast40, 6.0, px_at_16=px16, reads_down_to=CAMERA_PX)
    assert [ch for _, ch in reasons] == [LinkChoice("fast", 48), fast40], reasons
    assert reasons[0][0].startswith("probe from") and "failed" in reasons[1][0]
    assert end == fast40
    # Closer by the retry gain, it is tried again (and now read).
    closer = px16 * c.probe_retry_gain * 1.03
    assert px_at(closer, 16, 48) >= c.min_px["fast"]
    end, reasons, _ = run(policy, fast40, 2.0, t0=t, px_at_16=closer, reads_down_to=CAMERA_PX)
    assert end == LinkChoice("fast", 48) and reasons[0][0].startswith(("probe from", "up"))


def test_a_moving_camera_climbs_in_robust_only_and_a_swinging_one_not_at_all() -> None:
    for flow in (0.5, 1.8):  # a slow hand moves a 60 Hz frame of 8 px cells by a cell
        end, reasons, _ = run(camera_policy(), start_choice(60.0), 6.0, px_at_16=20.0, flow=flow)
        assert reasons and all(c.profile == "robust" for _, c in reasons) and end.cells > 16
    end, reasons, _ = run(camera_policy(), start_choice(60.0), 3.0, px_at_16=20.0, flow=3.5)
    assert end == start_choice(60.0) and not reasons


def test_it_never_climbs_on_a_dirty_window() -> None:
    for kwargs in (
        {"passed": 0.5},
        {"margin": 1.1},
        {"px_at_16": None},
    ):
        end, reasons, _ = run(camera_policy(), start_choice(60.0), 3.0, **kwargs)
        assert end == start_choice(60.0) and not reasons, kwargs
    # Cells near what they need (7.4 px at robust N = 56, N = 64 would fit): nearly every
    # frame must pass.
    robust56 = LinkChoice("robust", 56)
    end, reasons, _ = run(camera_policy(), robust56, 3.0, px_at_16=25.3, flow=1.0, passed=0.8)
    assert end == robust56 and not reasons


def test_errors_near_the_limit_stop_the_climb_and_errors_far_from_it_do_not() -> None:
    c = camera_policy().config
    # A hand-held camera (robust only) with 25.3 px per cell at N = 16: 7.4 at N = 56, near
    # the 6 robust needs; robust N = 64 would still fit.
    px16, robust56 = 25.3, LinkChoice("robust", 56)
    assert px_at(px16, 16, 56) < c.min_px["robust"] * c.far_margin
    assert px_at(px16, 16, 64) >= c.min_px["robust"] * c.up_margin
    clean, _, _ = run(
        camera_policy(), robust56, 3.0, px_at_16=px16, flow=1.0, reads_down_to=CAMERA_PX
    )
    assert clean == LinkChoice("robust", 64)
    policy = camera_policy()
    held, reasons, _ = run(policy, robust56, 3.0, px_at_16=px16, flow=1.0, ber=0.006)
    assert held == robust56 and not reasons
    # The same errors at cells far above what they need come from elsewhere: they do not
    # pin N, and it climbs as a clean link climbs. (At N = 64, near the limit, the clean link
    # then probes N = 72, which this camera does not read; the noisy one does not probe.)
    end, reasons, _ = run(
        camera_policy(), start_choice(60.0), 4.0, px_at_16=px16, flow=1.0, reads_down_to=CAMERA_PX
    )
    noisy, noisy_reasons, _ = run(
        camera_policy(),
        start_choice(60.0),
        4.0,
        px_at_16=px16,
        flow=1.0,
        ber=0.006,
        reads_down_to=CAMERA_PX,
    )
    assert noisy == end == LinkChoice("robust", 64)
    climb = [ch for _, ch in noisy_reasons]
    assert climb[-1] == noisy and [ch for _, ch in reasons][: len(climb)] == climb


def test_frames_lost_at_cells_far_above_what_they_need_do_not_stop_the_climb() -> None:
    """A full readout or a moving camera fails some frames whatever the cells: at 20 px per
    cell, 70% passing is no reason to stay at N = 16."""
    end, reasons, _ = run(camera_policy(), start_choice(60.0), 3.0, px_at_16=20.0, passed=0.7)
    assert reasons and end.cells > 16


def test_a_swinging_camera_is_judged_by_its_fewest_pixels_per_cell() -> None:
    """Reports at 20 and 17 px per cell at N = 16 by turns: the step up must fit 17."""
    policy, meter = camera_policy(), LinkMeter(start_choice(60.0), 60.0, 0.0)
    for i in range(30):
        meter.add(FrameSample(i / 30, True, 0.0, 20.0 if i % 2 else 17.0, 0.3, 1.0, 2.0))
    window = meter.window(1.0)
    assert window.px_per_cell == 20.0 and window.px_per_cell_low == 17.0
    up = policy.decide(start_choice(60.0), window, meter.window(1.0, 0.3), 1.0)
    assert up.changed and up.choice.profile == "robust"
    need = 6.0 * policy.config.up_margin
    assert px_at(17.0, 16, 48) < need <= px_at(20.0, 16, 48)  # the latest alone allows 48
    assert up.choice.cells == 40 and px_at(17.0, 16, 40) >= need


def test_the_frames_before_a_new_lock_are_not_losses() -> None:
    meter = LinkMeter(LinkChoice("robust", 16), 60.0, 0.0)
    for i in range(12):  # it locks 0.3 s after the change, then reads every data frame
        meter.add(FrameSample(0.3 + i / 30, True))
    window = meter.window(0.3 + 12 / 30)
    assert window.pass_share == pytest.approx(1.0, abs=0.1)
    assert window.span_s == pytest.approx(0.7)
    # The latest 0.3 s just after the lock count from it too.
    meter = LinkMeter(LinkChoice("robust", 16), 60.0, 0.0)
    for i in range(3):
        meter.add(FrameSample(0.25 + i / 30, True))
    recent = meter.window(0.35, 0.3)
    assert recent.pass_share == pytest.approx(1.0, abs=0.3)
    # The first frames of a new lock failing do not decide alone: losses need min_frames.
    policy, meter = camera_policy(), LinkMeter(LinkChoice("robust", 48), 60.0, 0.0)
    for i in range(4):
        meter.add(FrameSample(0.2 + i / 30, False, px_per_cell=8.0))
    decision = policy.decide(meter.choice, meter.window(0.35), meter.window(0.35, 0.3), 0.35)
    assert not decision.changed
    for i in range(4, 10):
        meter.add(FrameSample(0.2 + i / 30, False, px_per_cell=8.0))
    decision = policy.decide(meter.choice, meter.window(0.55), meter.window(0.55, 0.3), 0.55)
    assert decision.changed and "losses" in decision.reason


def test_losses_step_down_one_notch_at_once_and_the_failed_setting_is_held_off() -> None:
    policy = camera_policy()
    bad = LinkChoice("fast", 48)
    _, reasons, t = run(policy, bad, 1.0, passed=0.3, px_at_16=20.0)
    reason, choice = reasons[0]
    # The nearest lower setting that still fits: fast N = 40 carries more than robust N = 48.
    assert choice == LinkChoice("fast", 40)
    assert reason.startswith("down from fast N = 48: losses")
    assert policy.is_held_off(bad, t)  # not tried again at once


@pytest.mark.parametrize(
    ("kwargs", "why"),
    [
        ({"ber": 0.02, "passed": 0.7}, "BER"),
        ({"margin": 0.8}, "receiver behind"),
        ({"read": False}, "no frame read"),
        ({"passed": 0.3}, "losses"),
    ],
)
def test_each_limit_steps_down_one_notch(kwargs: dict, why: str) -> None:
    policy = camera_policy()
    _, reasons, _ = run(policy, LinkChoice("robust", 48), 0.4, px_at_16=20.0, **kwargs)
    assert why in reasons[0][0]
    assert reasons[0][1] == LinkChoice("robust", 40)


def test_a_failure_that_persists_walks_down_to_the_start_and_no_further() -> None:
    policy = camera_policy()
    end, reasons, _ = run(policy, LinkChoice("robust", 32), 3.0, px_at_16=20.0, passed=0.2)
    assert end == start_choice(60.0)
    assert [c.cells for _, c in reasons] == [24, 20, 16]


def test_high_ber_while_every_frame_passes_holds_and_does_not_step_down() -> None:
    policy = camera_policy()
    end, reasons, _ = run(policy, LinkChoice("robust", 32), 2.0, px_at_16=20.0, ber=0.02)
    assert end == LinkChoice("robust", 32) and not reasons
    window = LinkMeter(end, 60.0, 0.0)
    for i in range(60):
        window.add(FrameSample(i / 30, True, 0.02, 8.0, 0.3, 0.1, 2.0))
    decision = policy.decide(end, window.window(2.0), window.window(2.0, 0.3), 2.0)
    assert not decision.changed and "BER" in decision.reason


def test_a_burst_costs_one_notch_and_the_setting_comes_back_after_its_hold_off() -> None:
    """A setting that works but meets a burst of errors that fail frames: one notch down,
    held off, then back."""
    policy = camera_policy()
    c = policy.config
    good = LinkChoice("robust", 48)

    def burst(t: float) -> bool:
        return 1.0 <= t < 1.3

    def ber(t: float) -> float:
        return 0.025 if burst(t) else 0.001

    def passed(t: float) -> float:
        return 0.6 if burst(t) else 1.0

    # 6.5 px per cell at N = 48, the densest its pixels allow (5.4 at N = 56, too few to
    # probe); a hand-held camera.
    end, reasons, _ = run(policy, good, 4.0, px_at_16=18.5, ber=ber, passed=passed, flow=1.0)
    assert [c for _, c in reasons] == [LinkChoice("robust", 40), good]
    assert "BER" in reasons[0][0] and reasons[1][0].startswith("up")
    assert end == good and policy.held_off[good].span_s == c.holdoff_s


def test_held_off_settings_wait_and_repeated_quick_failures_wait_longer() -> None:
    policy = camera_policy()
    c = policy.config
    s = LinkChoice("robust", 32)
    down = policy._step_down(s, window(0.1), 10.0, "losses")
    assert down.choice == LinkChoice("robust", 24)
    assert policy.held_off[s].span_s == c.holdoff_s
    # While held off, a clean window at N = 24 does not go back to N = 32.
    held = policy.decide(down.choice, window(1.0), window(0.3), 10.0 + c.holdoff_s / 2)
    assert not held.changed and "held off" in held.reason
    back = policy.decide(down.choice, window(1.0), window(0.3), 10.0 + c.holdoff_s + 0.01)
    assert back.changed and back.choice == s
    # Failing again sooner after its return than it was held off doubles the hold-off...
    t = 10.0 + c.holdoff_s + 0.5
    policy._step_down(s, window(0.5), t, "losses")
    assert policy.held_off[s].span_s == 2 * c.holdoff_s
    assert policy.is_held_off(s, t + 1.5 * c.holdoff_s)
    # ...and failing after lasting longer than that starts it over.
    t += 10.0
    policy._step_down(s, window(3.0), t, "losses")
    assert policy.held_off[s].span_s == c.holdoff_s


def window(span_s: float, px_at_24: float = 8.5) -> LinkWindow:
    """A clean window of ``span_s`` at robust N = 24 (its pixels per cell fit N = 32)."""
    return LinkWindow(
        span_s=span_s,
        expected=30 * span_s,
        read=round(30 * span_s),
        passed=round(30 * span_s),
        ber=0.0,
        px_per_cell=px_at_24,
        readout_share=0.3,
        flow_px_per_ms=1.0,
        realtime_margin=2.0,
        silent_s=0.0,
    )


def test_a_camera_moving_away_is_followed_down_by_its_pixels() -> None:
    """At N = 64 a camera that drops to 8 px per cell at N = 16 (it moved away) goes down
    to an N its pixels fit, not just one notch."""
    end, reasons, _ = run(camera_policy(), LinkChoice("fast", 64), 0.5, px_at_16=8.0, passed=0.0)
    assert reasons[0][0].startswith("down from fast N = 64")
    assert px_at(8.0, 16, end.cells) >= 6.0
    assert end.cells < 48


def test_a_faster_display_offers_its_rate_unless_the_readout_is_full() -> None:
    end, _, _ = run(camera_policy(120.0), start_choice(120.0), 3.0, px_at_16=30.0)
    assert end.hold == 1
    end, _, _ = run(camera_policy(120.0), start_choice(120.0), 3.0, px_at_16=30.0, readout=0.95)
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


@pytest.mark.parametrize(
    ("px16", "flow", "top"),
    [
        (25.84, 0.0, LinkChoice("fast", 80)),
        (25.84, 1.0, LinkChoice("robust", 80)),
        (12.4, 0.0, LinkChoice("fast", 32)),
    ],
)
def test_the_evk4_defaults_climb_to_the_smallest_cells_it_reads(
    px16: float, flow: float, top: LinkChoice
) -> None:
    """The closed-loop benchmark's pixels per cell at N = 16, still (no motion reported) or
    hand-held at 1 px/ms, on a camera that reads each profile down to what it needs. At 0.6 m
    (25.8): ``fast`` N = 80 at 5.5 px still, not N = 96 at 4.6 (not even probed); hand-held,
    ``robust`` N = 80 at 5.5 px, not N = 96 at 4.6. At 1.25 m (12.4) still: ``fast`` N = 32
    at 6.5 px, after a probe of N = 40 at 4.96, just below the 5 this camera reads."""
    policy = LinkPolicy()
    assert policy.config.min_px == EVK4_MIN_PX
    end, reasons, _ = run(
        policy, start_choice(60.0), 4.0, px_at_16=px16, flow=flow, reads_down_to=EVK4_MIN_PX
    )
    assert reasons and all(r.startswith(("up", "probe")) for r, _ in reasons)
    assert end == top


def _probe_at_robust_80(policy: LinkPolicy) -> float:
    """Robust N = 72 read cleanly at 5.5 px per cell, a hand's swing at its fewest (5.1
    predicted at N = 80, under the 5.15 a step asks): the policy probes N = 80. Returns the
    time it did."""
    robust72, meter = LinkChoice("robust", 72), LinkMeter(LinkChoice("robust", 72), 60.0, 0.0)
    rate = 60.0 * get_profile("robust").data_share
    t = 0.0
    while t < 0.6:
        t += 1 / rate
        meter.add(FrameSample(t, True, 0.0, 5.52, 0.9, 0.4, None))
    probe = policy.decide(robust72, meter.window(t), meter.window(t, 0.3), t)
    assert probe.changed and probe.choice == LinkChoice("robust", 80), probe
    assert probe.reason.startswith("probe from robust N = 72")
    return t


@pytest.mark.parametrize(("after_lock", "kept"), [(1.0, True), (0.9, True), (0.7, False)])
def test_a_probe_is_judged_from_its_lock_and_kept_if_it_carries_more(
    after_lock: float, kept: bool
) -> None:
    """The probe's first two frames fail (a new lock's first frames fail at any density);
    from its first passed frame on it is kept if its share passing, times the 24% more each of
    its frames carries, beats the 100% its origin passed."""
    policy = LinkPolicy()
    t0 = _probe_at_robust_80(policy)
    robust80 = LinkChoice("robust", 80)
    meter = LinkMeter(robust80, 60.0, t0)
    rate = 60.0 * get_profile("robust").data_share
    t, frames, decisions = t0 + 0.1, 0, []
    while t < t0 + 1.5:
        t += 1 / rate
        frames += 1
        ok = frames > 2 and math.floor((frames - 2) * after_lock) > math.floor(
            (frames - 3) * after_lock
        )
        meter.add(FrameSample(t, ok, 0.002 if ok else None, 5.3, 0.9, 0.4, None))
        decision = policy.decide(robust80, meter.window(t), meter.window(t, 0.3), t)
        decisions.append(decision)
        if decision.changed:
            break
    if kept:
        assert not any(d.changed for d in decisions)
        assert policy.probe is None and not decisions[-1].reason.startswith("probing")
    else:
        assert decisions[-1].changed and decisions[-1].choice == LinkChoice("robust", 72)
        assert "failed" in decisions[-1].reason and robust80 in policy.failed_probes
        assert t - t0 < 0.8  # at once: within a judgement's frames after the lock
