"""A closed link simulated end to end, offline: a screen whose settings can change mid-message,
the virtual event camera watching it, a receiver rebuilt for each change (keeping its fountain
progress), and a controller choosing the settings from the receiver's frame reports.

Event time is the only clock: the controller sees each report as the server would, at the
event time it was made, so the run does not depend on how fast this machine simulates.

``LoopScene`` says what the camera sees (screen, distance, motion, sensor); ``run_link`` plays
one message through it, at fixed settings or under a ``LinkPolicy``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import astuple, dataclass, field

import numpy as np

from eventocc.occ.link_policy import (
    FrameSample,
    LinkChoice,
    LinkMeter,
    LinkPolicy,
    start_choice,
)
from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.live.link_quality import FlowMeter, frame_quality
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.receiver import FrameOutput, MessageOutput, PoseEstimate, Receiver
from eventocc.receiver.sim import (
    Display,
    HandHeldMotion,
    Optics,
    Scene,
    SensorModel,
    StaticMotion,
    simulate,
)
from eventocc.receiver.sim.sensor import PRESETS as SENSOR_PRESETS

CHUNK_US = 5_000
DECIDE_EVERY_US = 50_000
"""How often the controller looks at the reports (the page asks the server 4 times a second;
the simulated loop decides a little more often, as a server does on every report)."""


@dataclass(frozen=True)
class LoopScene:
    """What the camera sees: a marker the transmitter page fits to ``screen_m`` (the whole
    marker's side, whatever its N), from ``distance_m``, still or hand-held."""

    distance_m: float
    handheld: bool = False
    flow_px_per_ms: float = 1.0
    """Hand-held: the marker's mean image speed."""
    screen_m: float = 0.36
    camera: CameraModel = field(default_factory=CameraModel.paper)
    preset: str = "evk4"
    display_hz: float = 60.0
    seed: int = 0
    distance_after: tuple[float, float] | None = None
    """(event time s, distance m): the camera is carried to another distance at that time
    (a still camera; the move itself is not simulated, the next segment starts there)."""

    def marker_size_m(self, cells: int) -> float:
        """The white ring's side when the whole marker is ``screen_m`` across."""
        geo = MarkerGeometry(cells)
        return self.screen_m * geo.tracked_side / geo.side

    def distance_at(self, t_s: float) -> float:
        if self.distance_after is not None and t_s >= self.distance_after[0]:
            return self.distance_after[1]
        return self.distance_m

    def px_per_cell(self, cells: int, t_s: float = 0.0) -> float:
        """Pixels per cell square-on at the marker centre (the scene's design figure)."""
        geo = MarkerGeometry(cells)
        return self.camera.K[0, 0] * self.screen_m / geo.side / self.distance_at(t_s)

    @property
    def sensor_preset(self) -> str:
        """The preset's variant for a moving camera where it has one (``evk4-moving``: the
        simulator's moving renderer has no photoreceptor low-pass)."""
        moving = f"{self.preset}-moving"
        return moving if self.handheld and moving in SENSOR_PRESETS else self.preset

    def readout_events_per_s(self) -> float | None:
        sensor = SensorModel.preset(self.sensor_preset)
        caps = [c for c in (sensor.readout_hz, sensor.erc_hz, sensor.link_hz) if c]
        return min(caps) if caps else None

    def scene(
        self, encoder: StreamEncoder, hold: int, t_us: int, path_s: float, start_refresh: int = 0
    ) -> Scene:
        distance = self.distance_at(t_us / 1e6)
        motion = (
            HandHeldMotion(distance, self.flow_px_per_ms, seed=self.seed, start_s=path_s)
            if self.handheld
            else StaticMotion(distance)
        )
        return Scene(
            encoder=encoder,
            marker_size_m=self.marker_size_m(encoder.geometry.cells),
            camera=self.camera,
            motion=motion,
            display=Display(refresh_hz=self.display_hz / hold),
            sensor=SensorModel.preset(self.sensor_preset),
            optics=Optics.preset(self.sensor_preset),
            time_base_us=t_us,
            start_refresh=start_refresh,
            seed=self.seed,
        )


@dataclass
class Segment:
    """The settings on screen from ``t_s`` on, and why the controller chose them."""

    t_s: float
    choice: LinkChoice
    reason: str


@dataclass
class LinkRun:
    segments: list[Segment]
    duration_s: float
    message_done_s: float | None
    """Event time the message came out verified (None: it did not)."""
    message_ok: bool
    """It came out equal to the bytes sent (and nothing else came out)."""
    verified_bits: list[tuple[float, int]]
    """(event time s, payload bits) of every frame whose code and CRC passed."""
    first_read_s: float | None
    events: int

    def goodput_bps(self, start_s: float, end_s: float | None = None) -> float:
        """Verified payload bits per second over [start_s, end_s)."""
        end = self.duration_s if end_s is None else end_s
        bits = sum(b for t, b in self.verified_bits if start_s <= t < end)
        return bits / (end - start_s) if end > start_s else 0.0


def run_link(
    loop: LoopScene,
    message: bytes,
    duration_s: float,
    *,
    fixed: LinkChoice | None = None,
    policy: LinkPolicy | None = None,
    realtime_margin: Callable[[], float | None] = lambda: None,
    stop_when_done: bool = False,
    min_s: float = 0.0,
) -> LinkRun:
    """Play ``message`` for ``duration_s`` of event time: at ``fixed`` settings (as the fixed
    mode sends, unpacked), or under ``policy`` (packed, from ``start_choice``), the receiver
    rebuilt at each change and keeping its progress. ``stop_when_done``: stop once the message
    is out and ``min_s`` has passed."""
    if (fixed is None) == (policy is None):
        raise ValueError("give fixed settings or a policy")
    choice = fixed if fixed is not None else start_choice(loop.display_hz)
    packed = policy is not None
    segments = [Segment(0.0, choice, "fixed" if fixed else "start")]
    t_us, symbol_start, start_refresh, path_s = 0, 0, 0, 0.0
    receiver: Receiver | None = None
    verified: list[tuple[float, int]] = []
    done_s, ok, first_read, events = None, True, None, 0
    end_us, min_us = round(duration_s * 1e6), round(min_s * 1e6)
    readout = loop.readout_events_per_s()

    def done() -> bool:
        return stop_when_done and done_s is not None and t_us >= min_us

    while t_us < end_us and not done():
        enc = StreamEncoder(
            message,
            name="closed-loop.bin",
            profile=choice.profile,
            cells=choice.cells,
            packed=packed,
            symbol_start=symbol_start,
        )
        scene = loop.scene(enc, choice.hold, t_us, path_s, start_refresh)
        receiver = _rebuilt(receiver, loop, scene, choice)
        flow = FlowMeter(loop.camera, scene.marker_size_m)
        meter = LinkMeter(choice, loop.display_hz, t_us / 1e6)
        segment_start = t_us
        segment_end = min(end_us, _move_time_us(loop, t_us))
        change: tuple[LinkChoice, str] | None = None
        recording = simulate(scene, (segment_end - segment_start) / 1e6, CHUNK_US)
        for i, chunk in enumerate(recording):
            t_us = min(segment_start + (i + 1) * CHUNK_US, segment_end)
            events += len(chunk)
            rate = len(chunk) / (CHUNK_US / 1e6)
            for out in receiver.push(chunk):
                if isinstance(out, PoseEstimate):
                    flow.add(out)
                elif isinstance(out, FrameOutput):
                    t_s = out.read.t_us / 1e6
                    first_read = first_read if first_read is not None else t_s
                    if out.payload_bits:
                        verified.append((t_s, out.payload_bits))
                    q = frame_quality(
                        out,
                        px_per_cell=receiver.cell_px,
                        events_per_s=rate,
                        readout_events_per_s=readout,
                        flow_px_per_ms=flow.px_per_ms,
                        realtime_margin=realtime_margin(),
                    )
                    meter.add(FrameSample(t_s, *astuple(q)))
                elif isinstance(out, MessageOutput):
                    ok = ok and done_s is None and out.message.data == message
                    done_s = done_s if done_s is not None else out.t_us / 1e6
            if done():
                break
            if policy is not None and t_us % DECIDE_EVERY_US == 0:
                now = t_us / 1e6
                decision = policy.decide(
                    choice, meter.window(now), meter.window(now, policy.config.loss_window_s), now
                )
                if decision.changed:
                    change = (decision.choice, decision.reason)
                    break
        shown_us = t_us - segment_start
        path_s += shown_us / 1e6
        refreshes = round(shown_us * loop.display_hz / choice.hold / 1e6)
        # The page goes on where it was: a new packed segment from the next unsent symbol, the
        # fixed stream from its next refresh (after the camera was carried elsewhere).
        symbol_start = enc.symbol_end(refreshes) if packed else 0
        start_refresh = 0 if packed else start_refresh + refreshes
        if change is not None:
            choice = change[0]
            segments.append(Segment(t_us / 1e6, choice, change[1]))
    ok = ok and done_s is not None
    return LinkRun(segments, t_us / 1e6, done_s, ok, verified, first_read, events)


def _move_time_us(loop: LoopScene, t_us: int) -> int:
    if loop.distance_after is None:
        return 1 << 62
    at = round(loop.distance_after[0] * 1e6)
    return at if at > t_us else 1 << 62


def _rebuilt(older: Receiver | None, loop: LoopScene, scene: Scene, choice: LinkChoice) -> Receiver:
    """A receiver for the new settings that keeps what the last one collected."""
    if (
        older is not None
        and older.config.cells == choice.cells
        and older.config.profile == choice.profile
        and older.config.refresh_hz == loop.display_hz / choice.hold
    ):
        return older
    receiver = Receiver(
        ReceiverConfig(
            loop.camera,
            cells=choice.cells,
            profile=choice.profile,
            refresh_hz=loop.display_hz / choice.hold,
            marker_size_m=scene.marker_size_m,
        )
    )
    if older is not None:
        receiver.stream.adopt(older.stream)
    return receiver


def random_message(size: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
