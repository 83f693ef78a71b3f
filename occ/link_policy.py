"""The closed loop's controller: which density, profile and frame rate the transmitter sends,
from what a receiver measures of the link it reads now.

Pure: no clock, no I/O. A ``LinkMeter`` sums one receiver's frame reports at the settings on
screen into a ``LinkWindow``; ``LinkPolicy.decide`` turns that into the settings to send next
and the margin that limited them.

How it chooses, and why:

- It starts where any camera reads (``START``: N = 16, ``robust``, about 60 frames a second).
- Upward it moves by the measured margin. Pixels per cell scale with one over the marker's
  side in cells (the page fits the marker to the screen whatever N is), so the receiver's
  pixels per cell at the present N predict them at any other; the target is the setting that
  carries most among those whose predicted pixels per cell keep ``up_margin`` above what its
  profile needs (``min_px``; the defaults, ``EVK4_MIN_PX``, are the EVK4's), at most three
  times the cells per step (``fast`` only while the marker moves less than ``fast_max_shift``
  of a cell in one frame), predicted from the fewest pixels per cell the window saw. It moves
  only on a clean window: nearly every frame passing (most of them while the cells are far
  above what their profile needs: frames lost there are not lost to the cells' size, and a
  denser marker loses about as many), the sensor's readout and the receiver's real-time margin
  not near their limits, the camera not swinging, and no BER before FEC that looks like the
  cells' own: above ``ber_up`` while the cells are less than ``far_margin`` above what their
  profile needs, where errors grow as cells shrink. (Errors at cells far above it come from
  motion or a full readout, which a denser marker does not worsen much: they do not stop it.)
- Downward it moves at once: frames lost, frames failing with BER near what the code
  corrects (while every frame passes, such a BER only holds it), the lock gone, the cells
  too small for the profile or the receiver falling behind. It steps one notch: to the
  nearest lower setting (in what it carries; no more cells, the same profile or ``robust``)
  whose predicted pixels per cell still fit, so a burst costs one notch, not the climb. The
  setting that failed is held off for ``holdoff_s``, doubled each time it fails again sooner
  after its return than it was held off, so the link neither retries a setting beyond the
  camera at once nor stays below one that fails only now and then.
- Near the limit it probes. Pixels per cell are measured, not known: a hand-held camera's
  window holds its swing's fewest, and what a profile needs is known to a few percent. When
  no setting that carries more fits with ``up_margin``, the one predicted surest among those
  at least ``probe_margin`` of what they need is tried. It is kept once a judgement's time of
  it carries more than where it came from (its share of frames passing, counted from its
  lock's first passed frame, times what each carries), and left for where it came from as
  soon as it does not, or on any trouble that steps down. A failed probe is remembered with
  the pixels per cell predicted for it (``FailedProbe``): it is not tried again for
  ``probe_memory_s`` unless the camera came closer, so the link does not oscillate across
  the limit.
"""

from __future__ import annotations

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
EVK4_MIN_PX = {"robust": 5.0, "fast": 5.0}
"""Pixels per cell each profile needs on the EVK4 (the simulator's ``evk4`` preset), a tenth
or so above the smallest cells it reads. ``robust`` reads nearly every frame at 5.5 in
``bench.closed_loop``, still and hand-held, and at 5 in ``bench.realistic`` every frame at
60 Hz but none at 240 Hz. ``fast`` (still: ``fast_max_shift`` keeps it off a moving camera)
reads most frames at 5 px per cell in ``bench.realistic`` at 60 and 240 Hz and none at 4; the
closed loop's fixed ``fast`` settings deliver at 4.6-6 px per cell and nothing at 4.4."""


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
    return SYMBOL_SIZE * symbols_per_frame(FrameCodec(get_profile(profile), cells).room)


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
    """The latest report's (where the camera is now)."""
    readout_share: float | None
    flow_px_per_ms: float | None
    realtime_margin: float | None
    silent_s: float
    """Time since the receiver last read a frame (the whole span if it read none)."""
    px_per_cell_low: float | None = None
    """The fewest pixels per cell any report of the window gave (a hand-held camera's swing
    nearest to the limit); None: as ``px_per_cell``."""
    expected_locked: float = 0.0
    """Data frames sent since the first frame that passed (0: none passed)."""

    @property
    def pass_share(self) -> float:
        return self.passed / self.expected if self.expected > 0 else 0.0

    @property
    def locked_share(self) -> float:
        """Share of the data frames sent since the first that passed that passed: a new
        lock's first frames fail at any density."""
        return self.passed / self.expected_locked if self.expected_locked > 0 else 0.0


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
        # first read since the change are not losses (until it reads one, the whole span is
        # its silence).
        counted = span
        if self.samples:
            counted = max(0.0, min(span, now_s - self.samples[0].t_s + 1 / rate))
        pxs = [s.px_per_cell for s in got if s.px_per_cell is not None]
        locked = 0.0
        if passed:
            locked = max(0.0, min(span, now_s - passed[0].t_s + 1 / rate))
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
            px_per_cell_low=min(pxs) if pxs else None,
            expected_locked=locked * rate,
        )


def _low(window: LinkWindow) -> float | None:
    return window.px_per_cell_low if window.px_per_cell_low is not None else window.px_per_cell


def _latest(samples: list[FrameSample], name: str) -> float | None:
    values = [v for s in samples if (v := getattr(s, name)) is not None]
    return values[-1] if values else None


def _peak(samples: list[FrameSample], name: str) -> float | None:
    values = [v for s in samples if (v := getattr(s, name)) is not None]
    return max(values) if values else None


@dataclass(frozen=True)
class PolicyConfig:
    min_px: dict[str, float] = field(default_factory=lambda: dict(EVK4_MIN_PX))
    """Pixels per cell each profile needs."""
    up_margin: float = 1.03
    """Predicted pixels per cell kept this far above ``min_px`` when stepping up (little:
    a step that fails costs one notch back and a hold-off, a margin held for ever costs
    goodput)."""
    far_margin: float = 1.25
    """Pixels per cell this far above ``min_px`` are far from the limit: errors seen there come
    from elsewhere than the cells' size (``_near_limit``)."""
    settle_s: float = 0.25
    """After a change, time before any loss counts: the receiver rebuilds and locks again."""
    judge_s: float = 0.4
    """Clean time a setting must show before the next step up."""
    min_frames: int = 8
    """Frames a judgement needs at least: a step up's since the change, a loss's since the
    first read after it (the first frames of a new lock must not decide alone)."""
    loss_window_s: float = 0.3
    """Losses are judged over this much of the latest time."""
    pass_up: float = 0.85
    """Share of the data frames sent that must pass to step up..."""
    pass_down: float = 0.5
    """...and below which the link steps down at once."""
    pass_up_far: float = 0.6
    """Share that must pass to step up while the cells are ``far_margin`` above what their
    profile needs: the frames lost there are not lost to the cells' size (a full readout, a
    moving camera), so a denser marker of the same size loses about as many and carries more
    in each."""
    ber_up: float = 0.004
    """BER before FEC above which, with the cells less than ``far_margin`` above what their
    profile needs, it does not step to more cells."""
    ber_down: float = 0.015
    """BER before FEC near what the code corrects: the inner code corrects about 1% of
    independent bit errors (``LinkProfile.parity_fraction``), more with erasures. Above it the
    link does not step up, and steps down if frames also fail (fewer than ``pass_up`` of
    them pass): their errors are then why."""
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
    fast_max_shift: float = 0.25
    """Cells the marker may move in one of its frames for ``fast`` to be chosen (the window's
    fastest image speed over one frame's time, in the setting's predicted pixels per cell):
    ``fast`` reads each bit from one transition, which motion smears (``bench.closed_loop``:
    a still camera reports no motion; a hand at 1 px/ms on average, 0.5-1.9 px/ms measured,
    moves a 60 Hz marker a cell or more per frame, and ``fast`` passed a fraction of the
    frames ``robust`` passed at the same N)."""
    max_cells_factor: float = 3.0
    """A step up at most multiplies the cells by this."""
    holdoff_s: float = 1.0
    """A setting that failed is not chosen again for this long. Each time it fails again
    sooner after going back on screen than it was held off, its hold-off doubles (it fails
    more often than it works); when it lasts longer than that, the hold-off starts over (a
    burst, in a setting that works)."""
    max_holdoff_s: float = 60.0
    allow_fast: bool = True
    probe_margin: float = 0.95
    """A setting predicted at least this share of ``min_px`` (but below ``up_margin``) is
    probed: the measured pixels per cell (a swing's fewest) and the profiles' needs are known
    to about 5%."""
    probe_memory_s: float = 30.0
    """A failed probe is not tried again for this long..."""
    probe_retry_gain: float = 1.05
    """...unless the pixels per cell predicted for it grew by this factor (the camera came
    closer)."""


@dataclass(frozen=True)
class Decision:
    choice: LinkChoice
    reason: str
    """Why these settings: what moved it, or the margin that keeps it where it is."""
    changed: bool


@dataclass(frozen=True)
class HoldOff:
    """A setting that failed: not chosen before ``until_s``; ``span_s``: its last hold-off."""

    until_s: float
    span_s: float


@dataclass(frozen=True)
class Probe:
    """A setting on trial (``choice``), tried from ``origin`` at ``px`` predicted pixels per
    cell; kept while at least ``need`` of its frames pass."""

    choice: LinkChoice
    origin: LinkChoice
    px: float
    need: float


@dataclass(frozen=True)
class FailedProbe:
    """A probe that failed at ``px`` predicted pixels per cell: not tried again before
    ``until_s`` unless predicted ``probe_retry_gain`` higher."""

    px: float
    until_s: float


@dataclass
class LinkPolicy:
    """One receiver's controller. ``decide`` is called with the window of the settings on screen
    (``current``) whenever new reports came; it remembers the settings that failed and holds
    them off for a while."""

    display_hz: float = NOMINAL_HZ
    config: PolicyConfig = field(default_factory=PolicyConfig)
    held_off: dict[LinkChoice, HoldOff] = field(default_factory=dict)
    """Settings that failed, and until when they are not chosen."""
    probe: Probe | None = None
    """The setting on trial, if the one on screen is."""
    failed_probes: dict[LinkChoice, FailedProbe] = field(default_factory=dict)

    def decide(
        self, current: LinkChoice, window: LinkWindow, recent: LinkWindow, now_s: float
    ) -> Decision:
        """``window``: all of ``current``'s reports since it went on screen; ``recent``: the
        last ``config.loss_window_s`` of them."""
        if self.probe is not None and self.probe.choice != current:
            self.probe = None  # another receiver's choice is served: the trial is over
        trouble = self._trouble(window, recent, current)
        if self.probe is not None:
            trouble = trouble or self._probe_trouble(window)
            if trouble:
                return self._probe_failed(current, window, now_s, trouble)
            c = self.config
            if window.span_s < c.settle_s + c.judge_s or window.expected_locked < c.min_frames:
                return Decision(current, f"probing {current} (from {self.probe.origin})", False)
            self.probe = None
        if trouble:
            return self._step_down(current, window, now_s, trouble)
        held = self._why_hold(current, window, recent)
        if held:
            return Decision(current, held, False)
        return self._step_up(current, window, now_s)

    def is_held_off(self, choice: LinkChoice, now_s: float) -> bool:
        held = self.held_off.get(choice)
        return held is not None and held.until_s > now_s

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
            and recent.expected >= c.min_frames
            and recent.pass_share < c.pass_down
        ):
            return f"losses: {recent.pass_share:.0%} of frames passed"
        # High BER while every frame still passes costs nothing yet (it holds the step up);
        # with frames starting to fail, it says they fail for their errors.
        if (
            recent.ber is not None
            and recent.ber > c.ber_down
            and recent.span_s >= c.loss_window_s * 0.99
            and recent.expected >= c.min_frames
            and recent.pass_share < c.pass_up
        ):
            return f"BER before FEC {recent.ber:.2%}, {recent.pass_share:.0%} of frames passed"
        px = window.px_per_cell
        if px is not None and px < c.min_px[current.profile] * 0.85:
            return f"{px:.1f} px per cell, {current.profile} needs {c.min_px[current.profile]:g}"
        return ""

    def _hold_off(self, current: LinkChoice, on_screen_s: float, now_s: float) -> float:
        """Hold ``current`` off after it failed ``on_screen_s`` after going on screen."""
        c = self.config
        last = self.held_off.get(current)
        span = c.holdoff_s
        if last is not None and on_screen_s < last.span_s:
            span = min(last.span_s * 2, c.max_holdoff_s)
        self.held_off[current] = HoldOff(now_s + span, span)
        return span

    def _step_down(
        self, current: LinkChoice, window: LinkWindow, now_s: float, trouble: str
    ) -> Decision:
        """To the nearest lower setting (in what it carries; no more cells, the same profile
        or ``robust``, the same frame rate) that is not held off and whose predicted pixels per
        cell still fit its profile; the start if none does."""
        start = start_choice(self.display_hz)
        if current == start:
            return Decision(current, f"{trouble}; nothing lower to go to", False)
        span = self._hold_off(current, window.span_s, now_s)
        px = window.px_per_cell
        bps = current.payload_bps(self.display_hz)
        lower = [
            choice
            for profile in dict.fromkeys((current.profile, "robust"))
            for cells in CELLS_LADDER
            if cells <= current.cells
            and (choice := replace(current, profile=profile, cells=cells)).payload_bps(
                self.display_hz
            )
            < bps
            and not self.is_held_off(choice, now_s)
            and (px is None or self._fits(choice, current, px, 1.0))
        ]
        target = max(lower, key=lambda o: o.payload_bps(self.display_hz), default=start)
        return Decision(
            target, f"down from {current}: {trouble} (held off {span:g} s)", target != current
        )

    # --- probes -------------------------------------------------------------------------
    def _probe_trouble(self, window: LinkWindow) -> str:
        """A probe is kept only while it carries more than where it came from: from its
        lock's first passed frame on (a new lock's first frames fail at any density), at
        least ``need`` of its frames pass. (Frames read and none passing are losses.)"""
        assert self.probe is not None
        c = self.config
        if window.span_s < c.settle_s or window.expected_locked < c.min_frames:
            return ""
        if window.locked_share < self.probe.need:
            return (
                f"{window.locked_share:.0%} of frames passed since its lock (carrying more "
                f"than {self.probe.origin} needs {self.probe.need:.0%})"
            )
        return ""

    def _probe_failed(
        self, current: LinkChoice, window: LinkWindow, now_s: float, trouble: str
    ) -> Decision:
        """Back to where the probe came from, the probe remembered; one notch down as from
        any failure if the cells measured now no longer fit there (the camera moved away)."""
        assert self.probe is not None
        probe, self.probe = self.probe, None
        c = self.config
        self.failed_probes[current] = FailedProbe(probe.px, now_s + c.probe_memory_s)
        why = f"probe of {current} at {probe.px:.1f} px per cell failed: {trouble}"
        memory = f"not tried again for {c.probe_memory_s:g} s unless the cells grow"
        px = window.px_per_cell
        if px is not None and not self._fits(probe.origin, current, px, 1.0):
            down = self._step_down(current, window, now_s, trouble)
            return Decision(down.choice, f"{why}; down ({memory})", down.changed)
        self._hold_off(current, window.span_s, now_s)
        return Decision(probe.origin, f"{why}; back ({memory})", True)

    def _probe_blocked(self, choice: LinkChoice, px: float, now_s: float) -> bool:
        """A failed probe of ``choice`` is remembered and the pixels per cell predicted for
        it now are not ``probe_retry_gain`` above those it failed at."""
        failed = self.failed_probes.get(choice)
        return (
            failed is not None
            and failed.until_s > now_s
            and px < failed.px * self.config.probe_retry_gain
        )

    # --- up -----------------------------------------------------------------------------
    def _why_hold(self, current: LinkChoice, window: LinkWindow, recent: LinkWindow) -> str:
        c = self.config
        if window.span_s < c.judge_s or window.expected < c.min_frames:
            return f"judging ({window.span_s:.2f} of {c.judge_s:g} s)"
        px = _low(window)
        need = c.pass_up if px is None or self._close(current, px) else c.pass_up_far
        if window.pass_share < need:
            return f"{window.pass_share:.0%} of frames passed (stepping up needs {need:.0%})"
        if recent.ber is not None and recent.ber > c.ber_down:
            return f"BER before FEC {recent.ber:.2%}, near what the code corrects"
        if window.realtime_margin is not None and window.realtime_margin < c.margin_up:
            return f"receiver real-time margin {window.realtime_margin:.2f}"
        if window.flow_px_per_ms is not None and window.flow_px_per_ms > c.max_flow_up:
            return f"camera moving at {window.flow_px_per_ms:.1f} px/ms"
        if window.px_per_cell is None:
            return "no pixels-per-cell measurement yet"
        return ""

    def _step_up(self, current: LinkChoice, window: LinkWindow, now_s: float) -> Decision:
        """To the setting that carries most among those whose predicted pixels per cell keep
        ``up_margin`` over what their profile needs, not held off, at most
        ``max_cells_factor`` times the cells; none with more cells while the errors look like
        the cells' own (``_near_limit``). If none carries more than ``current``, a probe of the
        one that does predicted surest (most pixels per cell over what its profile needs)
        among those predicted at least ``probe_margin`` of it."""
        c = self.config
        px = _low(window)
        assert px is not None
        near = self._near_limit(current, window)
        bps = current.payload_bps(self.display_hz)
        options = self._options(current, window, now_s, c.up_margin, near)
        best = max(options, key=lambda o: o.payload_bps(self.display_hz), default=None)
        if best is not None and best.payload_bps(self.display_hz) > bps:
            return Decision(best, f"up from {current}: {px:.1f} px per cell, clean window", True)
        if near:
            need = c.min_px[current.profile]
            return Decision(
                current,
                f"BER before FEC {window.ber:.2%} at {px:.1f} px per cell, near the "
                f"{need:g} {current.profile} needs: smaller cells would add errors",
                False,
            )
        above = [
            o
            for o in self._options(current, window, now_s, c.probe_margin, near)
            if o.payload_bps(self.display_hz) > bps
        ]
        # The surest first: the most pixels per cell over what its profile needs.
        probe = max(
            above,
            key=lambda o: (self._ratio(o, current, px), -o.payload_bps(self.display_hz)),
            default=None,
        )
        if probe is None:
            return Decision(current, self._top_reason(current, px, now_s), False)
        predicted = px_at(px, current.cells, probe.cells)
        # It must carry more than the origin does now: its share of frames passing times what
        # each carries.
        share = min(window.pass_share, 1.0) * bps / probe.payload_bps(self.display_hz)
        self.probe = Probe(probe, current, predicted, max(share, c.pass_down))
        need = c.min_px[probe.profile]
        return Decision(
            probe,
            f"probe from {current}: {predicted:.1f} px per cell predicted, {probe.profile} "
            f"needs {need:g}",
            True,
        )

    def _options(
        self, current: LinkChoice, window: LinkWindow, now_s: float, margin: float, near: bool
    ) -> list[LinkChoice]:
        """The settings a step up may go to whose predicted pixels per cell keep ``margin``
        over what their profile needs."""
        c = self.config
        px = _low(window)
        assert px is not None
        full = window.readout_share is not None and window.readout_share > c.readout_up
        options = []
        for profile in AUTO_PROFILES if c.allow_fast else ("robust",):
            for hold in HOLDS:
                if self.display_hz / hold < 1.0 or (full and hold < current.hold):
                    continue
                for cells in CELLS_LADDER:
                    choice = replace(current, profile=profile, cells=cells, hold=hold)
                    if (
                        cells > current.cells * c.max_cells_factor
                        or (near and cells > current.cells)
                        or not self._fits(choice, current, px, margin)
                        or self.is_held_off(choice, now_s)
                        or self._probe_blocked(choice, px_at(px, current.cells, cells), now_s)
                        or (
                            profile == "fast"
                            and self._shift(choice, current, window) > c.fast_max_shift
                        )
                    ):
                        continue
                    options.append(choice)
        return options

    def _shift(self, choice: LinkChoice, current: LinkChoice, window: LinkWindow) -> float:
        """Cells the marker moves in one frame of ``choice`` at the window's fastest motion."""
        flow, px = window.flow_px_per_ms or 0.0, _low(window)
        assert px is not None
        frame_ms = 1e3 / choice.frame_hz(self.display_hz)
        return flow * frame_ms / px_at(px, current.cells, choice.cells)

    def _near_limit(self, current: LinkChoice, window: LinkWindow) -> bool:
        """BER before FEC above ``ber_up`` with the cells less than ``far_margin`` above what
        the profile needs: errors that grow as the cells shrink. (Errors with the cells far
        above it come from motion or a full readout, which a denser marker of the same size
        does not worsen much.)"""
        px = _low(window)
        return (
            window.ber is not None
            and window.ber > self.config.ber_up
            and px is not None
            and self._close(current, px)
        )

    def _close(self, current: LinkChoice, px: float) -> bool:
        """Whether ``px`` pixels per cell lie less than ``far_margin`` above what the profile
        of ``current`` needs."""
        return px < self.config.min_px[current.profile] * self.config.far_margin

    def _top_reason(self, current: LinkChoice, px: float, now_s: float) -> str:
        up = [n for n in CELLS_LADDER if n > current.cells]
        if not up:
            return "at the densest marker"
        nxt = replace(current, cells=up[0])
        if self.is_held_off(nxt, now_s):
            return f"{nxt} failed: held off for {self.held_off[nxt].until_s - now_s:.1f} s more"
        need = self.config.min_px[current.profile] * self.config.up_margin
        return (
            f"px per cell: {px:.1f} now, {px_at(px, current.cells, up[0]):.1f} at N = {up[0]}; "
            f"{current.profile} needs {need:.1f}"
        )

    def _ratio(self, choice: LinkChoice, current: LinkChoice, px: float) -> float:
        """Predicted pixels per cell of ``choice`` over what its profile needs."""
        return px_at(px, current.cells, choice.cells) / self.config.min_px[choice.profile]

    def _fits(self, choice: LinkChoice, current: LinkChoice, px: float, margin: float) -> bool:
        return px_at(px, current.cells, choice.cells) >= self.config.min_px[choice.profile] * margin
