"""The streaming receiver: detect -> track + decode -> (loss) -> detect again, without restarting.

``Receiver.push(chunk)`` takes an event chunk and returns what it produced: poses, read frames,
completed messages and state changes, in time order but for the poses, which come once the
updates after them have smoothed them (``ReceiverConfig.orientation_smoothing_us``, 15 ms).
The live daemon and the offline ``decode`` command share it. The stream decoder survives tracking
losses, so symbols gathered before a loss still count towards the message.

Detection attempts are spaced in event time (``DetectorParams.retry_us``), so a recording decodes
the same on any machine; only a real-time source also spaces them by their CPU cost. A detection
becomes a lock only once the frames still buffered verify it (``Receiver._unverified``; under
motion the frames after the detected burst's, waited for if need be: ``Receiver._postpone``). While
tracking, a lock is dropped when the tracker leaves the ring's edges, an outer edge stays silent
while the motion sweeps it (``EdgeTracker.contradicted``) or fires against it
(``EdgeTracker.reversed_edges``: a side fitted a ring width off), the marker leaves the view,
the inner locator goes unseen for several frames, or its 'L' reads upright barely better than
turned (``Track.misturned``): a pose a quarter turn off passes every other check. Some wrong
poses read the 'L' well all the same, so a lock stays unproven until one of its frames passes
its check (CRC; ``paper``: its 'L' read clearly), the first one while the ring's swept edges
fire with the motion (``Track.sides_agree``; a lock made under motion: every side since), and is
on probation meanwhile (a few frames for a still camera, more under motion:
``Track.failed_probation``). A proof lapses when no frame has passed for a while
(``DecoderParams.proof_lapse_us``), and the lock goes with it.
Poses outside a proof come out tentative (``PoseEstimate.verified`` false).

Only one stage touches every event while the marker is tracked: the compiled triage
(``triage.EventTriage``), which keeps each pixel's latest burst times for the decoder and hands
the tracker the events near its edges. Detection reads the buffered raw chunks of its window;
nothing copies or undistorts the whole stream.

Nothing depends on where the source cut a time-sorted stream into chunks (a camera's driver, a
file reader and the simulator all cut it differently): detection runs at scheduled event times on
the events before them, and tracking takes the stream in pieces cut on a fixed grid of event
time, each processed once an event at or after its end has arrived. At most one piece (2 ms)
waits for the next chunk; ``finish`` processes it at the end of a recording.
"""

from __future__ import annotations

import logging
import math
import time
from collections import defaultdict, deque
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from eventocc.occ.profiles import get_profile
from eventocc.occ.stream import ReceivedMessage, StreamDecoder
from eventocc.receiver.pipeline.buffer import EventBuffer, to_columns
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.decoder import (
    CellReader,
    FrameRead,
    cell_side_px,
    on_events_per_pixel,
    read_stride,
)
from eventocc.receiver.pipeline.detector import (
    Detection,
    MarkerNotFound,
    detect,
    nearest_turn,
    recheck_still,
)
from eventocc.receiver.pipeline.filters import EventFilter
from eventocc.receiver.pipeline.pose import PoseHistory, pnp, project_ideal
from eventocc.receiver.pipeline.smoothing import PoseSmoother
from eventocc.receiver.pipeline.tracker import EdgeTracker
from eventocc.receiver.pipeline.triage import EventTriage
from eventocc.receiver.poses import invert

log = logging.getLogger(__name__)

DETECTING, TRACKING = "detecting", "tracking"
_SEGMENT_US = 2000
"""Period of the event-time grid that tracking cuts the stream on: each piece is triaged with one
tracker mask (the edges move little meanwhile)."""
_DENSITY_BLINKS = 4
"""Blinks before the lock whose events tell how densely the marker's pixels fire
(``decoder.on_events_per_pixel``)."""


@dataclass(frozen=True)
class PoseEstimate:
    t_us: int
    T_world_cam: np.ndarray
    verified: bool = False
    """A frame proved the lock around the pose, on corners the receiver trusts
    (``Track.publishes_verified``); otherwise the pose is tentative: a wrong lock can look right
    to every other check."""


@dataclass(frozen=True)
class FrameOutput:
    read: FrameRead
    accepted: bool
    """The inner locator was seen, so the bits went to the stream decoder."""
    payload_bits: int = 0
    """Payload bits the stream decoder verified in this frame (``StreamDecoder.verified_bits``)."""
    corrected: np.ndarray | None = None
    """(cells, cells) bool: the cells whose bits the frame's Reed-Solomon code corrected; None
    if it did not decode or was not decoded (``StreamDecoder.corrected``)."""


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


@dataclass
class Track:
    """What one lock holds: made at the lock (``Receiver._lock``), dropped at its end."""

    tracker: EdgeTracker
    reader: CellReader
    next_frame: int
    """The next frame to read; negative for the frames still buffered from before a still lock."""
    moving: bool
    """The lock came from a burst under motion: its frame 0 (the burst's) only times the frame
    clock, and its proof needs every side of the ring seen firing with the motion."""
    late_mark: bool
    """Whether frames keep each pixel's first burst after their window's middle too
    (``DecoderParams.late_mark_px_per_cell``)."""
    probation: int | None
    """Frames with the locator seen left for the lock to be proven (``failed_probation``);
    None: no limit."""
    turn_leads: deque[float]
    """The latest read frames' leads of the locator's canonical turn (``misturned``)."""
    lapse_us: float | None
    """How long a proof holds (``DecoderParams.proof_lapse_us``); None: for good."""
    rechecked: list[np.ndarray] = field(default_factory=list)
    """Since the camera last moved, the corners refined to the locator's edges that the lock's
    detection and the rechecks found (``Receiver._recheck_still``)."""
    recheck_us: int | None = None
    """When a still lock's pose is next taken again from a fresh window
    (``Receiver._recheck_still``); None: never (a lock under motion)."""
    outline_until_us: float = -math.inf
    """A still lock's pose came from outline corners, not refined ones: its poses before this
    time go out unverified, and it is infinite until the first recheck has taken the pose again
    (``Receiver._recheck_still``)."""
    updates_seen: int = 0
    """The receiver's pose updates at the last recheck: more since, and the camera moved."""
    missed: int = 0
    """Frames in a row without the inner locator."""
    proven_at_us: int | None = None
    """Time of the latest frame that proved the lock: it passed its check (CRC, framed
    profiles) or, for ``paper`` (no check of its own), ended a run of frames that read the
    locator's 'L' upright (``upright``), while the ring's sides agreed (``sides_agree``).
    None: unproven so far."""

    def verified_at(self, t_us: int) -> bool:
        """Whether a pose at ``t_us`` comes out verified: a proof before it holds then, or one
        came after it (the lock's buffered frames prove the poses before them)."""
        if self.proven_at_us is None:
            return False
        return self.lapse_us is None or t_us - self.proven_at_us <= self.lapse_us

    def publishes_verified(self, t_us: int) -> bool:
        """Whether the pose at ``t_us`` goes out verified: proven then (``verified_at``) and not
        held on outline corners (``outline_until_us``)."""
        return t_us >= self.outline_until_us and self.verified_at(t_us)

    def failed_probation(self, frame: FrameOutput) -> bool:
        """Whether the lock must go after ``frame`` (locator seen, check failed or passed): an
        unproven one has read its last frame on probation, a proven one's proof has lapsed."""
        if self.proven_at_us is not None:
            return not self.verified_at(frame.read.t_us)
        if self.probation is None:
            return False
        self.probation -= 1
        return self.probation == 0

    def upright(self, min_lead: float) -> bool:
        """Whether each of the last ``turn_frames`` frames read the 'L' upright by ``min_lead``
        (``min_proof_lead``): ``paper``'s proof, as it has no check of its own, with
        ``sides_agree``. One frame is not enough: under motion a pose a quarter turn off reads
        one now and then."""
        leads = self.turn_leads
        return len(leads) == leads.maxlen and min(leads) >= min_lead

    def sides_agree(self, min_edge_agreement: float, every_side: bool) -> bool:
        """Whether the ring's swept outer edges last fired as the motion makes them, each
        agreeing at ``min_edge_agreement`` or better (``EdgeTracker.agreement``), and, with
        ``every_side``, each outer edge has so fired since the lock. A lock's first proof needs
        it: a pose a ring width off on a side, or skewed across a corner, reads the 'L' as the
        truth, and a frame's CRC can pass at a pose a few degrees off. Under motion detection
        places a side the motion runs along by the little that fires there, and only a later
        sweep shows it: a lock made under motion waits for ``every_side``."""
        tracker = self.tracker
        if np.any(tracker.agreement < min_edge_agreement):
            return False
        return not every_side or bool(np.all(tracker.best_agreement[:4] >= min_edge_agreement))

    def misturned(self, read: FrameRead, min_turn_lead: float) -> bool:
        """Record ``read``; whether the last ``turn_frames`` frames read the locator's 'L'
        upright barely better (``min_turn_lead``) than turned by a quarter or a half. Such a pose
        passes the locator score (the medians of the white and black cells) and the fit ratio
        (the ring is square: a turned pose lies on its edges) but reads garbage; under fast
        motion detection makes such fits."""
        self.turn_leads.append(float(read.turns[0] - read.turns[1:].max()))
        leads = self.turn_leads
        return len(leads) == leads.maxlen and np.median(leads) < min_turn_lead


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
        self._buffer = EventBuffer()
        self._keep_us = config.detector.window_us + 4 * int(config.frame_us)
        """How far back of the next detection, or of the cursor, events are kept: a lock reads
        the frames of its detection window again."""
        self._cursor = 0
        """While tracking, the events before this time have been processed."""
        # Allocated once (with the camera's undistortion table), reset at every lock.
        self._triage = EventTriage(
            cam.undistort_table,
            config.decoder.fast_on_gap_us if config.data_every == 1 else config.refresh_us / 2,
            config.data_every == 1,
            still_share=config.tracker.still_near_share,
            still_every=config.tracker.still_lookup_every,
        )
        self._next_attempt_us: int | None = None
        self._pending: Detection | None = None
        """A detection under motion waiting for the frame after its burst's (``_postpone``)."""
        self._track: Track | None = None
        """The lock being tracked (``state`` is ``TRACKING``)."""
        self._dark: tuple[float, float] = (0.0, 0.0)
        """The latest proven lock's tracker's (``dark_px``, ``dark_weight``): the optics and
        the screen's contrast that set them outlast a lock."""
        self._verified: tuple[int, np.ndarray] | None = None
        """(time, T_cam_world) of the latest frame that passed its check (``turn_memory_us``)."""
        self._gaps: deque[tuple[int, int]] = deque(maxlen=8)
        """Recent stretches longer than a data frame without a single event: the source dropped
        them (a camera's lost packets, the virtual camera skipping ahead)."""
        self._poses = PoseHistory()
        """The tracked poses (T_cam_world) that the decoder reads frames through."""
        self._smoother = PoseSmoother(
            config.pose_smoothing_us,
            config.orientation_smoothing_us,
            pivot=config.geometry.locator_corners(config.marker_size_m).mean(axis=0),
        )
        self._last_pose_out = -(1 << 62)
        self.cell_px: float | None = None
        """A cell's side in pixels as the camera sees it: at the latest frame's or lock's pose,
        or while detecting as the latest blinking region suggests (``MarkerNotFound.cell_px``);
        None until one was seen."""
        self.detection_failure: str | None = None
        """Why the latest detection attempt failed; None once locked."""

    # --- public ------------------------------------------------------------------------------
    def push(self, chunk: np.ndarray) -> list[Output]:
        if not len(chunk):
            return []
        st = self.stats
        t_first = int(chunk["t"][0])
        if st.last_event_us is not None and t_first - st.last_event_us > self.config.frame_us:
            self._gaps.append((st.last_event_us, t_first))
        st.first_event_us = t_first if st.first_event_us is None else st.first_event_us
        st.last_event_us = int(chunk["t"][-1])
        st.events += len(chunk)
        with self._cpu("filter"):
            self._buffer.append(self._filter(chunk))
        # The next chunk may hold more events at this one's last time, none before it.
        return self._advance(st.last_event_us)

    def finish(self) -> list[Output]:
        """Process what is held back at the end of a recording: the events after the last
        complete piece of the grid."""
        last = self.stats.last_event_us
        if last is None:
            return []
        return self._advance(last + 1, final=True) + self._flush_poses()

    # --- stages ------------------------------------------------------------------------------
    def _advance(self, until: int, final: bool = False) -> list[Output]:
        """Process the stream up to ``until`` (every event before it has arrived): detection
        at its scheduled times on the events before them, tracking and decoding in pieces cut
        on a fixed grid of event time (``_follow``). Nothing depends on where the source cut
        the stream into chunks, so a recording gives the same outputs however it is read."""
        out: list[Output] = []
        window = self.config.detector.window_us
        while True:
            if self.state == TRACKING:
                out += self._follow(until, final=final)
                if self.state == TRACKING:
                    self._buffer.forget_before(self._cursor - self._keep_us)
                    return out
            if self._next_attempt_us is None:
                span = self._buffer.span
                if span is None:
                    return out
                self._next_attempt_us = span[0] + window
            if self._next_attempt_us > until:
                self._buffer.forget_before(self._next_attempt_us - self._keep_us)
                return out
            out += self._try_detect(self._next_attempt_us)

    @contextmanager
    def _cpu(self, stage: str):
        t0 = time.process_time()
        try:
            yield
        finally:
            self.stats.cpu_s[stage] += time.process_time() - t0

    def _try_detect(self, now: int) -> list[Output]:
        """Detect the marker in the window of events before ``now``; lock on it if it holds."""
        window = self.config.detector.window_us
        cpu0 = time.process_time()
        try:
            found, self._pending = self._pending, None
            if found is None:
                with self._cpu("detect"):
                    found = detect(self._buffer.parts_between(now - window, now), self.config)
                    if (prior := self._recent_verified(now)) is not None:
                        found = nearest_turn(found, prior, self.config)
            return self._lock(found, now)
        except MarkerNotFound as exc:
            if exc.cell_px is not None:
                self.cell_px = exc.cell_px
            self._detection_failed(now, str(exc), time.process_time() - cpu0)
            return []

    def _recent_verified(self, now: int) -> np.ndarray | None:
        """The pose of the latest frame that passed its check, if within ``turn_memory_us``
        (``detector.nearest_turn``)."""
        if self._verified is None or now - self._verified[0] > self.config.detector.turn_memory_us:
            return None
        return self._verified[1]

    def _detection_failed(self, now: int, reason: str, cpu_s: float) -> None:
        """Count the failure and schedule the next attempt ``retry_us`` of event time later (so
        a recording gives the same result on any machine); a live source also spaces them so
        that failing ones take at most ``max_cpu_share`` of a core."""
        q = self.config.detector
        self.stats.detection_failures[reason] += 1
        self.detection_failure = reason
        log.debug("detection at %d us: %s", now, reason)
        wait_us = q.retry_us
        if q.max_cpu_share is not None:
            wait_us = max(wait_us, int(cpu_s * 1e6 / q.max_cpu_share))
        self._next_attempt_us = now + wait_us

    def _lock(self, found: Detection, now: int) -> list[Output]:
        """Start tracking from ``found`` and read the frames still buffered. The lock stands
        only if the inner locator shows in one of them and tracking survives them; otherwise
        this raises ``MarkerNotFound`` (a failed detection, not a loss), unless under motion the
        frame after the burst's is still to come (``_postpone``)."""
        T, t_lock = found.T_cam_world, found.t_us
        tracker = EdgeTracker(self.config, T, t_lock, found.flow_px_per_ms)
        tracker.dark_px, tracker.dark_weight = self._dark
        outline = not found.refined
        if not found.moving:
            with self._cpu("lock"):  # a still detection may lag a slow drift: snap to the ring
                recent = self._buffer.between(now - self.config.tracker.capture_us, now)
                recent = to_columns(recent, self.config.camera.undistort_table)
                if tracker.capture(recent["xu"], recent["yu"], now):
                    T, outline = tracker.T_cam_world, False
        side = self.cell_px = cell_side_px(self.config, T)
        with self._cpu("lock"):
            span_us = _DENSITY_BLINKS * 1e6 / found.blink_hz
            blinks = self._buffer.parts_between(now - span_us, now)
            density = on_events_per_pixel(blinks, found.corners_px, found.blink_hz)
        stride = read_stride(self.config, side, density)
        late, q = self.config.decoder.late_mark_px_per_cell, self.config.decoder
        framed = get_profile(self.config.profile).framed
        # Frames inside the detection window are still buffered: read them too. Under motion the
        # pose holds at the compensated burst (frame 0) and is tracked from there to now.
        window = self.config.detector.window_us
        still_recheck = not found.moving and self.config.detector.still_recheck_us is not None
        recheck_us = now + window if still_recheck else None
        self._track = track = Track(
            tracker,
            CellReader(self.config, found.burst_us, stride, density < q.dense_on_per_pixel),
            next_frame=0 if found.moving else -int(window // self.config.frame_us) + 1,
            moving=found.moving,
            late_mark=late is not None and side >= late,
            probation=self._probation_frames(found.moving) if framed else None,
            turn_leads=deque(maxlen=q.turn_frames),
            lapse_us=None
            if q.proof_lapse_us is None
            else max(q.proof_lapse_us, 2 * self.config.frame_us),
            rechecked=[found.corners_px] if found.refined else [],
            recheck_us=recheck_us,
            outline_until_us=math.inf if recheck_us is not None and outline else -math.inf,
            updates_seen=self.stats.pose_updates,
        )
        self._triage.reset(now, stride)
        self._poses.restart(t_lock, T)
        self.state = TRACKING
        out: list[Output] = [StateChange(now, TRACKING, "marker detected")]
        out += self._pose_output(t_lock, T)
        # A still lock's tracker starts with the clusters it would hold had it been tracking all
        # along (the buffered events of its slots' lifetime): a first solve on the few events
        # of its first fraction of a millisecond alone can swing a drifting camera's pose by
        # centimetres.
        track_from = t_lock if found.moving else now - self.config.tracker.max_age_us
        self._cursor = min(
            track.reader.window(track.next_frame)[0] - self._triage.gap_us, track_from
        )
        losses = self.stats.losses  # a lock lost on its own buffered events never stood
        counts = self.stats.frames_read, self.stats.pose_updates
        out += self._follow(track_from, tracking=False, final=True)
        out += self._follow(now, final=True)
        frames = [o for o in out if isinstance(o, FrameOutput)]
        if self.state != TRACKING:
            self.stats.losses = losses
            reason = out[-1].reason
            raise MarkerNotFound(f"verify: tracking failed on the buffered events ({reason})")
        reason = self._unverified(found, frames)
        if reason and found.moving and (whole := track.reader.window(1)[1]) > now:
            self.stats.frames_read, self.stats.pose_updates = counts
            return self._postpone(found, whole)
        if reason:
            self._end_track()  # its poses never stood
            raise MarkerNotFound(reason)
        self.stats.lock_times_us.append(now)
        self.detection_failure = None
        return out

    def _probation_frames(self, moving: bool) -> int | None:
        """Frames a framed lock has to pass a frame check (``DecoderParams``)."""
        q = self.config.decoder
        if moving:
            return q.probation_frames
        if q.still_probation_us is None:
            return None
        return max(2, math.ceil(q.still_probation_us / self.config.frame_us))

    def _postpone(self, found: Detection, until: int) -> list[Output]:
        """Lock on ``found`` again at ``until``, when its second frame is whole. Under motion
        the frame of the burst itself reads poorly even at a right pose (the pose before the
        burst is not known, and the scan-out shows half the frame before it), so a lock judged
        on it alone would be refused, and a wrong one might pass. The burst's frame only times
        the clock (``_decode``), so nothing of this attempt reached the stream decoder; the
        next attempt reads it again, the same."""
        self._end_track()
        self._pending, self._next_attempt_us = found, until
        return []

    def _unverified(self, found: Detection, frames: list[FrameOutput]) -> str | None:
        """Why the lock on ``found`` does not stand, given the frames read from the buffer.

        Under motion a lock must show the inner locator clearly in the frames after the burst's
        (a ring fit a ring width off, or a wrong rotation, still reads at half the contrast),
        the right way up whether or not the burst showed it (``Detection.oriented``: a blurred
        burst can show the 'L' a quarter turn off as clearly), and keep the tracker on the
        ring's edges; a still lock only needs the locator to show. A frame that passes its check
        settles the rest (a slow ring's few events can leave the fit ratio low at a right pose,
        and blur the locator faint where `fast`'s toggling cells light its dark ones), but not
        a moving lock's faint locator: a burst's ring fit two thirds of a cell off at its
        corners reads the ring it straddles at a third of its contrast, and Reed-Solomon still
        passes one frame in a few."""
        q = self.config.detector
        if found.moving:  # the burst's own frame reads poorly (``_postpone``)
            frames = [f for f in frames if f.read.index > 0]
            if not frames:
                return "verify: no frame after the burst's was read"
        best = max((f.read.locator_score for f in frames), default=None)
        need = q.min_lock_locator_score if found.moving else self.config.decoder.min_locator_score
        faint = None
        if best is not None and best < need:
            faint = f"verify: the inner locator reads at {best:.2f} at the detected pose"
        if faint and found.moving:
            return faint
        if any(f.payload_bits for f in frames):
            return None
        if found.moving or not found.oriented:
            lead = np.mean([f.read.turns[0] - f.read.turns[1:].max() for f in frames])
            if lead < self.config.decoder.min_turn_lead:
                return f"verify: the frames read do not show the 'L' this way up (lead {lead:.2f})"
        if faint:
            return faint
        fit = self._track.tracker.fit_ratio
        if found.moving and fit is not None and fit < q.min_lock_fit_ratio:
            return f"verify: only {fit:.0%} of the events near the ring lie on its edges"
        return None

    def _follow(self, until: int, tracking: bool = True, final: bool = False) -> list[Output]:
        """Triage (and track) the events from the cursor on, in pieces that end where the next
        frame's time span ends (its pixels' bursts are then complete, and it is read before the
        next ones come in) or at the next line of a ``_SEGMENT_US`` grid, whichever is first.
        A piece is processed once every event before its end has arrived (``until``); with
        ``final``, the last one ends at ``until`` itself."""
        out: list[Output] = []
        per_ms = self.config.tracker.max_events_per_ms
        while self.state == TRACKING:
            track = self._track
            if track.recheck_us is not None and self._cursor >= track.recheck_us:
                out += self._recheck_still(self._cursor)
            start, frame_end = track.reader.window(track.next_frame)
            if self._cursor >= frame_end:  # the frame's bursts are complete
                out += self._decode(frame_end)
                continue
            end = min(frame_end, (self._cursor // _SEGMENT_US + 1) * _SEGMENT_US)
            if end > until:
                if not final or self._cursor >= until:
                    break
                end = until
            parts = self._buffer.parts_between(self._cursor, end)
            self._cursor = end
            if not parts:
                continue
            self._triage.marks_us = (start, (start + frame_end) // 2 if track.late_mark else start)
            # No burst is cut before the frame's window opens: the plane is fitted only near it.
            cut = None
            if end >= start - self.config.refresh_us / 4:
                pose = self.pose_at(np.array([end]))[0]
                cut = track.reader.gate_opens(track.next_frame, pose)
            self._triage.cut_plane = cut
            with self._cpu("triage"):
                if tracking:
                    self._select_near_edges()
                near = self._triage(*parts, per_ms=per_ms)
            if tracking:
                out += self._track_events(near)
        return out

    def _recheck_still(self, now: int) -> list[Output]:
        """Take a still lock's pose again from the window before ``now``: from the mean of the
        corners refined to the locator's edges (``Detection.refined``) that the lock and the
        rechecks since the camera last moved (made a pose update) found, each a still detection
        within half a cell of the held pose's corners. A still camera gives the tracker no events
        to correct the pose with, and a window's outline corners can lie a pixel or two off
        (one that mixed the marker's first frames with what the screen showed before: 3.5 cm at
        1.7 m), where refined ones from another window hold it within a few millimetres."""
        track, q = self._track, self.config.detector
        track.recheck_us = now + q.still_recheck_us
        track.outline_until_us = min(track.outline_until_us, now)
        if self.stats.pose_updates != track.updates_seen:
            track.updates_seen = self.stats.pose_updates
            track.rechecked.clear()
            return []
        geo, cam, T = self.config.geometry, self.config.camera, track.tracker.T_cam_world
        world = geo.locator_corners(self.config.marker_size_m)
        held = cam.project(world @ T[:3, :3].T + T[:3, 3])
        with self._cpu("detect"):
            try:
                parts = self._buffer.parts_between(now - q.window_us, now)
                found = recheck_still(parts, self.config, held)
            except MarkerNotFound:
                return []
        if not found.refined:
            return []
        if np.abs(found.corners_px - held).max() > 0.5 * cell_side_px(self.config, T):
            return []
        track.rechecked.append(found.corners_px)
        T = pnp(np.mean(track.rechecked, axis=0), world, cam)
        track.tracker.restart(T, now)
        self._poses.append(now, T)
        # the poses before the jump are smoothed on their own side of it
        return self._flush_poses() + self._pose_output(now, T)

    def _select_near_edges(self) -> None:
        """Show the tracker only the events near its edges: twice its gate (so that a pose
        slipping off the edges still shows) plus the motion of one segment."""
        reach = 2 * self.config.tracker.gate_px + 4.0
        self._triage.track_near(*self._track.tracker.edges_px, reach)

    def _lose(self, now: int, reason: str) -> list[Output]:
        log.info("tracking lost at %d us: %s", now, reason)
        self.stats.losses += 1
        self._next_attempt_us = now + self.config.detector.window_us  # a fresh window of events
        return [*self._end_track(), StateChange(now, DETECTING, reason)]

    def _end_track(self) -> list[PoseEstimate]:
        """Back to detecting; the track's smoothed poses still held."""
        poses = self._flush_poses()
        if self._track.proven_at_us is not None:
            self._dark = self._track.tracker.dark_px, self._track.tracker.dark_weight
        self.state = DETECTING
        self._track = None
        return poses

    def _track_events(self, events: np.ndarray) -> list[Output]:
        out: list[Output] = []
        if len(events):
            tracker = self._track.tracker
            with self._cpu("track"):
                try:
                    updates = tracker.push(events["xu"], events["yu"], events["t"], events["p"])
                except ValueError as exc:  # the pose put the marker behind the camera
                    return out + self._lose(int(events["t"][-1]), str(exc))
            for u in updates:
                self.stats.pose_updates += 1
                self._poses.append(u.t_us, u.T_cam_world)
                out += self._pose_output(u.t_us, u.T_cam_world)
            now = int(events["t"][-1])
            if now - self._last_pose_out >= self.config.pose_interval_us:
                out += self._pose_output(now, tracker.T_cam_world)
            reason = self._out_of_view(tracker.T_cam_world) or tracker.off_edges()
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
        track = self._track
        reader, q = track.reader, self.config.decoder
        framed = get_profile(self.config.profile).framed
        while self.state == TRACKING and reader.window(track.next_frame)[1] <= now:
            m = track.next_frame
            track.next_frame += 1
            with self._cpu("decode"):
                t0, t1 = reader.window(m)
                box = reader.box(*self.pose_at(np.array([t0, (t0 + t1) / 2, t1])))
                bursts = self._triage.bursts(t0, t1, box)
                read = reader.read(m, bursts, self.pose_at)
            self.stats.frames_read += 1
            if m == 0 and track.moving:  # ``_postpone`` says why
                out.append(FrameOutput(read, False))
                continue
            seen = read.locator_score >= q.min_locator_score
            if not seen and any(a < t1 and t0 < b for a, b in self._gaps):
                continue  # the source delivered nothing then: no evidence either way
            if track.misturned(read, q.min_turn_lead):
                out.append(FrameOutput(read, False))
                out += self._lose(now, "the inner locator's 'L' does not read at the tracked pose")
                continue
            verified, messages = self.stream.verified_bits, []
            if seen or framed:
                # A framed frame's code and CRC vouch for it whatever its locator reads: a
                # small cell's dark locator cells fire from their lit neighbours' light.
                with self._cpu("stream"):
                    messages = self.stream.push(read.bits, read.confidence)
            passed = self.stream.verified_bits - verified
            if not (seen or passed):
                out.append(FrameOutput(read, False))
                track.missed += 1
                if track.missed >= q.lost_after_frames:
                    out += self._lose(now, "inner locator not seen in the last frames")
                continue
            track.missed = 0
            self.stats.frames_seen += 1
            frame = FrameOutput(read, True, passed, self.stream.corrected)
            pose = self.pose_at(np.array([read.t_us]))[0]
            self.cell_px = cell_side_px(self.config, pose)
            if frame.payload_bits:
                self._verified = (read.t_us, pose)
            checked = frame.payload_bits or (not framed and track.upright(q.min_proof_lead))
            first = track.proven_at_us is None
            agree = not first or track.sides_agree(q.min_edge_agreement, every_side=track.moving)
            if checked and agree:
                track.proven_at_us = read.t_us
            out.append(frame)
            out += [MessageOutput(read.t_us, msg) for msg in messages]
            if track.failed_probation(frame):
                reason = (
                    "no frame passed its check since the lock"
                    if track.proven_at_us is None
                    else "no frame passed its check lately"
                )
                out += self._lose(now, reason)
        return out

    # --- poses -------------------------------------------------------------------------------
    def pose_at(self, t_us: np.ndarray) -> np.ndarray:
        """T_cam_world (n, 4, 4) at the times ``t_us`` (n,): interpolated between the updates
        around each, or the nearest one outside them. Under motion updates come ~1 ms apart,
        over which a 12 px/ms flow moves the marker half a cell."""
        return self._poses.at(t_us)

    def _trim_poses(self) -> None:
        span = self._buffer.span
        if span:
            self._poses.forget_before(span[0])

    def _pose_output(self, t_us: int, T_cam_world: np.ndarray) -> list[PoseEstimate]:
        """Hand a tracked pose to the smoother; the smoothed poses it gives back."""
        self._last_pose_out = t_us
        return self._estimates(self._smoother.push(t_us, invert(T_cam_world)))

    def _flush_poses(self) -> list[PoseEstimate]:
        """The smoothed poses still held: the track is ending."""
        return self._estimates(self._smoother.flush())

    def _estimates(self, smoothed: list[tuple[int, np.ndarray]]) -> list[PoseEstimate]:
        track = self._track
        return [
            PoseEstimate(t, T, verified=track is not None and track.publishes_verified(t))
            for t, T in smoothed
        ]
