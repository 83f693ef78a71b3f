"""The event sensor: parameters, presets, and the level-crossing kernels.

Model (ESIM, Rebecq et al. CoRL 2018, with the noise of v2e, Hu et al. CVPRW 2021, and the
timing of IEBCS): a pixel holds a reference log intensity ``R``; whenever its log irradiance
``ln(J + dark)`` moves a whole threshold ``C`` (per pixel, per polarity: fixed-pattern mismatch)
away from ``R`` it emits an event and ``R`` steps by ``C``. Crossing times come from linear
interpolation between samples (ESIM) or, where the irradiance is a known exponential, from the
exact inverse. A pixel that fired less than the refractory period ago stays silent, but its
reference still advances (as in ESIM, v2e and the OpenEB simulator). Leak (ON) and shot noise
(both polarities, more frequent in the dark) are drawn as Poisson processes, independently of the
reference (a simplification: v2e lets a noise event move ``R``). Every event is then delayed by
the pixel latency plus Gaussian jitter, and an optional readout cap drops events uniformly.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import NamedTuple

import numba
import numpy as np

from eventocc.receiver.events import EVENT_DTYPE

SHOT_NOISE_BRIGHT_FACTOR = 0.25
"""v2e: shot-noise rate at full intensity relative to the dark rate."""
PHOTORECEPTOR_REF_NITS = 100.0
"""Scene luminance (cd/m²) at which ``SensorModel.photoreceptor_hz`` is stated."""


@dataclass(frozen=True)
class SensorModel:
    """Event-sensor parameters. ``preset()`` gives documented sets; fields may be overridden with
    ``dataclasses.replace``."""

    name: str = "ideal"
    lux: float = 250.0
    """Ambient illuminance of the scene: sets the wall and screen-reflection levels and, through
    the pixel intensity, the shot-noise rate."""
    threshold_on: float = 0.2
    threshold_off: float = 0.2
    """Contrast thresholds in ln units."""
    threshold_sigma: float = 0.0
    """Per-pixel standard deviation of both thresholds (fixed-pattern mismatch)."""
    refractory_us: float = 0.0
    leak_hz: float = 0.0
    """ON background events per pixel per second."""
    shot_hz: float = 0.0
    """Shot-noise events per pixel per second in the dark (both polarities together)."""
    latency_us: float = 0.0
    jitter_us: float = 0.0
    dark_nits: float = 0.01
    """Dark current as an equivalent scene luminance: the floor under the log."""
    max_rate_hz: float | None = None
    """Readout cap in events per second (None: unlimited); excess events drop uniformly per ms."""
    photoreceptor_hz: float = 0.0
    """3 dB cut-off of the photoreceptor at ``PHOTORECEPTOR_REF_NITS`` of scene luminance,
    proportional to the pixel's luminance (v2e); 0: infinitely fast. A first-order low-pass of
    the log irradiance; simulated for a still camera (a moving one is refused)."""
    readout_hz: float | None = None
    """Peak rate of the sensor's readout (events/s): beyond it events wait and are timestamped
    late (``eventocc.receiver.sim.readout``). None: unlimited."""
    erc_hz: float | None = None
    """Event-rate controller: at most this rate (events/s) in each ``erc_period_us``, the
    excess dropped evenly. None: off."""
    erc_period_us: int = 1000
    link_hz: float | None = None
    """Events/s the link to the host carries; None: unlimited."""
    link_buffer: int = 0
    """Events the camera buffers for the link; while it is full, arriving events are lost."""

    def __post_init__(self) -> None:
        if self.lux < 0:
            raise ValueError(f"lux must be >= 0, got {self.lux}")
        if min(self.threshold_on, self.threshold_off) < 0.01:
            raise ValueError(
                "contrast thresholds must be >= 0.01 ln units, got "
                f"{self.threshold_on}, {self.threshold_off}"
            )
        for name in (
            "threshold_sigma",
            "refractory_us",
            "leak_hz",
            "shot_hz",
            "latency_us",
            "jitter_us",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.dark_nits <= 0:
            raise ValueError(f"dark_nits must be positive, got {self.dark_nits}")
        if self.max_rate_hz is not None and self.max_rate_hz <= 0:
            raise ValueError(f"max_rate_hz must be positive or None, got {self.max_rate_hz}")
        for name in ("readout_hz", "erc_hz", "link_hz"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueError(f"{name} must be positive or None, got {value}")
        if self.photoreceptor_hz < 0:
            raise ValueError(f"photoreceptor_hz must be >= 0, got {self.photoreceptor_hz}")
        if self.erc_period_us < 1:
            raise ValueError(f"erc_period_us must be >= 1 us, got {self.erc_period_us}")
        if self.link_hz is not None and self.link_buffer < 1:
            raise ValueError(
                f"a link needs a buffer of at least one event, got link_buffer={self.link_buffer}"
            )
        if self.erc_hz is not None and self.erc_hz * self.erc_period_us * 1e-6 < 1:
            raise ValueError(
                f"erc_hz {self.erc_hz:g}/s lets no event through a {self.erc_period_us} us period"
            )

    @classmethod
    def preset(cls, name: str, lux: float | None = None) -> SensorModel:
        try:
            base = PRESETS[name]
        except KeyError:
            raise ValueError(
                f"unknown sensor preset {name!r}; valid presets: {', '.join(PRESETS)}"
            ) from None
        return base if lux is None else replace(base, lux=lux)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> SensorModel:
        return cls(**d)


_GEN4 = SensorModel(
    name="gen4-indoor",
    lux=250.0,  # the paper's "normal indoor lighting"
    # IMX636 nominal contrast sensitivity ~25 % (vendor figure) -> ln(1.25) = 0.22.
    threshold_on=0.22,
    threshold_off=0.22,
    threshold_sigma=0.03,  # v2e CLI default; v2e/OpenEB "noisy" use 0.05
    refractory_us=50.0,  # IEBCS example value (v2e CLI 500 us, OpenEB GPU 10 us)
    leak_hz=0.1,  # v2e / OpenEB "noisy" leak rate
    shot_hz=0.1,  # low end of v2e/OpenEB noisy 0.1-10 Hz: ~100 k ev/s over a 1 MP sensor
    latency_us=200.0,  # IEBCS example (IMX636 vendor figure: < 100 us at 1 klux)
    jitter_us=50.0,  # IEBCS example
)

_EVK4 = SensorModel(
    # Prophesee EVK4 HD: Sony IMX636 (Prophesee Gen 4.1), 1280x720, 4.86 um pixels; the paper's
    # camera. Biases at their defaults: each field below moves with one of them (Prophesee's
    # "Biases" manual: bias_diff_on/off the thresholds, bias_refr the refractory period,
    # bias_fo the photoreceptor's low-pass).
    name="evk4",
    lux=250.0,  # the paper's "normal indoor lighting"
    # IMX636 nominal contrast sensitivity ~25 % (vendor figure) -> ln(1.25) = 0.22.
    threshold_on=0.22,
    threshold_off=0.22,
    # Pixel-to-pixel threshold mismatch: v2e's CLI default 0.03, v2e/OpenEB "noisy" 0.05.
    threshold_sigma=0.04,
    # bias_refr's dead time; simulators' defaults span IEBCS's 50 us to v2e's 500 us.
    refractory_us=100.0,
    leak_hz=0.1,  # v2e / OpenEB "noisy" leak rate
    shot_hz=0.1,  # low end of v2e/OpenEB noisy 0.1-10 Hz
    # IMX636 latency < 100 us at 1 klux (vendor figure): a white surface under 1 klux is
    # 318 cd/m², so tau = 100 us there, f3dB = 1 / (2 pi tau) = 1.6 kHz, 500 Hz at 100 cd/m²
    # (v2e: the cut-off scales with the light). The screen's white then takes tau = 127 us,
    # its black (1.8 cd/m² at 250 lux) 17 ms.
    photoreceptor_hz=500.0,
    latency_us=0.0,  # the photoreceptor above is the pixel's latency
    jitter_us=50.0,  # IEBCS example
    # Finateu et al., ISSCC 2020 (the IMX636's design): "1.066 GEPS readout".
    readout_hz=1.066e9,
    # The sensor's event-rate controller (Prophesee's ESP manual) as our receiver sets it on a
    # live EVK4 (receiver/live/controls.py: 100 M events/s in 1 ms periods).
    erc_hz=100e6,
    erc_period_us=1000,
    # USB 3 link: 1.6 Gbit/s (Prophesee's EVK3 page; the EVK4 has the same interface) at 25
    # bits per event (Lucid's Triton2 EVS note: ERC at 40 M events/s for a 1 Gbit/s link).
    link_hz=64e6,
    link_buffer=64_000,  # our assumption: one millisecond of the link buffered in the camera
)

PRESETS: dict[str, SensorModel] = {
    # ESIM's clean defaults: thresholds 0.2, no mismatch, no noise, no delay.
    "ideal": SensorModel(),
    "gen4-indoor": _GEN4,
    # The paper's other two light levels (Sec. V-A): night-time and sunlit rooms.
    "gen4-night": replace(_GEN4, name="gen4-night", lux=10.0),
    "gen4-sunlit": replace(_GEN4, name="gen4-sunlit", lux=1000.0),
    "evk4": _EVK4,
    # The same camera set up for a screen link: bias_refr raised to v2e's CLI refractory
    # period, and the event-rate controller below the USB link, so that the link's buffer
    # never fills (the controller alone thins, evenly within each period).
    "evk4-link": replace(_EVK4, name="evk4-link", refractory_us=500.0, erc_hz=60e6),
    # For a moving camera, whose renderer has no photoreceptor low-pass: its lag at the
    # screen's white (127 us) as a fixed latency instead.
    "evk4-moving": replace(_EVK4, name="evk4-moving", photoreceptor_hz=0.0, latency_us=127.0),
}


@dataclass(frozen=True)
class PixelArray:
    """Per-pixel draws of one sensor instance (fixed pattern), flattened row-major."""

    threshold_on: np.ndarray
    threshold_off: np.ndarray
    leak_factor: np.ndarray

    @classmethod
    def draw(cls, sensor: SensorModel, n: int, rng: np.random.Generator) -> PixelArray:
        def thresholds(mean: float) -> np.ndarray:
            c = mean + sensor.threshold_sigma * rng.standard_normal(n)
            return np.clip(c, 0.01, 1.0)

        on, off = thresholds(sensor.threshold_on), thresholds(sensor.threshold_off)
        # v2e: per-pixel log-normal leak rate, coefficient of variation 0.1 in decades.
        leak = np.exp(math.log(10) * 0.1 * rng.standard_normal(n))
        return cls(on, off, leak)


# --- level crossings (numba) -----------------------------------------------------------------


LEVEL, REF, LAST, C_ON, C_OFF = range(5)
"""Rows of the per-pixel state the level-crossing kernels update: log irradiance rendered so far,
reference log level (events fire when the level moves a threshold away from it), time (us) of
the last event (the refractory period counts from it), ON and OFF thresholds. One 2-D array
rather than five: numba passes each array argument at a cost, and the kernels nest deeply."""

EVENT_OUT_DTYPE = np.dtype([("t", np.float64), ("i", np.int64), ("p", np.int8)])
"""What the kernels write per event: time (us, float), pixel index, polarity."""


def pixel_state(level: np.ndarray, c_on: np.ndarray, c_off: np.ndarray) -> np.ndarray:
    """State of pixels that have seen ``level`` for ever: reference there, no event yet."""
    return np.stack([level, level, np.full(len(level), -np.inf), c_on, c_off])


class PixelSink(NamedTuple):
    """Where a renderer's window kernel writes: the pixels' state (rows ``LEVEL`` .. ``C_OFF``),
    their refractory period (us) and the output for the events (``EVENT_OUT_DTYPE``; the
    kernels return the count, which may pass its capacity). The level-crossing kernels under
    it take the three apart: they run per pixel and segment, and arrays taken out of a tuple
    there cost time (a simulation ran 8-17 % slower)."""

    state: np.ndarray
    refractory: float
    out: np.ndarray


class EventBuffer:
    """Output array the kernels fill (``EVENT_OUT_DTYPE``), reused from window to window (a
    fresh multi-megabyte array would cost a page fault per 4 KiB on every window). Kernels
    return the event count, which may exceed the capacity: then ``grow`` and rerun."""

    def __init__(self, capacity: int = 1 << 18) -> None:
        self._out = np.empty(capacity, EVENT_OUT_DTYPE)

    def get(self) -> np.ndarray:
        """The output array, to be copied out before the next ``get``."""
        return self._out

    def grow(self) -> None:
        self._out = np.empty(2 * len(self._out), EVENT_OUT_DTYPE)


@numba.njit(cache=True, inline="always")
def _emit(t, i, p, state, refractory, out, n):
    if t - state[LAST, i] >= refractory:
        state[LAST, i] = t
        if n < out.shape[0]:
            e = out[n]
            e.t = t
            e.i = i
            e.p = p
        return n + 1
    return n


@numba.njit(cache=True)
def cross_linear(ta, la, tb, lb, i, state, refractory, out, n):
    """Events of pixel ``i`` while its log intensity goes linearly from ``la`` at ``ta`` to
    ``lb`` at ``tb`` (``ta == tb``: a step, every event at that instant)."""
    dl = lb - la
    while lb >= state[REF, i] + state[C_ON, i]:
        level = state[REF, i] + state[C_ON, i]
        t = tb if dl == 0.0 else ta + (level - la) / dl * (tb - ta)
        n = _emit(min(max(t, ta), tb), i, 1, state, refractory, out, n)
        state[REF, i] = level
    while lb <= state[REF, i] - state[C_OFF, i]:
        level = state[REF, i] - state[C_OFF, i]
        t = tb if dl == 0.0 else ta + (level - la) / dl * (tb - ta)
        n = _emit(min(max(t, ta), tb), i, -1, state, refractory, out, n)
        state[REF, i] = level
    return n


@numba.njit(cache=True)
def cross_exponential(t0, ua, ub, a, b, tau, i, state, refractory, out, n):
    """Events of pixel ``i`` whose irradiance (dark floor included) is ``a + b exp(-u / tau)``
    at ``t0 + u``, for ``u`` from ``ua`` to ``ub``; crossing times are exact. Leaves the log
    level at ``ub`` in the state."""
    lb = math.log(a + b * math.exp(-ub / tau))
    while lb >= state[REF, i] + state[C_ON, i]:
        level = state[REF, i] + state[C_ON, i]
        u = -tau * math.log((math.exp(level) - a) / b)
        n = _emit(t0 + min(max(u, ua), ub), i, 1, state, refractory, out, n)
        state[REF, i] = level
    while lb <= state[REF, i] - state[C_OFF, i]:
        level = state[REF, i] - state[C_OFF, i]
        u = -tau * math.log((math.exp(level) - a) / b)
        n = _emit(t0 + min(max(u, ua), ub), i, -1, state, refractory, out, n)
        state[REF, i] = level
    state[LEVEL, i] = lb
    return n


@numba.njit(cache=True, inline="always")
def _relaxed_at(d0, d, tau, span):
    """When (within [0, span]) ``d0 exp(-u / tau)`` reaches ``d``."""
    if d == 0.0:
        return span
    if d0 * d <= 0.0:
        return 0.0
    return min(max(tau * math.log(d0 / d), 0.0), span)


@numba.njit(cache=True)
def cross_relaxation(t0, span, y0, target, tau, j, state, refractory, out, n):
    """Events of pixel ``j`` while its level relaxes as ``target + (y0 - target) exp(-u/tau)``
    over ``u`` in [0, span] from ``t0``; crossing times are exact."""
    y_end = target + (y0 - target) * math.exp(-span / tau)
    d0 = y0 - target
    while y_end >= state[REF, j] + state[C_ON, j]:
        level = state[REF, j] + state[C_ON, j]
        n = _emit(t0 + _relaxed_at(d0, level - target, tau, span), j, 1, state, refractory, out, n)
        state[REF, j] = level
    while y_end <= state[REF, j] - state[C_OFF, j]:
        level = state[REF, j] - state[C_OFF, j]
        n = _emit(t0 + _relaxed_at(d0, level - target, tau, span), j, -1, state, refractory, out, n)
        state[REF, j] = level
    return n


# --- noise, delay, readout (numpy, per chunk) --------------------------------------------------


def background_rates(
    sensor: SensorModel, pixels: PixelArray, intensity: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel leak (ON) and shot-noise rates in Hz. ``intensity`` is each pixel's irradiance
    relative to the screen's white (v2e's ``(I + 20) / 275`` on 8-bit values)."""
    leak = sensor.leak_hz * pixels.leak_factor
    rel = (np.clip(intensity, 0.0, 1.0) * 255 + 20) / 275
    bright = 1.0 - (1.0 - SHOT_NOISE_BRIGHT_FACTOR) * rel
    c_nominal = 0.5 * (sensor.threshold_on + sensor.threshold_off)
    c_pixel = 0.5 * (pixels.threshold_on + pixels.threshold_off)
    shot = sensor.shot_hz * bright * c_nominal / c_pixel
    return leak, shot


class BackgroundNoise:
    """Poisson leak and shot-noise events over the whole sensor, drawn per time window.

    Each source is drawn by thinning: candidates at the highest pixel rate land on uniformly
    random pixels and each survives with probability rate / highest rate, which is exact for
    independent per-pixel Poisson processes and needs no search through a million-entry table.
    """

    def __init__(self, leak_hz: np.ndarray, shot_hz: np.ndarray) -> None:
        self._sources = []
        for rates, polarity in ((leak_hz, 1), (shot_hz, 0)):
            peak = float(rates.max(initial=0.0))
            if peak > 0:
                self._sources.append((peak, rates / peak, polarity))

    def events(
        self, t0: float, t1: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ts, idx, ps = [np.zeros(0)], [np.zeros(0, np.int64)], [np.zeros(0, np.int8)]
        for peak, accept, polarity in self._sources:
            n = rng.poisson(peak * len(accept) * (t1 - t0) * 1e-6)
            pix = rng.integers(0, len(accept), n)
            pix = pix[rng.random(n) < accept[pix]]
            ts.append(rng.uniform(t0, t1, len(pix)))
            idx.append(pix)
            ps.append(
                np.full(len(pix), polarity, np.int8)
                if polarity
                else rng.choice(np.array([-1, 1], np.int8), len(pix))
            )
        return np.concatenate(ts), np.concatenate(idx), np.concatenate(ps)


def to_events(
    t: np.ndarray,
    idx: np.ndarray,
    p: np.ndarray,
    width: int,
    sensor: SensorModel,
    rng: np.random.Generator,
    pending: np.ndarray | None = None,
) -> np.ndarray:
    """Delay, quantise to microseconds, cap the readout rate, and pack as events sorted by time
    together with the already packed ``pending`` events (held back from an earlier window)."""
    delay = sensor.latency_us
    if sensor.jitter_us:
        # No event is read out before its change happened: an early one would land in a time
        # already handed out in an earlier chunk, out of order.
        delay = np.maximum(delay + sensor.jitter_us * rng.standard_normal(len(t)), 0.0)
    t = t + delay
    t_us = np.maximum(np.rint(t), 0).astype(np.int64)
    if sensor.max_rate_hz is not None and len(t_us):
        keep = _readout_cap(t_us, sensor.max_rate_hz * 1e-3, rng)
        t_us, idx, p = t_us[keep], idx[keep], p[keep]
    if pending is not None and len(pending):
        t_us = np.concatenate([pending["t"], t_us])
        idx = np.concatenate([pending["y"].astype(np.int64) * width + pending["x"], idx])
        p = np.concatenate([pending["p"], p])
    ev = np.empty(len(t_us), EVENT_DTYPE)
    if len(t_us):
        _pack_sorted(
            t_us, idx.astype(np.int64, copy=False), p.astype(np.int8, copy=False), width, ev
        )
    return ev


@numba.njit(cache=True)
def _pack_sorted(t_us, idx, p, width, out):
    """Fill ``out`` with the events sorted by time, stably. A window's events span a few
    milliseconds, so a counting sort over its microseconds is linear and several times faster
    than a comparison sort."""
    lo, hi = t_us.min(), t_us.max()
    if hi - lo > 4 * len(t_us) + 1_000_000:  # sparse events over a long span
        order = np.argsort(t_us, kind="mergesort")
    else:
        start = np.zeros(hi - lo + 2, np.int64)
        for t in t_us:
            start[t - lo + 1] += 1
        for k in range(1, len(start)):
            start[k] += start[k - 1]
        order = np.empty(len(t_us), np.int64)
        for j in range(len(t_us)):
            k = t_us[j] - lo
            order[start[k]] = j
            start[k] += 1
    for n in range(len(order)):
        j = order[n]
        e = out[n]
        e["t"] = t_us[j]
        e["x"] = idx[j] % width
        e["y"] = idx[j] // width
        e["p"] = p[j]


def _readout_cap(t_us: np.ndarray, per_ms: float, rng: np.random.Generator) -> np.ndarray:
    """Mask keeping at most ``per_ms`` events in each millisecond, chosen uniformly: in each
    millisecond that holds more, the ``ceil(per_ms)`` with the smallest of a uniform random key
    each."""
    ms = t_us // 1000
    key = rng.random(len(ms))
    return _smallest_keys(ms - ms.min(), key, math.ceil(per_ms))


@numba.njit(cache=True)
def _smallest_keys(bucket, key, k):
    """Mask of the entries whose ``key`` is among the ``k`` smallest of their ``bucket``
    (integers from 0 on). Linear: a partition per over-full bucket, no sort (a sort of a
    capped second's tens of millions of keys took most of a simulation's time)."""
    counts = np.zeros(bucket.max() + 1, np.int64)
    for b in bucket:
        counts[b] += 1
    keep = np.ones(len(bucket), np.bool_)
    if counts.max() <= k:
        return keep
    start = np.zeros(len(counts) + 1, np.int64)
    for b in range(len(counts)):
        start[b + 1] = start[b] + (counts[b] if counts[b] > k else 0)
    grouped = np.empty(start[-1])
    filled = start[:-1].copy()
    for i in range(len(bucket)):
        b = bucket[i]
        if counts[b] > k:
            grouped[filled[b]] = key[i]
            filled[b] += 1
    limit = np.full(len(counts), np.inf)
    for b in range(len(counts)):
        if counts[b] > k:
            limit[b] = np.partition(grouped[start[b] : start[b + 1]], k - 1)[k - 1]
    for i in range(len(bucket)):
        keep[i] = key[i] <= limit[bucket[i]]
    return keep
