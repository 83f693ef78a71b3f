"""The transmitter's mode, held by the server: ``fixed`` (the page sends what its user set) or
``auto`` (the server chooses, from the receivers' frame reports, and the page follows).

In ``auto`` each connected receiver gets its own controller (``eventocc.occ.link_policy``), fed
its ``FrameStats`` on the server's clock. The settings served are those of the pinned receiver,
or else the weakest proposal among the receivers that verified a frame lately: a receiver that
reads nothing says nothing about what the link can carry, and must not hold the others down.
The page learns the choice in the answer to its status report (``POST
/api/transmitter/status``) and starts a new packed segment from the next unsent symbol.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

from eventocc.occ.link_policy import (
    FrameSample,
    LinkChoice,
    LinkMeter,
    LinkPolicy,
    LinkWindow,
    PolicyConfig,
    start_choice,
)
from eventocc.occ.report import FrameStats

MODES = ("fixed", "auto")
LIVE_POLICY = PolicyConfig(settle_s=2.0, judge_s=2.0, lost_s=1.5, loss_window_s=1.0, holdoff_s=5.0)
"""A live loop is slower than the simulated one: the page takes up a choice at its next status
report (4 a second in ``auto``), a receiver at its next look at the page's status, and then it
must lock again; the windows are longer so that this is not taken for losses, and a setting
that failed is held off for as many of them as in the simulated loop."""
VERIFIED_WITHIN_S = 10.0
"""A receiver counts as reading the link while a frame of it passed this recently."""
HISTORY = 120
"""Goodput points kept (one a second: two minutes)."""
DECIDE_EVERY_S = 0.1


@dataclass
class ReceiverLoop:
    policy: LinkPolicy
    meter: LinkMeter
    last_passed_s: float | None = None
    proposal: LinkChoice | None = None
    reason: str = "no report yet"
    source_speed: float | None = None
    """Share of real time the receiver's source delivers (its health report): a virtual
    camera simulating below real time skips frames that the link did not lose."""


@dataclass
class LinkMode:
    config: PolicyConfig = LIVE_POLICY
    mode: str = "fixed"
    pinned: str | None = None
    """Public id of the receiver the choice follows (None: the weakest verified one)."""
    display_hz: float = 60.0
    choice: LinkChoice = field(default_factory=lambda: start_choice(60.0))
    reason: str = "fixed mode: the page sends what its user set"
    served: str | None = None
    """The receiver whose proposal is served."""
    changed_s: float = 0.0
    loops: dict[str, ReceiverLoop] = field(default_factory=dict)
    history: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=HISTORY))
    """One point a second: goodput of the served receiver and the settings on screen."""
    _bits: int = 0
    _bucket_s: float | None = None
    _next_decision_s: float = 0.0

    def set_mode(self, mode: str, pinned: str | None, now_s: float) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode, self.pinned = mode, pinned
        self.loops.clear()
        if mode == "auto":
            self.choose(
                start_choice(self.display_hz), "auto mode: start where any camera reads", now_s
            )
        else:
            self.reason = "fixed mode: the page sends what its user set"

    def set_display_hz(self, frame_hz: float, hold: int) -> None:
        """The page's display rate, from its measured frame rate and the frames' hold."""
        self.display_hz = frame_hz * hold

    def on_health(self, receiver: str, source_speed: float | None) -> None:
        if (loop := self.loops.get(receiver)) is not None:
            loop.source_speed = source_speed

    def forget(self, receiver: str) -> None:
        self.loops.pop(receiver, None)

    def on_frame(self, receiver: str, report: FrameStats, now_s: float) -> bool:
        """Take one frame report; True if the served settings changed."""
        if self.mode != "auto":
            return False
        loop = self.loops.get(receiver)
        if loop is None:
            policy = LinkPolicy(self.display_hz, self.config)
            loop = self.loops[receiver] = ReceiverLoop(policy, self._meter(now_s))
        if (report.profile, report.cells) != (self.choice.profile, self.choice.cells):
            return False  # read as other settings: the screen's last, not these
        if report.passed:
            loop.last_passed_s = now_s
            if receiver == self.served or self.served is None:
                self._count(report.payload_bits, now_s)
        loop.meter.add(
            FrameSample(
                now_s,
                bool(report.passed),
                report.ber_before_fec,
                report.px_per_cell,
                report.readout_share,
                report.flow_px_per_ms,
                report.realtime_margin,
            )
        )
        if now_s < self._next_decision_s:
            return False
        self._next_decision_s = now_s + DECIDE_EVERY_S
        return self.decide(now_s)

    def decide(self, now_s: float) -> bool:
        """Every receiver's controller proposes; serve the pinned or weakest verified one."""
        for loop in self.loops.values():
            window = self._seen(loop, loop.meter.window(now_s))
            recent = self._seen(loop, loop.meter.window(now_s, self.config.loss_window_s))
            decision = loop.policy.decide(self.choice, window, recent, now_s)
            loop.proposal, loop.reason = decision.choice, decision.reason
        candidates = {
            r: loop
            for r, loop in self.loops.items()
            if loop.proposal is not None
            and (
                r == self.pinned
                or (
                    self.pinned is None
                    and loop.last_passed_s is not None
                    and now_s - loop.last_passed_s <= VERIFIED_WITHIN_S
                )
            )
        }
        if not candidates:
            return False
        served, loop = min(
            candidates.items(), key=lambda kv: kv[1].proposal.payload_bps(self.display_hz)
        )
        self.served = served
        if loop.proposal == self.choice:
            self.reason = loop.reason
            return False
        self.choose(loop.proposal, loop.reason, now_s)
        return True

    @staticmethod
    def _seen(loop: ReceiverLoop, window: LinkWindow) -> LinkWindow:
        """The frames the source showed the receiver, of those the screen sent: a source that
        skips ahead (a simulation below real time) hides frames the link did not lose. A
        receiver that itself falls behind shows in its real-time margin instead."""
        speed = loop.source_speed
        if speed is None or not 0 < speed < 1:
            return window
        return replace(window, expected=window.expected * speed)

    def choose(self, choice: LinkChoice, reason: str, now_s: float) -> None:
        """Serve ``choice``: every controller judges it afresh from now."""
        self.choice, self.reason, self.changed_s = choice, reason, now_s
        for loop in self.loops.values():
            loop.meter = self._meter(now_s)

    def _meter(self, now_s: float) -> LinkMeter:
        return LinkMeter(self.choice, self.display_hz, now_s)

    def _count(self, bits: int, now_s: float) -> None:
        if self._bucket_s is None:
            self._bucket_s = now_s
        while now_s - self._bucket_s >= 1.0:
            self.history.append(
                {"t": round(self._bucket_s, 3), "bps": self._bits, "settings": str(self.choice)}
            )
            self._bits, self._bucket_s = 0, self._bucket_s + 1.0
        self._bits += bits

    def public(self, now_s: float) -> dict[str, Any]:
        c = self.choice
        return {
            "mode": self.mode,
            "pinned": self.pinned,
            "served": self.served,
            "choice": (
                {
                    "profile": c.profile,
                    "cells": c.cells,
                    "hold": c.hold,
                    "frame_hz": round(c.frame_hz(self.display_hz), 3),
                }
                if self.mode == "auto"
                else None
            ),
            "reason": self.reason,
            "since_s": round(max(now_s - self.changed_s, 0.0), 3),
            "history": list(self.history),
        }
