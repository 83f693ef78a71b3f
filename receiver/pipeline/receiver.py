"""The streaming receiver: detect -> track + decode -> (loss) -> detect again, without restarting.

``Receiver.push(chunk)`` takes an event chunk and returns what it produced: poses, read frames,
completed messages and state changes, in time order. The live daemon and the offline ``decode``
command share it. The stream decoder survives tracking losses, so symbols gathered before a loss
still count towards the message.
"""

from __future__ import annotations

import bisect
import logging
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from occ.stream import ReceivedMessage, StreamDecoder
from receiver.pipeline.buffer import EventBuffer
from receiver.pipeline.config import ReceiverConfig
from receiver.pipeline.decoder import CellReader, FrameRead
from receiver.pipeline.detector import MarkerNotFound, detect
from receiver.pipeline.filters import EventFilter
from receiver.pipeline.pose import pnp, project_ideal
from receiver.pipeline.tracker import EdgeTracker
from receiver.poses import invert

log = logging.getLogger(__name__)

DETECTING, TRACKING = "detecting", "tracking"


@dataclass(frozen=True)
class PoseEstimate:
    t_us: int
    T_world_cam: np.ndarray


@dataclass(frozen=True)
class FrameOutput:
    read: FrameRead
    accepted: bool
    """The inner locator was seen, so the bits went to the stream decoder."""


@dataclass(frozen=True)
class MessageOutput:
    t_us: int
    message: ReceivedMessage


@dataclass(frozen=True)
class StateChange:
    t_us: int
    state: str
    reason: str


Output = PoseEstimate | FrameOutput | MessageOutput | StateChange


@dataclass
class ReceiverStats:
    first_event_us: int | None = None
    last_event_us: int | None = None
    events: int = 0
    lock_times_us: list[int] = field(default_factory=list)
    losses: int = 0
    detection_failures: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    frames_read: int = 0
    frames_seen: int = 0
    pose_updates: int = 0
    cpu_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))


class Receiver:
    def __init__(self, config: ReceiverConfig, message_size: int | None = None) -> None:
        self.config = config
        cam = config.camera
        self.state = DETECTING
        self.stats = ReceiverStats()
        self.stream = StreamDecoder(
            profile=config.profile, cells=config.cells, message_size=message_size
        )
        self._filter = EventFilter(config.filters, cam.width, cam.height)
        keep = config.detector.window_us + 4 * int(config.frame_us)
        self._buffer = EventBuffer(cam.undistort_table, keep)
        self._next_attempt_us: int | None = None
        self._tracker: EdgeTracker | None = None
        self._reader: CellReader | None = None
        self._next_frame = 0
        self._missed = 0
        self._pose_t: list[int] = []
        self._pose_T: list[np.ndarray] = []
        self._last_pose_out = -(1 << 62)

    # --- public ------------------------------------------------------------------------------
    def push(self, chunk: np.ndarray) -> list[Output]:
        if not len(chunk):
            return []
        st = self.stats
        st.first_event_us = int(chunk["t"][0]) if st.first_event_us is None else st.first_event_us
        st.last_event_us = int(chunk["t"][-1])
        st.events += len(chunk)
        with self._cpu("filter"):
            events = self._buffer.append(self._filter(chunk))
        if not len(events):
            return []
        out: list[Output] = []
        if self.state == DETECTING:
            out += self._try_detect(int(events["t"][-1]))
            if self.state == TRACKING:  # track only what arrived after the detection window
                events = events[:0]
        if self.state == TRACKING:
            out += self._track(events)
        if self.state == TRACKING:
            out += self._decode(int(events["t"][-1]) if len(events) else st.last_event_us)
        return out

    def finish(self) -> list[Output]:
        """Flush at the end of a recording (nothing is pending in this design)."""
        return []

    # --- stages ------------------------------------------------------------------------------
    @contextmanager
    def _cpu(self, stage: str):
        t0 = time.process_time()
        try:
            yield
        finally:
            self.stats.cpu_s[stage] += time.process_time() - t0

    def _try_detect(self, now: int) -> list[Output]:
        span = self._buffer.span
        window = self.config.detector.window_us
        if self._next_attempt_us is None:
            self._next_attempt_us = span[0] + window
        if now < self._next_attempt_us:
            return []
        self._next_attempt_us = now + window
        with self._cpu("detect"):
            events = self._buffer.between(now - window, now + 1)
            try:
                found = detect(events, self.config)
                geo = self.config.geometry
                world = geo.locator_corners(self.config.marker_size_m)
                T = pnp(found.corners_px, world, self.config.camera)
            except (MarkerNotFound, ValueError) as exc:
                self.stats.detection_failures[str(exc)] += 1
                log.debug("detection at %d us: %s", now, exc)
                return []
        self._tracker = EdgeTracker(self.config, T)
        self._reader = CellReader(self.config, found.burst_us)
        # Frames inside the detection window are still buffered: read them too.
        self._next_frame = -int(window // self.config.frame_us) + 1
        self._missed = 0
        self._pose_t, self._pose_T = [now], [T]
        self.state = TRACKING
        self.stats.lock_times_us.append(now)
        return [StateChange(now, TRACKING, "marker detected"), self._pose_output(now, T)]

    def _lose(self, now: int, reason: str) -> list[Output]:
        log.info("tracking lost at %d us: %s", now, reason)
        self.state = DETECTING
        self.stats.losses += 1
        self._tracker = self._reader = None
        self._next_attempt_us = now + self.config.detector.window_us  # a fresh window of events
        return [StateChange(now, DETECTING, reason)]

    def _track(self, events: np.ndarray) -> list[Output]:
        out: list[Output] = []
        if len(events):
            with self._cpu("track"):
                updates = self._tracker.push(events["xu"], events["yu"], events["t"])
            for u in updates:
                self.stats.pose_updates += 1
                self._pose_t.append(u.t_us)
                self._pose_T.append(u.T_cam_world)
                out.append(self._pose_output(u.t_us, u.T_cam_world))
            now = int(events["t"][-1])
            if now - self._last_pose_out >= self.config.pose_interval_us:
                out.append(self._pose_output(now, self._tracker.T_cam_world))
            reason = self._out_of_view(self._tracker.T_cam_world)
            if reason:
                return out + self._lose(now, reason)
        self._trim_poses()
        return out

    def _out_of_view(self, T_cam_world: np.ndarray) -> str | None:
        geo, cam = self.config.geometry, self.config.camera
        px = project_ideal(T_cam_world, cam.K, geo.locator_corners(self.config.marker_size_m))
        if not np.all(np.isfinite(px)):
            return "marker behind the camera"
        centre = px.mean(axis=0)
        if not (0 <= centre[0] < cam.width and 0 <= centre[1] < cam.height):
            return "marker left the field of view"
        return None

    def _decode(self, now: int) -> list[Output]:
        out: list[Output] = []
        reader = self._reader
        q = self.config.decoder
        while self.state == TRACKING and reader.window(self._next_frame)[1] <= now:
            m = self._next_frame
            self._next_frame += 1
            with self._cpu("decode"):
                t0, t1 = reader.window(m)
                events = self._buffer.between(t0, t1)
                read = reader.read(m, events, self.pose_at)
            self.stats.frames_read += 1
            seen = read.locator_score >= q.min_locator_score
            out.append(FrameOutput(read, seen))
            if not seen:
                self._missed += 1
                if self._missed >= q.lost_after_frames:
                    out += self._lose(now, "inner locator not seen in the last frames")
                continue
            self._missed = 0
            self.stats.frames_seen += 1
            with self._cpu("stream"):
                messages = self.stream.push(read.bits, read.confidence)
            out += [MessageOutput(read.t_us, msg) for msg in messages]
        return out

    # --- poses -------------------------------------------------------------------------------
    def pose_at(self, t_us: float) -> np.ndarray:
        """T_cam_world in effect at ``t_us`` (the latest update not after it)."""
        i = bisect.bisect_right(self._pose_t, t_us) - 1
        return self._pose_T[max(i, 0)]

    def _trim_poses(self) -> None:
        span = self._buffer.span
        if span and len(self._pose_t) > 64 and self._pose_t[32] < span[0]:
            del self._pose_t[:32], self._pose_T[:32]

    def _pose_output(self, t_us: int, T_cam_world: np.ndarray) -> PoseEstimate:
        self._last_pose_out = t_us
        return PoseEstimate(t_us, invert(T_cam_world))
