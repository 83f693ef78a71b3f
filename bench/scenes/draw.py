"""Drawing the suite's scenes: every parameter from the range real cameras and screens span.

A scene is drawn from ``(seed, index)`` alone, so any subset of a suite can be rerun. Ranges
(``RANGES``) follow the receiver's issue: display (LC rise and fall, scan-out, black level,
PWM backlight), sensor (thresholds and their mismatch, refractory period, leak, shot noise,
latency and jitter, readout cap), optics (radial and tangential distortion, blur, vignetting),
geometry (any roll, oblique views, pixels per cell), time (a lead-in of black screen or unrelated
moving content before the marker appears, any time base), hand-held motion, N, profile and
refresh rate. Pixels per cell and N are drawn together under one constraint: the marker must fit
one of three real sensor formats (a hand-held one with room to wander).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.profiles import PROFILE_NAMES, get_profile
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.sim import Display, HandHeldMotion, Optics, Scene, SensorModel, StaticMotion
from eventocc.receiver.sim.display import LEAD_IN_CONTENTS, LeadIn
from eventocc.receiver.sim.motion import look_at, project_points

SENSORS = ((346, 260), (640, 480), (1280, 720), (1280, 960))
"""Sensor formats (DAVIS346, Prophesee Gen3 VGA, IMX636, Samsung DVS Gen4): a scene gets the
smallest its marker fits."""
CELLS = tuple(range(16, 129, 8))
"""N, drawn uniformly among those that fit."""
REFRESH_HZ = (60.0, 75.0, 90.0, 120.0, 144.0, 165.0, 240.0)
HAND_HELD_SHARE = 0.55
"""Share of scenes with a hand-held camera (the others stand still)."""
STATIC_FIT = 0.9
HAND_HELD_FIT = 0.55
"""Share of the sensor's width and height the marker may span: a hand-held wander shifts it by
up to 70% of the room left and turns it by up to 12 degrees."""
MOVING_MAX_PX = 240
"""A hand-held scene's marker spans at most this many pixels: the simulator's moving camera costs
CPU time in proportion to the marker's pixels (``docs/BENCHMARKS.md``'s simulator section)."""
PWM_MAX_PX = 240
"""A PWM backlight only on markers that span at most this many pixels (square-on): its edges make
every lit pixel fire twice per PWM period, and a 1.4 kHz backlight on a 740 px marker took the
simulator past 15 CPU minutes for a 1.6 s clip."""
AFTER_S = 0.7
"""Simulated seconds after the marker appears."""
MESSAGE_SHARE = 0.15
"""A message takes this share of the raw capacity of ``AFTER_S``: it spans many frames, and
leaves room for the lock, FEC and a frame or two missed."""
PWM_SHARE = 0.5
"""Share of still scenes with a PWM backlight (the simulator renders PWM for still cameras),
where the marker is small enough (``PWM_MAX_PX``)."""

RANGES: dict[str, tuple[float, float]] = {
    "cell_px": (4.0, 30.0),
    "refresh_hz": (60.0, 240.0),
    "flow_px_per_ms": (0.1, 2.0),
    "roll_deg": (-180.0, 180.0),
    "view_deg": (0.0, 45.0),
    "hfov_deg": (40.0, 70.0),
    "marker_size_m": (0.1, 0.6),
    "k1": (-0.3, 0.1),
    "tangential": (-0.002, 0.002),
    "blur_px": (0.0, 1.5),
    "vignetting": (0.0, 0.5),
    "rise_ms": (0.3, 5.0),
    "fall_ms": (0.3, 5.0),
    "scanout": (0.5, 1.0),
    "peak_nits": (150.0, 500.0),
    "contrast": (300.0, 5000.0),
    "reflectance": (0.01, 0.04),
    "pwm_hz": (200.0, 2000.0),
    "pwm_duty": (0.3, 0.9),
    "lux": (20.0, 1000.0),
    "threshold": (0.12, 0.5),
    "threshold_sigma": (0.0, 0.06),
    "refractory_us": (20.0, 1500.0),
    "leak_hz": (0.0, 0.5),
    "shot_hz": (0.05, 2.0),
    "latency_us": (20.0, 2000.0),
    "jitter_share": (0.0, 0.5),
    "max_rate_mev_s": (5.0, 100.0),
    "lead_in_s": (0.0, 1.0),
    "time_base_us": (1e3, 1e10),
}
"""Uniform ranges, or log-uniform for the names in ``LOG_UNIFORM``."""
LOG_UNIFORM = {
    "cell_px",
    "rise_ms",
    "fall_ms",
    "contrast",
    "pwm_hz",
    "lux",
    "refractory_us",
    "shot_hz",
    "latency_us",
    "max_rate_mev_s",
    "time_base_us",
}


@dataclass(frozen=True)
class SceneDraw:
    """One drawn scene, flat and JSON-able: what ``scene()`` builds and the suite reports by."""

    seed: int
    index: int
    profile: str
    cells: int
    refresh_hz: float
    cell_px: float
    """Pixels per cell at the marker centre, as if seen square-on (``Scene.cell_px``)."""
    width: int
    height: int
    hfov_deg: float
    k1: float
    p1: float
    p2: float
    blur_px: float
    vignetting: float
    marker_size_m: float
    distance_m: float
    roll_deg: float
    view_deg: float
    """How oblique the view is: the angle between the optical axis and the marker's normal."""
    tilt_deg: float
    elevation_deg: float
    flow_px_per_ms: float
    """Mean image flow of the hand-held wander; 0 for a still camera."""
    rise_ms: float
    fall_ms: float
    scanout: float
    peak_nits: float
    contrast: float
    reflectance: float
    pwm_hz: float | None
    pwm_duty: float
    lux: float
    threshold_on: float
    threshold_off: float
    threshold_sigma: float
    refractory_us: float
    leak_hz: float
    shot_hz: float
    latency_us: float
    jitter_us: float
    max_rate_mev_s: float | None
    lead_in_refreshes: int
    lead_in_content: str
    time_base_us: int
    start_refresh: int
    message_bytes: int
    sim_seed: int

    @property
    def moving(self) -> bool:
        return self.flow_px_per_ms > 0

    @property
    def lead_in_s(self) -> float:
        return self.lead_in_refreshes / self.refresh_hz

    @property
    def duration_s(self) -> float:
        return self.lead_in_s + AFTER_S

    def camera(self) -> CameraModel:
        return _camera(self.width, self.height, self.hfov_deg, self.k1, self.p1, self.p2)

    def message(self) -> bytes:
        return np.random.default_rng([self.seed, self.index, 1]).bytes(self.message_bytes)

    def scene(self) -> Scene:
        view = {"tilt_deg": self.tilt_deg, "elevation_deg": self.elevation_deg}
        motion = (
            HandHeldMotion(
                self.distance_m,
                self.flow_px_per_ms,
                seed=self.sim_seed,
                roll_deg=self.roll_deg,
                **view,
            )
            if self.moving
            else StaticMotion(self.distance_m, roll_deg=self.roll_deg, **view)
        )
        return Scene(
            encoder=StreamEncoder(self.message(), profile=self.profile, cells=self.cells),
            marker_size_m=self.marker_size_m,
            display=Display(
                refresh_hz=self.refresh_hz,
                scanout_fraction=self.scanout,
                rise_ms=self.rise_ms,
                fall_ms=self.fall_ms,
                black_nits=self.peak_nits / self.contrast,
                peak_nits=self.peak_nits,
                pwm_hz=self.pwm_hz,
                pwm_duty=self.pwm_duty,
                reflectance=self.reflectance,
            ),
            camera=self.camera(),
            motion=motion,
            sensor=SensorModel(
                name="drawn",
                lux=self.lux,
                threshold_on=self.threshold_on,
                threshold_off=self.threshold_off,
                threshold_sigma=self.threshold_sigma,
                refractory_us=self.refractory_us,
                leak_hz=self.leak_hz,
                shot_hz=self.shot_hz,
                latency_us=self.latency_us,
                jitter_us=self.jitter_us,
                max_rate_hz=None if self.max_rate_mev_s is None else self.max_rate_mev_s * 1e6,
            ),
            optics=Optics(blur_px=self.blur_px, vignetting=self.vignetting),
            start_refresh=self.start_refresh,
            lead_in=LeadIn(self.lead_in_refreshes, self.lead_in_content),
            time_base_us=self.time_base_us,
            seed=self.sim_seed,
        )

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> SceneDraw:
        return cls(**{f.name: d[f.name] for f in fields(cls)})


def with_values(d: SceneDraw, assignments: list[str]) -> SceneDraw:
    """``d`` with some of its drawn values replaced, each given as ``NAME=VALUE`` (a JSON value:
    a number, ``null``, or a bare word for a string): how one scene fares with one thing
    changed, say a PWM backlight. Only what ``SceneDraw.scene`` reads takes effect (``cell_px``
    is a report of the drawn geometry, not an input)."""
    names = {f.name for f in fields(SceneDraw)}
    values = {}
    for assignment in assignments:
        name, sep, raw = assignment.partition("=")
        if not sep or name not in names:
            raise ValueError(
                f"expected NAME=VALUE with NAME a scene parameter, got {assignment!r} "
                f"(parameters: {', '.join(sorted(names))})"
            )
        try:
            values[name] = json.loads(raw)
        except json.JSONDecodeError:
            values[name] = raw
    return replace(d, **values)


def _camera(width: int, height: int, hfov_deg: float, k1: float, p1: float, p2: float):
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, np.array([k1, 0.0, p1, p2, 0.0]))


FOLD_MARGIN = 0.8
"""A drawn lens keeps the sensor's corners within this share of the largest radius its radial
distortion reaches (``folds``)."""


def folds(width: int, height: int, hfov_deg: float, k1: float) -> bool:
    """Whether a barrel distortion ``k1`` folds over within the sensor: ``r (1 + k1 r^2)`` peaks
    at ``r^2 = -1 / (3 k1)``, and pixels beyond that peak's image see no ray (their inverse is
    garbage: 700 px off at the corners of a 640x480 sensor, 70 deg wide, k1 = -0.3). A real lens
    of such a field has a k2 to keep it monotonic; the suite draws k1 alone and keeps the corners
    within ``FOLD_MARGIN`` of the peak."""
    if k1 >= 0:
        return False
    corner = math.tan(math.radians(hfov_deg) / 2) * math.hypot(1.0, height / width)
    peak = 2 / 3 * math.sqrt(-1 / (3 * k1))
    return corner > FOLD_MARGIN * peak


class _Draws:
    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def __call__(self, name: str) -> float:
        lo, hi = RANGES[name]
        if name in LOG_UNIFORM:
            return float(math.exp(self.rng.uniform(math.log(lo), math.log(hi))))
        return float(self.rng.uniform(lo, hi))

    def chance(self, p: float) -> bool:
        return bool(self.rng.random() < p)

    def choice(self, options):
        return options[int(self.rng.integers(len(options)))]


def draw(seed: int, index: int) -> SceneDraw:
    """Scene ``index`` of the suite of ``seed``: the same draw on any machine."""
    rng = np.random.default_rng([seed, index])
    u = _Draws(rng)
    found = None
    while found is None:  # pixels per cell and a view that some N fits
        found = _geometry(u)
    cells, cell_px, moving, (width, height), view = found
    profile = u.choice(PROFILE_NAMES)
    refresh = u.choice(REFRESH_HZ)
    flow = u("flow_px_per_ms") if moving else 0.0
    threshold_on = u("threshold")
    threshold_off = float(np.clip(threshold_on * math.exp(rng.uniform(-0.2, 0.2)), 0.12, 0.5))
    latency = u("latency_us")
    small = MarkerGeometry(cells).side * cell_px <= PWM_MAX_PX
    pwm = not moving and u.chance(PWM_SHARE) and small
    raw_bps = cells**2 * refresh / get_profile(profile).data_every
    lead_in = round(u("lead_in_s") * refresh)
    return SceneDraw(
        seed=seed,
        index=index,
        profile=profile,
        cells=cells,
        refresh_hz=refresh,
        cell_px=cell_px,
        width=width,
        height=height,
        flow_px_per_ms=flow,
        **view,
        rise_ms=u("rise_ms"),
        fall_ms=u("fall_ms"),
        scanout=u("scanout"),
        peak_nits=u("peak_nits"),
        contrast=u("contrast"),
        reflectance=u("reflectance"),
        pwm_hz=u("pwm_hz") if pwm else None,
        pwm_duty=u("pwm_duty") if pwm else 0.5,
        lux=u("lux"),
        threshold_on=threshold_on,
        threshold_off=threshold_off,
        threshold_sigma=u("threshold_sigma"),
        refractory_us=u("refractory_us"),
        leak_hz=u("leak_hz"),
        shot_hz=u("shot_hz"),
        latency_us=latency,
        jitter_us=latency * u("jitter_share"),
        max_rate_mev_s=u("max_rate_mev_s") if u.chance(0.5) else None,
        lead_in_refreshes=lead_in,
        lead_in_content=u.choice(LEAD_IN_CONTENTS),
        time_base_us=round(u("time_base_us")) if u.chance(0.8) else 0,
        # ``paper`` has no frame header: the page starts its stream when the marker appears.
        start_refresh=0 if profile == "paper" or u.chance(0.5) else int(rng.integers(1, 3000)),
        message_bytes=max(16, int(raw_bps * AFTER_S * MESSAGE_SHARE / 8)),
        sim_seed=int(rng.integers(2**31)),
    )


def _geometry(u: _Draws):
    """(cells, cell_px, moving, sensor, view fields of ``SceneDraw``), or None if nothing fits.

    Half the scenes draw pixels per cell first, then N among those whose marker fits the
    largest sensor at the drawn view; the other half draw N first, then pixels per cell up to
    what fits. Either alone leaves a corner thin (the first draws few large N, whose cells
    shrink to fit; the second few large cells). The sensor is then the smallest that fits."""
    n_first = u.chance(0.5)
    cells = int(u.choice(CELLS)) if n_first else 0
    cell_px = 0.0 if n_first else u("cell_px")
    moving = u.chance(HAND_HELD_SHARE)
    roll = u("roll_deg")
    view = u("view_deg")
    heading = u.rng.uniform(0, 2 * math.pi)
    tilt, elevation = view * math.cos(heading), view * math.sin(heading)
    hfov = u("hfov_deg")
    size = u("marker_size_m")
    k1, p1, p2 = u("k1"), u("tangential"), u("tangential")
    blur, vignetting = u("blur_px"), u("vignetting")
    fit = HAND_HELD_FIT if moving else STATIC_FIT

    def room(cells: int, cell_px: float, width: int, height: int) -> tuple[float, float]:
        """How many times over the marker fits the sensor (< 1: it does not), and its
        distance."""
        geo = MarkerGeometry(cells)
        cam = _camera(width, height, hfov, k1, p1, p2)
        distance = cam.K[0, 0] * geo.cell_size_m(size) / cell_px
        T = look_at(np.array([size / 2, size / 2, 0.0]), distance, tilt, elevation, roll)
        span = np.ptp(project_points(cam, T, geo.marker_corners(size)), axis=0)
        fits = float(np.min(fit * np.array([width, height]) / span))
        if moving:
            fits = min(fits, MOVING_MAX_PX / float(span.max()))
        return fits, distance

    lo, hi = RANGES["cell_px"]
    if n_first:  # the marker's extent scales about as its cells' pixels
        most = lo * room(cells, lo, *SENSORS[-1])[0]
        if most < lo:
            return None
        cell_px = float(math.exp(u.rng.uniform(math.log(lo), math.log(min(hi, most)))))
    else:
        feasible = [n for n in CELLS if room(n, cell_px, *SENSORS[-1])[0] >= 1.0]
        if not feasible:
            return None
        cells = int(u.choice(feasible))
    for width, height in SENSORS:
        fits, distance = room(cells, cell_px, width, height)
        if fits >= 1.0:
            if not 0.15 <= distance <= 5.0 or folds(width, height, hfov, k1):
                return None
            fields = {
                "hfov_deg": hfov,
                "k1": k1,
                "p1": p1,
                "p2": p2,
                "blur_px": blur,
                "vignetting": vignetting,
                "marker_size_m": size,
                "distance_m": distance,
                "roll_deg": roll,
                "view_deg": view,
                "tilt_deg": tilt,
                "elevation_deg": elevation,
            }
            return cells, cell_px, moving, (width, height), fields
    return None
