"""The transmitting screen: refresh timing, progressive scan-out, pixel response, luminance.

A display shows refresh ``k`` by scanning it out top to bottom: the screen row at height fraction
``v`` (0 = top row, 1 = bottom row) switches at ``refresh_start(k) + v * scanout_fraction /
refresh_hz``. After the switch a pixel's emitted luminance approaches the new level exponentially,
with the rise time constant when it gets brighter and the fall time constant when it gets darker
(liquid crystals relax at different speeds in the two directions; OLED switches within
microseconds, ``0`` here). Between switches the luminance is therefore a known exponential per
cell, which the event generator solves in closed form.

The marker is drawn centred on the screen with a black margin around it; ambient light reflected
by the panel adds to every screen pixel.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from eventocc.occ.marker import MarkerGeometry

LUX_TO_NITS_PER_REFLECTANCE = 1.0 / math.pi
"""Luminance (cd/m²) of a Lambertian surface of reflectance 1 under 1 lux."""


@dataclass(frozen=True)
class Display:
    """A screen's temporal and photometric behaviour.

    Defaults model the paper's DELL U2417H office LCD at 60 Hz: 250 cd/m² peak and 1000:1
    contrast (Dell datasheet), a 6-8 ms grey-to-grey response (datasheet; 10-90 % over about
    2.2 time constants gives the rise/fall constants below), and 1080 active of 1125 total lines
    in the CEA-861 1080p60 timing (scan-out over 96 % of the period).
    """

    refresh_hz: float = 60.0
    scanout_fraction: float = 0.96
    """Share of the refresh period the top-to-bottom scan takes (the rest is vertical blanking)."""
    rise_ms: float = 2.5
    """Time constant of a pixel getting brighter."""
    fall_ms: float = 1.5
    """Time constant of a pixel getting darker."""
    black_nits: float = 0.25
    peak_nits: float = 250.0
    pwm_hz: float | None = None
    """Backlight PWM frequency (None: DC-dimmed backlight, the usual office monitor). The
    backlight (an OLED's emission) is on for the first ``pwm_duty`` of each PWM period, counted
    from t = 0; it gates the light the cells emit, not the ambient light the panel reflects (nor
    the black margin's faint glow). Simulated for a still camera only (a moving camera with PWM
    is refused)."""
    pwm_duty: float = 0.5
    """Share of each PWM period the backlight is on."""
    reflectance: float = 0.02
    """Diffuse reflectance of the panel: ambient light adds ``lux * reflectance / pi`` cd/m²
    to every screen pixel (matte anti-glare panels reflect a few per cent)."""
    margin: float = 0.05
    """Black screen around the marker on each side, as a fraction of the marker's outer side."""

    def __post_init__(self) -> None:
        if not 1.0 <= self.refresh_hz <= 1000.0:
            raise ValueError(f"refresh_hz must be 1..1000 Hz, got {self.refresh_hz}")
        if not 0.0 < self.scanout_fraction <= 1.0:
            raise ValueError(f"scanout_fraction must be in (0, 1], got {self.scanout_fraction}")
        if self.rise_ms < 0 or self.fall_ms < 0:
            raise ValueError(
                f"rise/fall time constants must be >= 0 ms, got {self.rise_ms}, {self.fall_ms}"
            )
        if not 0.0 < self.black_nits < self.peak_nits:
            raise ValueError(
                f"need 0 < black_nits < peak_nits, got {self.black_nits}, {self.peak_nits}"
            )
        if self.pwm_hz is not None and self.pwm_hz <= 0:
            raise ValueError(f"pwm_hz must be positive or None, got {self.pwm_hz}")
        if not 0.0 < self.pwm_duty <= 1.0:
            raise ValueError(f"pwm_duty must be in (0, 1], got {self.pwm_duty}")
        if not 0.0 <= self.reflectance < 1.0 or self.margin < 0:
            raise ValueError("reflectance must be in [0, 1) and margin >= 0")

    @classmethod
    def oled(cls, refresh_hz: float = 60.0, pwm_hz: float | None = 240.0) -> Display:
        """A phone-style OLED: microsecond switching, deep blacks, PWM dimming (240 Hz is common
        on phones below full brightness)."""
        return cls(
            refresh_hz=refresh_hz,
            rise_ms=0.0,
            fall_ms=0.0,
            black_nits=0.01,
            peak_nits=400.0,
            pwm_hz=pwm_hz,
        )

    @property
    def period_us(self) -> float:
        return 1e6 / self.refresh_hz

    @property
    def scan_us(self) -> float:
        """Time the scan takes from the top row to the bottom row."""
        return self.scanout_fraction * self.period_us

    def backlight_us(self) -> tuple[float, float]:
        """(PWM period, on time) in us, as the kernels take them; (0, 0) without PWM."""
        if self.pwm_hz is None or self.pwm_duty == 1.0:
            return 0.0, 0.0
        period = 1e6 / self.pwm_hz
        return period, self.pwm_duty * period

    def ambient_nits(self, lux: float) -> float:
        return lux * self.reflectance * LUX_TO_NITS_PER_REFLECTANCE

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Display:
        return replace(cls(), **d)


@dataclass(frozen=True)
class ScreenLayout:
    """Where the marker sits on the screen, in the marker frame (metres, y down)."""

    cell_m: float
    ring: int
    side: int
    """Cells across the whole marker."""
    screen_top_m: float
    """Marker-frame y (and x) of the screen's top-left corner."""
    screen_side_m: float

    @classmethod
    def of(cls, geometry: MarkerGeometry, marker_size_m: float, display: Display) -> ScreenLayout:
        cell = geometry.cell_size_m(marker_size_m)
        outer = geometry.side * cell
        margin = display.margin * outer
        return cls(
            cell, geometry.ring, geometry.side, -geometry.ring * cell - margin, outer + 2 * margin
        )

    @property
    def marker_top_fraction(self) -> float:
        """Screen-height fraction of the marker's top edge (outer black ring)."""
        return (-self.ring * self.cell_m - self.screen_top_m) / self.screen_side_m

    @property
    def marker_height_fraction(self) -> float:
        return self.side * self.cell_m / self.screen_side_m

    def screen_corners(self) -> np.ndarray:
        """(4, 3) marker-frame corners of the lit screen area: TL, TR, BR, BL."""
        lo, hi = self.screen_top_m, self.screen_top_m + self.screen_side_m
        return np.array([[lo, lo, 0.0], [hi, lo, 0.0], [hi, hi, 0.0], [lo, hi, 0.0]])


def settle(
    start: np.ndarray, target: np.ndarray, elapsed_us: float, display: Display
) -> np.ndarray:
    """Emitted luminance ``elapsed_us`` after a switch from ``start`` towards ``target``."""
    tau = np.where(target > start, display.rise_ms, display.fall_ms) * 1e3
    with np.errstate(divide="ignore"):
        decay = np.where(tau > 0, np.exp(-elapsed_us / np.maximum(tau, 1e-12)), 0.0)
    return target + (start - target) * decay


LEAD_IN_CONTENTS = ("black", "bars")
_BAR_PERIOD_CELLS = 8
"""Cells from one bar of the lead-in's moving content to the next (half of them lit): each
cell toggles every 4 refreshes, far from the marker's blink at half the refresh rate."""


@dataclass(frozen=True)
class LeadIn:
    """What the screen shows over the marker's area before the marker's first refresh, for
    ``refreshes`` refreshes from t = 0: black (a page still loading, a screen waking up) or
    ``bars``, diagonal white bars sweeping one cell per refresh (unrelated moving content)."""

    refreshes: int = 0
    content: str = "black"

    def __post_init__(self) -> None:
        if self.refreshes < 0:
            raise ValueError(f"lead-in refreshes must be >= 0, got {self.refreshes}")
        if self.content not in LEAD_IN_CONTENTS:
            raise ValueError(
                f"unknown lead-in content {self.content!r}; valid: {', '.join(LEAD_IN_CONTENTS)}"
            )

    def frame(self, j: int, side: int) -> np.ndarray:
        """Bool (side, side): the cells at lead-in refresh ``j`` (0 at t = 0)."""
        if self.content == "black":
            return np.zeros((side, side), bool)
        rows, cols = np.mgrid[0:side, 0:side]
        return (rows + cols + j) % _BAR_PERIOD_CELLS < _BAR_PERIOD_CELLS // 2

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TimelineWindow:
    """Per-cell emitted luminance of refreshes ``k_first ..``: the level each refresh drives
    towards and the level at the instant of its switch (both cd/m², flattened cell index)."""

    k_first: int
    target: np.ndarray
    at_switch: np.ndarray


class DisplayTimeline:
    """What every marker cell emits at each refresh of the stream, computed on demand in order.

    Refresh ``start_refresh`` of the stream is the first the marker shows, after the
    ``lead_in``'s refreshes: ``self.start_refresh``, ``start_refresh - lead_in.refreshes``,
    starts scanning out at t = 0. Refreshes before the stream's first are blank frames, those
    of the lead-in show its content, and the screen had settled on refresh
    ``self.start_refresh - 1`` when the simulation starts.
    """

    def __init__(
        self, encoder, display: Display, start_refresh: int = 0, lead_in: LeadIn | None = None
    ) -> None:
        self.encoder = encoder
        self.display = display
        self.lead_in = lead_in or LeadIn()
        self.marker_from = start_refresh
        """The first refresh that shows the marker."""
        self.start_refresh = start_refresh - self.lead_in.refreshes
        """The refresh whose scan-out starts at t = 0."""
        self._states: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        first = self.start_refresh - 1
        target = self.target(first)
        self._states[first] = (target, target.copy())

    def frame(self, k: int) -> np.ndarray:
        if k < self.marker_from and self.lead_in.refreshes:
            return self.lead_in.frame(k - self.start_refresh, self.encoder.geometry.side)
        if k < 0:
            return self.encoder.geometry.blank_frame
        return self.encoder.frame(k)

    def target(self, k: int) -> np.ndarray:
        d = self.display
        return np.where(self.frame(k).ravel(), d.peak_nits, d.black_nits)

    def refresh_start_us(self, k: np.ndarray | int) -> np.ndarray:
        return (np.asarray(k, dtype=np.float64) - self.start_refresh) * self.display.period_us

    def refresh_at(self, t_us: float, v: float = 0.0) -> int:
        """The refresh screen row ``v`` shows at time ``t_us``."""
        d = self.display
        return self.start_refresh + math.floor((t_us - v * d.scan_us) / d.period_us)

    def window(self, k_lo: int, k_hi: int) -> TimelineWindow:
        """States of refreshes ``k_lo .. k_hi`` (inclusive); calls must move forward in time."""
        k_lo = max(k_lo, self.start_refresh - 1)
        if k_lo not in self._states:
            raise ValueError(f"refresh {k_lo} was dropped: timeline windows must move forward")
        last = max(self._states)
        for k in range(last + 1, k_hi + 1):
            target, at_switch = self._states[k - 1]
            self._states[k] = (
                self.target(k),
                settle(at_switch, target, self.display.period_us, self.display),
            )
        for k in [k for k in self._states if k < k_lo]:
            del self._states[k]
        ks = range(k_lo, k_hi + 1)
        return TimelineWindow(
            k_lo,
            np.stack([self._states[k][0] for k in ks]),
            np.stack([self._states[k][1] for k in ks]),
        )
