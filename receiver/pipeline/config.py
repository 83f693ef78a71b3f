"""Everything the receiver must be told about the link, and its tuning knobs (paper Sec. IV)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.profiles import MAX_REFRESH_HZ, MIN_REFRESH_HZ, get_profile
from eventocc.receiver.camera import CameraModel


@dataclass(frozen=True)
class FilterParams:
    """Pre-processing (Sec. IV-A); both filters are off unless enabled."""

    refractory: bool = False
    same_polarity_us: int = 1000
    opposite_polarity_us: int = 1000
    neighbourhood: bool = False
    radius_px: int = 1
    """3x3 window, as in the paper."""
    window_us: int = 10_000
    min_neighbours: int = 3


LIVE_CPU_SHARE = 0.5
"""Share of a core that failing detection attempts may take on a real-time source."""


@dataclass(frozen=True)
class DetectorParams:
    """Temporal + spatial detection (Sec. IV-B)."""

    window_us: int = 70_000
    """DFT window T: two blink periods at 60 Hz are enough to lock, and the first frame can be
    read as soon as the window is full (the paper's 0.5 s would delay it by half a second)."""
    retry_us: int = 17_500
    """Event time between detection attempts, each over the latest window: the marker locks
    within about a window plus a retry of coming into view. Under motion each attempt reads
    another burst and few read the inner locator clearly, so attempts come about twice per blink
    period."""
    max_cpu_share: float | None = None
    """Real-time sources only (``LIVE_CPU_SHARE``): failed attempts are spaced further apart when
    they cost more than this share of one core (on a megapixel sensor an attempt over a crowded
    window takes longer than the window). None keeps the spacing in event time alone, so that a
    recording decodes the same on any machine."""
    min_tile_ratio: float = 0.25
    """|X_k| / X_0 of a blink-map tile's signed events for it to blink: ON bursts and OFF bursts
    half a period later add up, swept edges (both polarities at any phase) do not."""
    sigma_frac: float = 0.1
    """Width of the triplet-period Gaussian, as a fraction of the blink frequency."""
    heat_threshold: float = 0.2
    """Heat-map binarisation, relative to its (robust) maximum."""
    still_recheck_us: int | None = 500_000
    """A still lock's pose is taken again from a fresh window one window after the lock, then
    this often while the camera stands still (``Receiver._recheck_still``; None: never)."""
    min_side_px: float = 12.0
    """Smallest accepted locator side (the paper uses 50 px on a 1280x720 sensor)."""
    max_square_skew: float = 0.15
    """The quadrilateral, taken through the camera's intrinsics back onto a plane, must be a
    square: its plane axes may meet at most this far from a right angle (|cos|), while a square
    gives 0 at any view. Corners found on suite scenes viewed at up to 43 deg gave at most
    0.005, where a check of the image's own angles (the paper's 90 +- 15 deg) turned away the
    perspective of near markers seen at 40-45 deg."""
    max_square_stretch: float = 1.25
    """...and its plane axes may differ in length by at most this factor (1 for a square)."""
    max_view_deg: float = 70.0
    """Largest angle between the marker's normal and the line of sight to it."""
    min_period_match: float = 0.2
    """Mean Gaussian weight of the region's triplets: ~0.9 at the right blink frequency with a
    still camera, ~0.3 under hand-held motion (swept edges flip at any period), ~0.1 at a
    display 10 Hz off (one sigma is ``sigma_frac`` of the frequency). Below it, 2 x 2 binned
    pixels decide by beating blinks two widths off instead (``detector._binned_blink``)."""
    min_harmonic_ratio: float = 0.08
    """|X_k| / X_0 of the ROI's signed event count; noise gives ~1/sqrt(events), ``fast`` ~0.15."""
    min_orientation_score: float = 0.25
    """Lead of the best rotation's contrast between the inner locator's expected white and black
    cells over the runner-up's, in the motion-compensated burst under motion."""
    min_still_orientation_score: float = 0.6
    """The same for the still path's phase-locked image: a still marker shows sharp there and its
    'L' leads by more than 1, while a camera drifting too slowly for the burst to give a flow
    smears it into quadrilaterals centimetres off whose 'L' leads by about 0.3."""
    min_checked_orientation_score: float = 0.4
    """The same for profiles whose frames prove the lock (a CRC at the tracked pose), where a
    wrong lock stays tentative and is dropped once its frames fail: blur of 1.4 px at 6-7 px
    per cell, or a readout that leaves a pixel one event per blink, makes a still marker's
    'L' lead by 0.4-0.56 only, still above a drift's smear."""
    min_binned_cell_px: float = 4.0
    """The still path retries on binned pixels (``detector.bin_factor``) only while a cell keeps
    this many binned pixels across: fewer blur the inner locator's 'L' away."""
    max_square_flow_px_per_ms: float = 0.3
    min_square_orientation_score: float = 0.5
    """Up to this flow the square fitted to the burst's locator gives the pose itself if it
    reads the 'L' at least this clearly (so does the last-resort slow path's square,
    ``detector._detect_slow``); faster bursts are pulled onto the ring's edge events first. A
    slow ring fires too little beside the burst's own ON events for that capture, which then
    settles a ring width off, while the square lies within a few pixels and the tracker
    refines its pose within milliseconds."""
    min_edge_polarity: float = 0.7
    """Under motion, the ring fitted at the burst must fire with the polarities the flow gives
    its edges (``detector.ring_support``) at least this well: +1.0 at the true pose on the
    virtual camera, +0.2 to +0.5 for fits a ring width too large, which read the white ring as
    the inner locator's 'L' and pass every later check."""
    unoriented_edge_polarity: float = 0.97
    max_unoriented_flow_px_per_ms: float = 1.5
    """A burst that shows no clear 'L' still gives a lock whose frames then read the 'L' this
    way up (``Detection.oriented``), if its ring fit agrees this well with the flow's
    polarities and the flow is at most this fast: at 4 px per cell few bursts show the 'L'
    clearly, while at faster flows right and wrong captures agree with the polarities alike."""
    turn_memory_us: int = 500_000
    """A detection within this much event time of a frame that passed its check takes the
    quarter turn nearest that frame's pose (``detector.nearest_turn``): a hand-held camera
    turns a few degrees in that time, far from the 45 that would make the turn ambiguous."""
    min_lock_fit_ratio: float = 0.6
    """Under motion, a lock stands only if this share of the events near the ring lie on its
    edges while the buffered events are tracked (a still camera's ring fires only noise)."""
    min_lock_locator_score: float = 0.5
    """Under motion, a lock stands only if a buffered frame reads the inner locator at this
    contrast (``DecoderParams.min_locator_score`` for a still camera): correct locks read
    ~0.6, rotated ones or ring fits a ring width off ~0.35."""


@dataclass(frozen=True)
class TrackerParams:
    """Edge tracking and pose (Sec. IV-C)."""

    gate_px: float = 6.0
    """theta_d: events this close to a projected edge join its cluster."""
    alpha: float = 0.3
    """Cluster slots per pixel of edge length."""
    min_fill: float = 0.25
    """An edge's latency indicator counts once this share of its slots is filled (a quiet
    sensor's noise rarely fills a cluster; a noisy one's does, and ``min_firing_chi2`` keeps
    such clusters from moving the pose)."""
    min_firing_chi2: float = 25.0
    """The pose is re-solved only if an outer edge fired since the last update: its events
    within two gates pile up at some distance from it, by Pearson's chi-square against an even
    spread above this (3 degrees of freedom; noise alone exceeds 25 once in 60,000 tests).
    A still marker's edges fire nothing, and its clusters then fill with the sensor's leak and
    shot noise alone, whose fits walk the pose away (``tracker._edges_firing``)."""
    min_update_interval_us: int = 250
    """At most one pose update per interval (the authors' 4 kHz tick)."""
    max_update_interval_us: int = 1000
    """At least one pose update per interval while new events join the clusters, even if no
    indicator fired (the 1 kHz pose-rate target holds under slow motion too)."""
    min_new_events: int = 16
    """Events that must have joined the clusters since the last update before a timed one."""
    velocity_span_us: int = 2000
    """The edges' image velocity is fitted to the poses of this span (three at least), which
    averages out the jitter of single poses."""
    carry_us: int = 1000
    """An event is carried along its edge's motion for at most this long: under half of
    ``velocity_span_us``, so that the velocity's jitter and the poses' do not feed each other."""
    capture_us: int = 0
    """Recent events used to pull a detected pose onto the ring's edges (0: off). Off by
    default: with a still camera the only events near the ring are noise, and capture then
    moves a correct pose by centimetres."""
    fit_min_events: int = 400
    """Events near the edges needed before their on-edge share (the fit ratio) is judged."""
    min_fit_ratio: float = 0.0
    """Below this on-edge share the pose has slipped off the marker: tracking is lost (0: off).
    Off by default: with a still camera the events near the ring are noise and the blinking
    locator one ring width inside, so correct poses score 0-50%; loss is then caught by the
    locator check and the view check instead."""
    fit_judgements: int = 9
    """Consecutive fit ratios (of ``fit_min_events`` each) whose median must fall below
    ``min_fit_ratio`` to lose the lock. A correct pose under slow motion dips for one judgement
    now and then (its edges fire little while the locator keeps blinking nearby), while a wrong
    lock stays low: a median over several keeps the one and drops the other as fast."""
    min_fit_speed_px_per_ms: float = 0.0
    """Events near the edges while their image moves slower than this (the median of the
    edges' ends) are not judged (0: judged at any speed). A near-still ring fires little and
    its band is the blinking locator's, so its fit ratio says little about the pose."""
    silent_sweep_px_per_ms: float = 1.0
    """An outer edge whose image crosses itself this fast fires along its whole length within a
    millisecond, as its inner edge does (``EdgeTracker.silent_edges``)."""
    silent_updates: int = 30
    """Consecutive pose updates that must find a silent swept outer edge to contradict the pose
    (``EdgeTracker.contradicted``): one that slides off at a flow peak often comes back."""
    polarity_sweep_px_per_ms: float = 0.2
    """An edge's events are judged by their polarity (``EdgeTracker.reversed_edges``) while the
    image crosses it at least this fast: a swept edge's pixels fire ~10 events each, hundreds
    of times the sensor's noise on the edge's few pixels."""
    polarity_window_us: int = 10_000
    min_polarity_events: int = 30
    """An edge's events are judged in windows of ``polarity_window_us``, those with at least
    ``min_polarity_events`` swept ones."""
    reversed_windows: int = 3
    """Judged windows in a row in which an edge fires reversed (``tracker.REVERSED_AGREEMENT``)
    before the lock goes: a right pose's swept edges agree at +0.9 or more, one a ring width
    off on a side reads -0.7 to -1 there."""
    max_age_us: int = 30_000
    """Slots older than this are stale and leave the cluster."""
    max_events_per_ms: float | None = 4000.0
    """Events near the edges given to the tracker per millisecond at most, evenly thinned
    beyond (None: all). A hand-held 1280x720 camera puts ~37 M events a second near the ring,
    whose ~1000 slots each keep only their newest: 4 per slot and millisecond still refresh
    every slot between pose updates, and the tracker's cost stops growing with the event rate."""
    still_near_share: float = 0.01
    still_lookup_every: int = 4
    """Below this share of the events near the edges (but above none), the triage looks up at
    most every ``still_lookup_every``-th event in the tracker's tiles: a camera standing still
    puts under 1% of its events there and its tracker waits for motion, which a quarter of them
    shows as well as all of them do."""
    huber_px: float = 1.0
    max_iterations: int = 10

    def __post_init__(self) -> None:
        for name in ("fit_judgements", "silent_updates", "still_lookup_every", "reversed_windows"):
            if getattr(self, name) < 1:
                raise ValueError(f"tracker {name} must be at least 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class DecoderParams:
    """Data decoding (Sec. IV-D)."""

    template_px: int = 0
    """Template pixels per cell; 0 picks one from the cell's size in the image."""
    cell_margin: float = 0.2
    """Fraction of each cell side ignored at its border (blur, pose error)."""
    step_us: int = 250
    """Longest stretch of a frame's bursts unwarped with one pose: under hand-held motion the
    marker must move well under a cell meanwhile (0.5 px/ms moves it 1/8 px per 250 us)."""
    lost_after_frames: int = 6
    """Consecutive frames without the inner locator before tracking counts as lost."""
    min_locator_score: float = 0.3
    sure_contrast: float = 1 / 2
    """A cell this share of the contrast away from the threshold has full confidence: wide, so
    that the confidences rank the cells for the Reed-Solomon decoder's extra erasures
    (``FrameCodec.decode``). The framed profiles erase outright only below 1/32 of it
    (``LinkProfile.erasure_below``), a 64th of the contrast, and only where a codeword's bits
    alone fail: an erasure pays only when more than half of the erased bytes are wrong, and
    under motion a cell an eighth of the contrast away is still mostly right."""
    min_edge_agreement: float = 0.5
    """A lock's first proof also asks each swept outer edge of the ring to have fired with the
    motion's polarity at least this well in the tracker's latest window (``Track.sides_agree``):
    the truth's agree at +0.9 or more where the motion crosses them squarely, +0.5 where it
    barely does; poses a ring width off on a side or skewed across a corner read -1 to +0.5.
    Later proofs do not: where the motion turns, the velocity fitted to the latest poses points
    the old way for a few milliseconds, and a right pose's edges then read reversed."""
    turn_frames: int = 3
    """Read frames over which the inner locator's 'L' is judged (``min_turn_lead``)."""
    min_turn_lead: float = 0.5
    """Median over the last ``turn_frames`` frames of the canonical turn's locator reading
    minus the best other turn's (``FrameRead.turns``, ring-mean units), below which tracking
    counts as lost. A correct pose reads a lead of ~1.5 (hand-held at 0.5 px/ms); a pose a
    quarter turn off, or one whose ring fit is a ring width too large, reads ~0-0.6 although
    its ``locator_score`` (medians of the white and black cells) often reads 1."""
    min_proof_lead: float = 0.8
    """The lead each of the last ``turn_frames`` frames must read for ``paper``'s proof, which has
    no CRC (``Track.upright``): stricter than ``min_turn_lead``, as a wrong pose that passes it
    goes out verified. A square a quarter turn off read 0.52-0.60 in three frames in a row under
    1.3 px/ms; right poses read the lead below 0.8 in 1.8% of the suite's ``paper`` frames (below
    0.5 in 1.3%)."""
    read_px_per_cell: float | None = 7.0
    """Cells at least twice this wide (pixels, at the lock) are read from one pixel in every
    s x s block: s is the largest stride leaving this many pixels per cell side. A 1280x720
    camera 0.6 m from an N = 16 marker sees 22 px per cell, where a stride of 3 cuts the
    triage's memory traffic ninefold; coarser strides lose bits under fast motion. None: every
    pixel."""
    dense_on_per_pixel: float = 4.0
    """ON events per lit pixel per transition from which a read pixel says as much as a dense
    sensor's; below it the stride shrinks in proportion (``decoder.read_stride``). A readout
    that keeps a quarter of the events leaves 1-2, and each pixel then misses bursts or times
    them by a late event."""
    fast_on_gap_us: int = 4000
    """``fast``: an ON event this long after its pixel's last ON event starts a new burst even
    with no OFF event between (``triage._burst``). A cell dark for a few refreshes fires ON when
    a neighbour lights up (the lens spreads a few per cent of its light onto it, a large step in
    the log of a dark pixel's light) and no OFF event follows while that neighbour stays lit,
    so its own switch a refresh or more later would only continue that burst and go unread.
    Longer than the gaps between the last ON events of a pixel settling at white (its light
    approaches white with the display's rise constant, ~2.5 ms on an LCD), shorter than a
    240 Hz refresh."""
    late_mark_px_per_cell: float | None = 12.0
    """Cells at least this wide (pixels, at the lock) are also read from each pixel's first burst
    after the middle of the frame's window (``EventTriage.marks_us``). The scan-out switches the
    bottom rows last, and under fast motion the images of the rows above sweep over their
    pixels first, so a bottom row's pixel often fires for a neighbour's image before its own
    switch; on small cells one pixel's extra burst flips a cell. None: never."""
    probation_frames: int | None = 20
    """A lock from a detection under motion must pass a frame check (CRC, framed profiles only)
    within this many frames with the locator seen, or it is dropped: a pose a quarter turn
    off and a ring width too near reads the static white ring as the 'L' and passes every
    other check, but none of its frames ever verifies, while a right lock's first frames do
    within a dozen. None: no probation."""
    still_probation_us: int | None = 100_000
    """A lock from a still detection (framed profiles) must pass a frame check within the
    frames of this much event time (at least two), or it is dropped and detection resumes: a
    still camera reads a right lock's frames cleanly from the first, so frames that keep
    failing their CRC mean a wrong lock. None: no probation."""
    proof_lapse_us: int | None = 100_000
    """A proven lock stays proven for this much event time (at least two frames) after its
    latest frame that passed its check: its poses after that come out tentative, and it is
    dropped at its next frame that fails, so detection resumes. A tracker that slides off the
    marker keeps reading the locator (its ring is wide) long after its frames stopped
    passing. None: once proven, for good."""

    def __post_init__(self) -> None:
        if self.read_px_per_cell is not None and self.read_px_per_cell <= 0:
            raise ValueError(
                f"decoder read_px_per_cell must be positive or None, got {self.read_px_per_cell}"
            )
        if self.dense_on_per_pixel <= 0:
            raise ValueError(
                f"decoder dense_on_per_pixel must be positive, got {self.dense_on_per_pixel}"
            )
        if self.turn_frames < 1:
            raise ValueError(f"decoder turn_frames must be at least 1, got {self.turn_frames}")
        if self.still_probation_us is not None and self.still_probation_us <= 0:
            raise ValueError(
                "decoder still_probation_us must be positive or None, "
                f"got {self.still_probation_us}"
            )
        if self.proof_lapse_us is not None and self.proof_lapse_us <= 0:
            raise ValueError(
                f"decoder proof_lapse_us must be positive or None, got {self.proof_lapse_us}"
            )
        if self.probation_frames is not None and self.probation_frames < 1:
            raise ValueError(
                f"decoder probation_frames must be at least 1 or None, got {self.probation_frames}"
            )


@dataclass(frozen=True)
class ReceiverConfig:
    camera: CameraModel
    cells: int = 16
    profile: str = "robust"
    refresh_hz: float = 60.0
    marker_size_m: float = 0.272
    ring: int = 0
    filters: FilterParams = field(default_factory=FilterParams)
    detector: DetectorParams = field(default_factory=DetectorParams)
    tracker: TrackerParams = field(default_factory=TrackerParams)
    decoder: DecoderParams = field(default_factory=DecoderParams)
    pose_interval_us: int = 1000
    """Longest gap between two output poses while the camera (and pose) stand still."""
    pose_smoothing_us: int = 5000
    """Each output pose places the marker's centre in the camera frame on a straight line fitted
    to the poses within this much event time of it (``smoothing.PoseSmoother``); 0 gives the
    tracker's own poses."""
    orientation_smoothing_us: int = 15000
    """...and the camera's orientation on one fitted within this much (at least
    ``pose_smoothing_us``; less while the camera turns fast), which is how much later each pose
    comes. The orientation is what a small marker's image fixes worst, with a noise that stays
    correlated over several updates."""

    def __post_init__(self) -> None:
        get_profile(self.profile)  # raises with the list of valid names
        if not MIN_REFRESH_HZ <= self.refresh_hz <= MAX_REFRESH_HZ:
            hz_range = f"{MIN_REFRESH_HZ:g}..{MAX_REFRESH_HZ:g}"
            raise ValueError(f"refresh rate must be {hz_range} Hz, got {self.refresh_hz}")
        if self.marker_size_m <= 0:
            raise ValueError(f"marker size must be positive metres, got {self.marker_size_m}")
        if self.pose_smoothing_us < 0 or self.orientation_smoothing_us < 0:
            raise ValueError(
                f"pose smoothing must be >= 0 us, got {self.pose_smoothing_us} "
                f"and {self.orientation_smoothing_us} for the orientation"
            )
        MarkerGeometry(self.cells, self.ring)  # raises for an unsupported N

    @cached_property
    def geometry(self) -> MarkerGeometry:
        return MarkerGeometry(self.cells, self.ring)

    @property
    def data_every(self) -> int:
        return get_profile(self.profile).data_every

    @property
    def refresh_us(self) -> float:
        return 1e6 / self.refresh_hz

    @property
    def frame_us(self) -> float:
        """Time between data frames."""
        return self.refresh_us * self.data_every

    @property
    def blink_hz(self) -> float:
        """The inner locator is shown on every other refresh in every profile."""
        return self.refresh_hz / 2
