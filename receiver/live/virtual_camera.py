"""The virtual event camera as a live source: it watches what the server's transmitter plays.

It asks the server which message, profile, cell count and frame the transmitter page shows,
fetches that message, and simulates an event camera watching that screen in real time, so the
whole loop (upload -> transmitter -> camera -> receiver -> dashboard) closes without hardware.
When the transmitter switches to another message the simulation restarts on it (and ``link``
tells the daemon the new link settings). Until a transmitter page reports, the camera watches
its stand-in message (``sim:MESSAGE_ID``; ``sim:`` alone: the newest upload) from its first
frame, as if a page were showing it. A paused page holds one still frame and a closed one
shows nothing: the camera then sees no events, and ``waiting`` says why.

The simulation runs in a child process (``SimulatorProcess``), a few packets ahead, so that on
two cores the simulator and the receiver pipeline work side by side. The camera stays live:
when the simulation runs slower than real time, it does not fall ever further behind the
screen; once ``MAX_LAG_S`` late it skips ahead to what the screen shows now, says so in the
log, and reports its ``speed``.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import queue
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol

import numpy as np

from eventocc.occ.profiles import LinkSettings
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.events import empty_events
from eventocc.receiver.live.screen import Idle, Showing, StatusError, TransmitterClient
from eventocc.receiver.live.sources import MAX_LAG_S, BehindNote, LiveClock, SourceError

if TYPE_CHECKING:
    from eventocc.receiver.sim import Scene

log = logging.getLogger(__name__)

MOTIONS = ("static", "handheld")
DEFAULT_MOTION = "handheld"
"""The demo's camera: a gentle hand, so the dashboard shows the pose move. The moving camera's
simulation runs below real time on one core, so the camera skips ahead now and then; its path
goes on where it was, so the receiver keeps its lock across the gap."""
WAIT_S = 1.0
"""How often to ask again while there is nothing to watch."""
DISTANCE_M = 0.6
"""Camera to marker centre: about 5 pixels per cell on the default sensor, the 0.272 m marker
filling a quarter of the view's width (a hand-held phone's distance)."""
HANDHELD_FLOW_PX_PER_MS = 0.05
"""A gentle hand: the marker drifts ~50 px/s across the 320 px sensor."""
SIMULATOR_TIMEOUT_S = 120.0
"""Longest wait for the simulator's next packet (its first one compiles the kernels)."""


def default_camera() -> CameraModel:
    """The paper camera's whole view on a quarter of its pixels (320x180, binned): with the
    sensor below, the marker makes about 1 M events/s, so the simulator and the pipeline keep
    close to real time on one core. Binned, not cropped: a crop sees the marker from 2.5 m
    through a 17-degree view, nearly without perspective, and a moving camera's pose then
    flips between the two tilts that look alike (median position error 15-50 cm, excursions
    of 1-2 m, against 0.6 cm binned at 0.6 m)."""
    return CameraModel.paper().binned(320, 180)


def virtual_sensor():
    from eventocc.receiver.sim import SensorModel

    # Coarser contrast steps and a refractory period than the ideal sensor: ~5x fewer events
    # per refresh, still a few per cell edge, which is all the receiver needs.
    return replace(
        SensorModel.preset("ideal"), threshold_on=1.0, threshold_off=1.0, refractory_us=200.0
    )


class Simulator(Protocol):
    def watch(self, scene) -> Iterator[np.ndarray]:
        """The events of ``scene`` from its start, endlessly, in ``chunk_us`` packets."""
        ...

    def close(self) -> None: ...


class SimulatorInThread:
    """The simulation in the caller's thread: it shares a core with the receiver pipeline."""

    def __init__(self, chunk_us: int) -> None:
        self.chunk_us = chunk_us

    def watch(self, scene) -> Iterator[np.ndarray]:
        from eventocc.receiver.sim import simulate

        return iter(simulate(scene, duration_s=24 * 3600, chunk_us=self.chunk_us))

    def close(self) -> None:
        pass


class SimulatorProcess:
    """The simulation in a child process, so that on two cores it runs beside the receiver
    pipeline: it simulates the next packet while the camera hands out this one (a pipe holds
    about one packet, which paces it).

    One process for the camera's life (it compiles the kernels once): each ``watch`` sends it a
    new scene, and packets of the scene it was on are dropped on arrival.
    """

    def __init__(self, chunk_us: int) -> None:
        context = multiprocessing.get_context("spawn")  # no fork of a threaded daemon
        self._chunks, chunks_end = context.Pipe(duplex=False)
        scenes_end, self._scenes = context.Pipe(duplex=False)
        self._process = context.Process(
            target=_simulate_scenes,
            args=(scenes_end, chunks_end, chunk_us),
            name="eventocc-simulator",
            daemon=True,
        )
        self._process.start()
        # Only the child holds these ends now: its death reads as end-of-file, never a hang.
        chunks_end.close()
        scenes_end.close()
        self._scene_number = 0
        # Scenes go out from their own thread: a large message does not fit the pipe, and the
        # child may be waiting for us to take a packet before it reads the scene.
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._send_scenes, name="eventocc-scenes", daemon=True).start()

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def watch(self, scene) -> Iterator[np.ndarray]:
        self._scene_number += 1
        number = self._scene_number
        self._outbox.put((number, scene.describe()))  # a Scene holds unpicklable parts
        while (packet := self._next()) is not None:
            arrived, events = packet
            if arrived == number:
                yield events

    def _send_scenes(self) -> None:
        try:
            while (job := self._outbox.get()) is not None:
                self._scenes.send(job)
        except OSError:
            pass  # the child is gone: ``_next`` says why
        finally:
            self._scenes.close()

    def _next(self) -> tuple[int, np.ndarray] | None:
        """The next packet; None once the process was stopped by a signal (the camera ends)."""
        deadline = time.monotonic() + SIMULATOR_TIMEOUT_S
        while not self._chunks.poll(1.0):
            if time.monotonic() > deadline:
                raise SourceError(f"the simulator sent nothing for {SIMULATOR_TIMEOUT_S:.0f} s")
        try:
            return self._chunks.recv()
        except (EOFError, OSError):  # OSError: it died in the middle of sending a packet
            self._process.join(5)
        code = self._process.exitcode
        if code is not None and code < 0:  # e.g. SIGTERM to the daemon's process group
            log.warning("the simulator process was stopped by signal %d", -code)
            return None
        raise SourceError(f"the simulator process died (exit code {code}); its error is above")

    def close(self) -> None:
        """Stop the process: it holds nothing that needs a graceful end."""
        self._outbox.put(None)
        self._process.terminate()
        self._process.join(5)
        self._chunks.close()


def _simulate_scenes(scenes, chunks, chunk_us: int) -> None:
    """The simulator process: simulate each scene sent until the next one comes."""
    from eventocc.receiver.sim import Scene, simulate

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the daemon, which stops us
    try:
        job = scenes.recv()
        while job is not None:
            number, description = job
            job = None
            for events in simulate(Scene.from_dict(description), 24 * 3600, chunk_us):
                chunks.send((number, events))  # waits while the camera holds the last one
                if scenes.poll():  # the screen changed: on to the new scene
                    job = scenes.recv()
                    break
    except (EOFError, BrokenPipeError):
        pass  # the camera is gone


class VirtualCamera:
    def __init__(
        self,
        server_url: str,
        *,
        stand_in: str | None = None,
        camera: CameraModel | None = None,
        motion: str = DEFAULT_MOTION,
        chunk_us: int = 5_000,
        check_every_s: float = 1.0,
        seed: int = 0,
        clock: LiveClock | None = None,
        simulator: Simulator | None = None,
    ) -> None:
        """``stand_in``: the message watched until a transmitter page reports (None: the
        newest upload). ``simulator`` defaults to a ``SimulatorProcess``, started on the first
        ``chunks``."""
        self.server = TransmitterClient(server_url, who="the virtual camera", stand_in=stand_in)
        if motion not in MOTIONS:
            raise SourceError(f"unknown motion {motion!r}; choose one of {', '.join(MOTIONS)}")
        self.camera = camera or default_camera()
        self.width, self.height = self.camera.width, self.camera.height
        self.motion = motion
        self.chunk_us = chunk_us
        self.check_every_s = check_every_s
        self.seed = seed
        self.clock = clock or LiveClock()
        self.simulator = simulator
        self.link: LinkSettings | None = None
        """The link settings of the stream being simulated (the daemon follows them)."""
        self.speed: float | None = None
        """Simulated seconds per wall-clock second over the last ``check_every_s`` simulated
        (1.0: keeping up; None: nothing to watch)."""
        self.skips = 0
        """Times the camera skipped ahead because the simulation fell behind the screen."""
        self.waiting: str | None = None
        """Why the camera sees nothing now (None while it watches a message)."""
        self._watching: Showing | None = None
        self._timeline: tuple[int, int, float] | None = None
        """(event time, frame, period in us) of the stream watched: frame k is on screen from
        ``time + (k - frame) * period``."""
        self._encoder: tuple[Showing, StreamEncoder] | None = None
        self._last_t = -1
        self._path_us = 0
        """Time the camera has moved along its path: the simulated time, skips left out."""
        self._behind_note = BehindNote(
            "virtual camera", "the simulation cannot keep up with the screen"
        )

    def encoder(self, showing: Showing) -> StreamEncoder:
        """The stream's encoder, fetched once per stream (a skip ahead reuses it)."""
        if self._encoder is not None and self._encoder[0].same_stream(showing):
            return self._encoder[1]
        name, data = self.server.message(showing.message_id)
        link = showing.link
        encoder = StreamEncoder(
            data,
            name=name,
            profile=link.profile,
            cells=link.cells,
            packed=showing.packed,
            symbol_start=showing.symbol_start,
        )
        self._encoder = (showing, encoder)
        return encoder

    # --- simulating ---

    def scene(self, encoder: StreamEncoder, showing: Showing) -> Scene:
        from eventocc.receiver.sim import Display, HandHeldMotion, Scene, StaticMotion

        motion = (
            # The hand carries on where it was, across skips ahead and new messages alike.
            HandHeldMotion(
                distance_m=DISTANCE_M,
                flow_px_per_ms=HANDHELD_FLOW_PX_PER_MS,
                seed=self.seed,
                start_s=self._path_us / 1e6,
            )
            if self.motion == "handheld"
            else StaticMotion(distance_m=DISTANCE_M)
        )
        return Scene(
            encoder=encoder,
            start_refresh=showing.frame_now,
            motion=motion,
            camera=self.camera,
            sensor=virtual_sensor(),
            display=Display(refresh_hz=showing.refresh_hz),
            seed=self.seed,
        )

    def chunks(self) -> Iterator[np.ndarray]:
        """Endless: simulated events of whatever the transmitter shows, at real-time pace.

        While nothing plays it yields an empty chunk every ``WAIT_S``: a heartbeat, so the
        daemon keeps reporting its health.
        """
        if self.simulator is None:
            self.simulator = SimulatorProcess(self.chunk_us)
        try:
            yield from self._follow_the_screen()
        finally:
            self.simulator.close()

    def _follow_the_screen(self) -> Iterator[np.ndarray]:
        while True:
            watching = self._scene_to_watch()
            if watching is None:
                self.speed = None
                yield empty_events()
                time.sleep(WAIT_S)
                continue
            scene, showing, t_offset = watching
            if self._watching is None or not showing.same_stream(self._watching):
                log.info(
                    "virtual camera watching message %s (%s, %d cells, %.1f Hz) from frame %d",
                    showing.message_id,
                    showing.link.profile,
                    showing.link.cells,
                    showing.refresh_hz,
                    showing.frame_now,
                )
            self._watching, self.link = showing, showing.link
            yield from self._watch(scene, showing, t_offset)

    def _scene_to_watch(self) -> tuple[Scene, Showing, int] | None:
        """The scene of what the transmitter shows, the showing from where the camera resumes
        and that frame's event time; None while there is nothing the camera can watch."""
        showing = self._something_to_watch()
        if showing is None:
            return None
        showing, t_offset = self._resume(showing)
        try:
            scene = self.scene(self.encoder(showing), showing)
        except OSError as error:
            return self._wait(f"cannot fetch message {showing.message_id} ({error})")
        except (LookupError, ValueError) as error:  # gone, or no encoder takes it
            return self._wait(f"cannot show message {showing.message_id}: {error}")
        self.waiting = None
        return scene, showing, t_offset

    def _resume(self, showing: Showing) -> tuple[Showing, int]:
        """Where to start simulating ``showing``: the frame on screen and the event time of its
        start. One clock across restarts, tied to the wall clock at the first chunk (that one
        pays for compiling the simulator and is not late). After a skip ahead within the same
        stream the screen's own timeline goes on, as it does for a real camera that dropped
        events: frame k keeps its time, so the receiver's frame clock stays right."""
        now = max(self.clock.now_us(), self._last_t + 1) if self.clock.started else 0
        same = self._watching is not None and showing.same_stream(self._watching)
        if self._timeline is None or not same:
            self._timeline = (now, showing.frame_now, 1e6 / showing.refresh_hz)
            return showing, now
        t0, first, period = self._timeline
        k = math.ceil((now - t0) / period)
        return replace(showing, frame_now=first + k), round(t0 + k * period)

    def _watch(self, scene, showing: Showing, t_offset: int) -> Iterator[np.ndarray]:
        """The scene's events from ``t_offset`` on, until the stream changes or the camera
        falls ``MAX_LAG_S`` behind the screen."""
        window_us, late_before = 0, 0.0  # simulated time and lateness at the window's start
        for events in self.simulator.watch(scene):
            events["t"] += t_offset
            late_s = 0.0
            if len(events):
                self._last_t = int(events["t"][-1])
                if not self.clock.started:
                    self.clock.start(self._last_t)
                late_s = self.clock.wait(self._last_t)
            window_us += self.chunk_us
            self._path_us += self.chunk_us
            yield events
            if late_s > MAX_LAG_S:
                self.speed = _speed(window_us, late_s - late_before)
                self.skips += 1
                self._behind_note.skipped(self.speed)
                return
            if window_us >= self.check_every_s * 1e6:
                self.speed = _speed(window_us, late_s - late_before)
                self._behind_note.measured(self.speed)
                window_us, late_before = 0, late_s
                now = self._something_to_watch()
                if now is None or not now.same_stream(showing):
                    return

    def _something_to_watch(self) -> Showing | None:
        """``showing()``, or None with the reason: the camera waits for something it can watch."""
        try:
            showing = self.server.showing()
        except OSError as error:
            return self._wait(f"server unreachable ({error})")
        except StatusError as error:
            return self._wait(str(error))
        if isinstance(showing, Idle):
            return self._wait(showing.reason, logging.INFO)
        return showing

    def _wait(self, reason: str, level: int = logging.WARNING) -> None:
        """Say once why the camera waits (until it watches something again)."""
        if reason != self.waiting:
            log.log(level, "virtual camera waiting: %s", reason)
        self.waiting = reason


def _speed(simulated_us: int, later_by_s: float) -> float:
    """Simulated per wall-clock time: the wall time spent is the simulated time plus how much
    later than the screen the camera got meanwhile (on time, ``LiveClock`` sleeps: 1.0)."""
    return simulated_us / (simulated_us + max(later_by_s, 0.0) * 1e6)
