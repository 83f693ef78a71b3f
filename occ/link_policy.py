"""The closed loop's controller: which density, profile and frame rate the transmitter sends,
from what a receiver measures of the link it reads now.

Pure: no clock, no I/O. A ``LinkMeter`` sums one receiver's frame reports at the settings on
screen into a ``LinkWindow``; ``LinkPolicy.decide`` turns that into the settings to send next
and the margin that limited them.

How it chooses, and why:

- It starts where any camera reads (``START``: N = 16, ``robust``, about 60 frames a second).
- Upward it moves by the measured margin. Pixels per cell scale with one over the marker's
  side in cells (the page fits the marker to the screen whatever N is), so the receiver's
  pixels per cell at the present N predict them at any other; the target is the fastest
  setting whose predicted pixels per cell keep ``up_margin`` above what its profile needs
  (``min_px``; the defaults are the EVK4's in ``bench.realistic``: ``robust`` still passes
  every frame at 6 px per cell, ``fast`` from 7), and at most twice the cells per step. It
  moves only on a clean window: nearly every frame passing, BER before FEC low, the sensor's
  readout and the receiver's real-time margin not near their limits, the camera not swinging.
- Downward it moves at once: frames lost, BER rising, the lock gone, the readout full or the
  receiver falling behind. It goes back to the last settings that worked (or, if the camera's
  pixels per cell say those no longer fit, to the largest N that does), and keeps the failed
  settings off the table for a while, twice as long each time they fail again, so it does not
  oscillate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cache

from eventocc.occ.frame_codec import FrameCodec
from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.packing import SYMBOL_SIZE, symbols_per_frame
from eventocc.occ.profiles import get_profile

CELLS_LADDER = (16, 20, 24, 32, 40, 48, 56, 64, 72, 80, 96, 112, 128)
"""The densities the controller chooses from (a few cells' steps, so each step changes the
pixels per cell by 10-25%)."""
AUTO_PROFILES = ("robust", "fast")
"""``paper`` has no fountain code to carry a message across a change: never chosen."""
HOLDS = (1, 2, 3, 4)
"""Display refreshes each frame is held for: the frame rates a display offers are its own
refresh rate divided by these."""
NOMINAL_HZ = 60.0


@dataclass(frozen=True)
class LinkChoice:
    """What the transmitter sends: profile, cells, and each frame held for ``hold`` display
    refreshes (a 240 Hz display sends at 240, 120, 80 or 60 frames a second)."""

    profile: str = "robust"
    cells: int = 16
    hold: int = 1

    def __post_init__(self) -> None:
        if self.profile not in AUTO_PROFILES:
            raise ValueError(f"auto mode sends {' or '.join(AUTO_PROFILES)}, not {self.profile!r}")
        if self.cells not in CELLS_LADDER:
            raise ValueError(f"auto mode's cells are one of {CELLS_LADDER}, not {self.cells!r}")
        if self.hold not in HOLDS:
            raise ValueError(f"hold must be one of {HOLDS}, not {self.hold!r}")

    def frame_hz(self, display_hz: float) -> float:
        return display_hz / self.hold

    def payload_bps(self, display_hz: float) -> float:
        """Fountain-symbol bits per second the settings carry (packed frames), what the
        controller ranks settings by: the header, CRC and parity take a larger share of a
        small frame, so cells alone misrank them (``fast`` N = 24 sends more cells than
        ``robust`` N = 32, and fewer symbols)."""
        share = get_profile(self.profile).data_share
        return 8 * _packed_bytes(self.profile, self.cells) * share * self.frame_hz(display_hz)

    def __str__(self) -> str:
        return f"{self.profile} N = {self.cells}" + (f" held {self.hold}x" if self.hold > 1 else "")


@cache
def _packed_bytes(profile: str, cells: int) -> int:
    return SYMBOL_SIZE * symbols_per_frame(FrameCodec(get_profile(profile), cells).symbol_size)


def start_choice(display_hz: float) -> LinkChoice:
    """N = 16 ``robust`` at the frame rate nearest 60 Hz from below (the display's own if it
    is slower): what any camera that reads us at all reads."""
    hold = next((h for h in HOLDS if display_hz / h <= NOMINAL_HZ * 1.05), HOLDS[-1])
    return LinkChoice("robust", 16, hold)


def px_at(px_per_cell: float, cells_now: int, cells: int) -> float:
    """Pixels per cell at ``cells``, from those measured at ``cells_now``: the marker keeps its
    size on screen, so a cell's side goes with one over the marker's side in cells."""
    return px_per_cell * MarkerGeometry(cells_now).side / MarkerGeometry(cells).side


@dataclass(frozen=True)
class FrameSample:
    """One frame's report, as the policy needs it (``eventocc.occ.report.FrameStats``)."""

    t_s: float
    passed: bool
    """Its Reed-Solomon code and CRC passed."""
    ber: float | None = None
    """Share of its coded bits the code corrected (passed frames: BER before FEC)."""
    px_per_cell: float | None = None
    readout_share: float | None = None
    """Events per second over what the camera's readout carries."""
    flow_px_per_ms: float | None = None
    realtime_margin: float | None = None
    """Event time the receiver processes per second of its own time (below 1: behind)."""


@dataclass(frozen=True)
class LinkWindow:
    """One receiver's reports over the time since the settings on screen last changed."""

    span_s: float
    """Time the window covers (since the change, or its first report)."""
    expected: float
    """Data frames the screen sent meanwhile."""
    read: int
    passed: int
    ber: float | None
    """Mean BER before FEC over the passed frames."""
    px_per_cell: float | None
    readout_share: float | None
    flow_px_per_ms: float | None
    realtime_margin: float | None
    silent_s: float
    """Time since the receiver last read a frame (the whole span if it read none)."""

    @property
    def pass_share(self) -> float:
        return self.passed / self.expected if self.expected > 0 else 0.0


class LinkMeter:
    """Frame samples of the settings on screen since they last changed: ``window`` sums them."""

    def __init__(self, choice: LinkChoice, display_hz: float, since_s: float) -> None:
        self.choice, self.display_hz, self.since_s = choice, display_hz, since_s
        self.samples: list[FrameSample] = []

    def add(self, sample: FrameSample) -> None:
        if sample.t_s >= self.since_s:
            self.samples.append(sample)

    def window(self, now_s: float, last_s: float | None = None) -> LinkWindow:
        """The samples of the last ``last_s`` seconds (None: all since the change)."""
        start = self.since_s if last_s is None else max(self.since_s, now_s - last_s)
        got = [s for s in self.samples if s.t_s >= start]
        passed = [s for s in got if s.passed]
        span = max(now_s - start, 0.0)
        rate = self.choice.frame_hz(self.display_hz) * get_profile(self.choice.profile).data_share
        bers = [s.ber for s in passed if s.ber is not None]
        # A receiver rebuilt for new settings locks again first: the frames sent before its
        # first read are not losses (until it reads one, the whole span is its silence).
        counted = span
        if got and last_s is None:
            counted = max(0.0, min(span, now_s - got[0].t_s + 1 / rate))
        return LinkWindow(
            span_s=span,
            expected=counted * rate,
            read=len(got),
            passed=len(passed),
            ber=sum(bers) / len(bers) if bers else None,
            px_per_cell=_latest(got, "px_per_cell"),
            readout_share=_peak(got, "readout_share"),
            flow_px_per_ms=_peak(got, "flow_px_per_ms"),
            realtime_margin=_latest(got, "realtime_margin"),
            silent_s=now_s - got[-1].t_s if got else span,
        )


def _latest(samples: list[FrameSample], name: str) -> float | None:
    values = [v for s in samples if (v := getattr(s, name)) is not None]
    return values[-1] if values else None


def _peak(samples: list[FrameSample], name: str) -> float | None:
    values = [v for s in samples if (v := getattr(s, name)) is not None]
    return max(values) if values else None


@dataclass(frozen=True)
class PolicyConfig:
    min_px: dict[str, float] = field(default_factory=lambda: {"robust": 6.0, "fast": 7.0})
    """Pixels per cell each profile needs (the EVK4's, ``bench.realistic``)."""
    up_margin: float = 1.03
    """Predicted pixels per cell kept this far above ``min_px`` when stepping up (little:
    a step that fails costs one step back and a backoff, a margin held for ever costs
    goodput)."""
    settle_s: float = 0.25
    """After a change, time before any loss counts: the receiver rebuilds and locks again."""
    judge_s: float = 0.4
    """Clean time a setting must show before the next step up."""
    min_frames: int = 8
    """Frames a step-up judgement needs at least."""
    loss_window_s: float = 0.3
    """Losses are judged over this much of the latest time."""
    pass_up: float = 0.85
    """Share of the data frames sent that must pass to step up..."""
    pass_down: float = 0.5
    """...and below which the link steps down at once."""
    ber_up: float = 0.004
    """BER before FEC above which a step up must keep ``ber_px_margin`` over ``min_px``: near
    the pixels a profile needs, errors grow as cells shrink; well above them (large cells
    under a moving camera: 1.1-1.4% at 25 px per cell, hand-held at 0.6 m) they come from
    elsewhere, and a denser marker does not add many."""
    ber_px_margin: float = 1.3
    ber_down: float = 0.015
    """BER before FEC above which it steps down: the inner code corrects about 1% of bits
    (``LinkProfile.parity_fraction``), so this is losses about to come."""
    lost_s: float = 0.35
    """No frame read for this long after settling: the receiver lost the marker."""
    readout_up: float = 0.9
    """Event rate over the camera's readout above which the frame rate does not step up: a
    higher rate makes proportionally more events, where a denser marker of the same size
    makes about as many. (A full readout alone is no reason to step down: the EVK4 drops half
    the events of a marker filling its view and still reads 7 px cells, ``bench.realistic``;
    the losses and BER it causes are.)"""
    margin_up: float = 1.15
    margin_down: float = 1.0
    """Receiver's real-time margin: below 1 it falls behind the camera."""
    max_flow_up: float = 3.0
    """px/ms above which it does not step up: past 2 px/ms the receiver's locks go wrong now
    and then (README, known gaps), and a hand held at 1 px/ms on average swings past 1.5 at
    times, which must not stop it."""
    fast_max_flow: float = 0.5
    """px/ms above which ``fast`` is not chosen: it reads each bit from one transition, which
    motion smears (``bench.closed_loop``, hand-held at 1 px/ms and 0.6 m: ``fast`` passed a
    fraction of the frames ``robust`` passed at the same N)."""
    max_cells_factor: float = 3.0
    """A step up at most multiplies the cells by this."""
    backoff_s: float = 5.0
    """Settings that failed are not tried again for this long, doubled at each failure."""
    allow_fast: bool = True


@dataclass(frozen=True)
class Decision:
    choice: LinkChoice
    reason: str
    """Why these settings: what moved it, or the margin that keeps it where it is."""
    changed: bool


@dataclass
class LinkPolicy:
    """One receiver's controller. ``decide`` is called with the window of the settings on screen
    (``current``) whenever new reports came; it remembers the settings that worked (to fall
    back to) and those that failed (kept off the table for a while)."""

    display_hz: float = NOMINAL_HZ
    config: PolicyConfig = field(default_factory=PolicyConfig)
    worked: list[LinkChoice] = field(default_factory=list)
    """Settings that passed a clean window, in the order stepped through."""
    banned: dict[LinkChoice, tuple[float, float]] = field(default_factory=dict)
    """Failed settings -> (until when, the next backoff)."""

    def decide(
        self, current: LinkChoice, window: LinkWindow, recent: LinkWindow, now_s: float
    ) -> Decision:
        """``window``: all of ``current``'s reports since it went on screen; ``recent``: the
        last ``config.loss_window_s`` of them."""
        trouble = self._trouble(window, recent, current)
        if trouble:
            return self._step_down(current, window, now_s, trouble)
        held = self._why_hold(window)
        if held:
            return Decision(current, held, False)
        if current not in self.worked:
            self.worked.append(current)
        return self._step_up(current, window, now_s)

    # --- down ---------------------------------------------------------------------------
    def _trouble(self, window: LinkWindow, recent: LinkWindow, current: LinkChoice) -> str:
        c = self.config
        if window.span_s < c.settle_s:
            return ""
        if window.realtime_margin is not None and window.realtime_margin < c.margin_down:
            return f"receiver behind (real-time margin {window.realtime_margin:.2f})"
        if window.silent_s >= c.lost_s:
            return f"no frame read for {window.silent_s:.2f} s"
        if (
            recent.read
            and recent.span_s >= c.loss_window_s * 0.99
            and recent.pass_share < c.pass_down
        ):
            return f"losses: {recent.pass_share:.0%} of frames passed"
        if recent.ber is not None and recent.ber > c.ber_down:
            return f"BER before FEC {recent.ber:.2%}"
        px = window.px_per_cell
        if px is not None and px < c.min_px[current.profile] * 0.85:
            return f"{px:.1f} px per cell, {current.profile} needs {c.min_px[current.profile]:g}"
        return ""

    def _step_down(
        self, current: LinkChoice, window: LinkWindow, now_s: float, trouble: str
    ) -> Decision:
        start = start_choice(self.display_hz)
        if current != start:
            _, backoff = self.banned.get(current, (0.0, self.config.backoff_s))
            self.banned[current] = (now_s + backoff, backoff * 2)
        while self.worked and self.worked[-1] == current:
            self.worked.pop()
        target = self.worked.pop() if self.worked else start
        px = window.px_per_cell
        if px is not None and not self._fits(target, current, px, 1.0):
            target = self._largest_fit(current, px, "robust", target.hold) or start
        if target == current:
            return Decision(current, f"{trouble}; nothing lower to go to", False)
        return Decision(target, f"down from {current}: {trouble}", True)

    # --- up -----------------------------------------------------------------------------
    def _why_hold(self, window: LinkWindow) -> str:
        c = self.config
        if window.span_s < c.judge_s or window.expected < c.min_frames:
            return f"judging ({window.span_s:.2f} of {c.judge_s:g} s)"
        if window.pass_share < c.pass_up:
            return f"{window.pass_share:.0%} of frames passed (stepping up needs {c.pass_up:.0%})"
        if window.realtime_margin is not None and window.realtime_margin < c.margin_up:
            return f"receiver real-time margin {window.realtime_margin:.2f}"
        if window.flow_px_per_ms is not None and window.flow_px_per_ms > c.max_flow_up:
            return f"camera moving at {window.flow_px_per_ms:.1f} px/ms"
        if window.px_per_cell is None:
            return "no pixels-per-cell measurement yet"
        return ""

    def _step_up(self, current: LinkChoice, window: LinkWindow, now_s: float) -> Decision:
        px = window.px_per_cell
        assert px is not None
        margin = self.config.up_margin
        if window.ber is not None and window.ber > self.config.ber_up:
            margin = max(margin, self.config.ber_px_margin)
        options = []
        full = window.readout_share is not None and window.readout_share > self.config.readout_up
        moving = (window.flow_px_per_ms or 0.0) > self.config.fast_max_flow
        for profile in AUTO_PROFILES if self.config.allow_fast and not moving else ("robust",):
            for hold in HOLDS:
                if self.display_hz / hold < 1.0 or (full and hold < current.hold):
                    continue
                fit = self._largest_fit(current, px, profile, hold, margin, now_s)
                if fit is not None:
                    options.append(fit)
        best = max(options, key=lambda o: o.payload_bps(self.display_hz), default=None)
        if best is None or best.payload_bps(self.display_hz) <= current.payload_bps(
            self.display_hz
        ):
            if margin > self.config.up_margin:
                return Decision(
                    current,
                    f"BER before FEC {window.ber:.2%}: a step up needs its cells "
                    f"{margin:g}x the pixels its profile needs",
                    False,
                )
            need = self.config.min_px[current.profile]
            return Decision(current, self._top_reason(current, px, need), False)
        return Decision(best, f"up from {current}: {px:.1f} px per cell, clean window", True)

    def _top_reason(self, current: LinkChoice, px: float, need: float) -> str:
        up = [n for n in CELLS_LADDER if n > current.cells]
        if not up:
            return "at the densest marker"
        next_px = px_at(px, current.cells, up[0])
        return (
            f"px per cell: {px:.1f} now, {next_px:.1f} at N = {up[0]}; "
            f"{current.profile} needs {need * self.config.up_margin:.1f}"
        )

    def _fits(self, choice: LinkChoice, current: LinkChoice, px: float, margin: float) -> bool:
        return px_at(px, current.cells, choice.cells) >= self.config.min_px[choice.profile] * margin

    def _largest_fit(
        self,
        current: LinkChoice,
        px: float,
        profile: str,
        hold: int,
        margin: float = 1.0,
        now_s: float = -math.inf,
    ) -> LinkChoice | None:
        """The largest N whose predicted pixels per cell fit ``profile`` (at most
        ``max_cells_factor`` times the present N), not banned; None if none fits."""
        most = current.cells * self.config.max_cells_factor
        for cells in reversed(CELLS_LADDER):
            choice = replace(current, profile=profile, cells=cells, hold=hold)
            if cells > most or not self._fits(choice, current, px, margin):
                continue
            if self.banned.get(choice, (-math.inf, 0.0))[0] > now_s:
                continue
            return choice
        return None
