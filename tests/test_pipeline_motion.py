"""Detection and tracking while a hand-held camera moves: the blink map, the motion-compensated
locator search and the orientation read on synthetic inputs, the retry schedule, and the
receiver on a small virtual event camera (the scene of ``bench.tracking``)."""

from __future__ import annotations

import os
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.experiments.eventcam import HAND_HELD_TRACKER, clip_message
from bench.experiments.eventcam import hand_held_scene as paper_hand_held_scene
from bench.tracking import CAMERA, hand_held_config, hand_held_scene
from eventocc.occ.marker import MarkerGeometry, render
from eventocc.occ.stream import StreamDecoder, StreamEncoder
from eventocc.receiver.events import EVENT_DTYPE, make_events
from eventocc.receiver.pipeline import receiver as receiver_module
from eventocc.receiver.pipeline.buffer import to_columns
from eventocc.receiver.pipeline.config import DecoderParams, DetectorParams, ReceiverConfig
from eventocc.receiver.pipeline.detector import (
    Detection,
    blinking_region,
    locator_cells,
    nearest_turn,
    orient,
    ring_cells,
    ring_support,
    turn_readings,
)
from eventocc.receiver.pipeline.locate import (
    Box,
    MarkerNotFound,
    compensated_burst,
    densest_burst_us,
    events_between,
    fit_square,
    latest_burst_us,
    locator_blob,
    locator_fits,
    motion_flow,
    quadrilateral,
    slow_flow,
    warped_counts,
)
from eventocc.receiver.pipeline.pose import pnp, project_ideal
from eventocc.receiver.pipeline.receiver import (
    DETECTING,
    TRACKING,
    FrameOutput,
    PoseEstimate,
    Receiver,
    StateChange,
)
from eventocc.receiver.pipeline.tracker import EdgeTracker, edge_polarities
from eventocc.receiver.sim import Recording, StaticMotion, simulate

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

LOCK_WITHIN_US = 300_000
"""A lock needs one detection window (70 ms) plus a few retries."""
FIRST_POSE_MAX_M = 0.05
"""Initial pose (after capture onto the ring edges) against ground truth."""
HAND_HELD_ATE_M = 0.01
"""What the hand-held tracker promises (README: ATE <= 1 cm)."""
TRACKED_RMS_M = 0.02
TRACKED_P95_M = 0.03
"""At about 4 px per cell a pixel is 2-3 mm on the marker; a re-lock may start a few cm off and
converge within milliseconds (the wrong-lock test bounds how long anything worse may last)."""
WRONG_LOCK_M = 0.10
WRONG_LOCK_DROPPED_US = 50_000
"""A pose this far off must be dropped (fit ratio) within this time on the slow clip."""


SHAPE = (180, 240)
SENSOR = Box(0, 0, 240, 180)
PERIOD_US = 1e6 / 30
CONFIG = ReceiverConfig(CAMERA)


def _events(t, x, y, p) -> np.ndarray:
    ev = np.zeros(len(t), EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, np.rint(x), np.rint(y), p
    return ev[np.argsort(ev["t"], kind="stable")]


def _noise(rng, n, span_us, p) -> np.ndarray:
    """``n`` events of polarity ``p`` at random times in [0, ``span_us``) and random pixels."""
    t = np.sort(rng.integers(0, span_us, n))
    return make_events(t, rng.integers(0, SHAPE[1], n), rng.integers(0, SHAPE[0], n), p)


def _outline(rng, n, t0, t1, corner, side, flow, polarity):
    """``n`` events on a square outline (top-left ``corner`` at t = 0) moving at ``flow``."""
    t = rng.integers(t0, t1, n)
    s, edge = rng.uniform(0, side, n), rng.integers(0, 4, n)
    x = corner[0] + np.choose(edge, [s, np.full(n, side), s, np.zeros(n)])
    y = corner[1] + np.choose(edge, [np.zeros(n), s, np.full(n, side), s])
    return _events(t, x + flow[0] * t / 1e3, y + flow[1] * t / 1e3, polarity(n))


def _moving_marker(flow, duration_us=70_000, seed=0):
    """A 60 px square that fires ON in the bursts (at whole periods) and OFF half a period
    later, moving at ``flow`` px/ms, framed by a 90 px outline (the static white ring) whose
    swept edges fire both polarities all the time."""
    rng = np.random.default_rng(seed)
    parts = []
    for k in range(int(duration_us // PERIOD_US) + 1):
        for centre, p in ((k * PERIOD_US, 1), ((k + 0.5) * PERIOD_US, -1)):
            t = rng.normal(centre, 0.05 * PERIOD_US, 4000).astype(np.int64)
            x, y = rng.uniform(90, 150, 4000), rng.uniform(60, 120, 4000)
            parts.append(_events(t, x + flow[0] * t / 1e3, y + flow[1] * t / 1e3, p))
    parts.append(
        _outline(
            rng,
            60_000,
            0,
            duration_us,
            (75, 45),
            90,
            flow,
            lambda n: rng.choice(np.array([-1, 1], np.int8), n),
        )
    )
    ev = np.concatenate(parts)
    ev = ev[(ev["t"] >= 0) & (ev["t"] < duration_us) & (ev["x"] < SHAPE[1]) & (ev["y"] < SHAPE[0])]
    return ev[np.argsort(ev["t"], kind="stable")]


@pytest.mark.parametrize("flow", [(0.5, -0.3), (-1.5, 1.0), (6.0, -4.0), (-9.0, 2.0)])
def test_motion_flow_recovers_the_translation_of_an_outline(flow):
    rng = np.random.default_rng(1)
    ev = _outline(rng, 20_000, 0, 13_000, (60, 40), 80, flow, lambda n: -np.ones(n, np.int8))
    assert np.allclose(motion_flow(ev, 13_000, SENSOR), flow, atol=0.1)


def test_motion_flow_of_unstructured_noise_is_zero():
    ev = _noise(np.random.default_rng(2), 20_000, 13_000, -1)
    assert np.array_equal(motion_flow(ev, 13_000, SENSOR), [0.0, 0.0])


def test_motion_flow_of_a_still_outline_is_zero():
    """A still outline's events at random times: no flow may look sharper than none, or a still
    camera would pay for (and risk) the motion path."""
    rng = np.random.default_rng(6)
    ev = _outline(rng, 20_000, 0, 13_000, (60, 40), 80, (0.0, 0.0), lambda n: -np.ones(n, np.int8))
    assert np.array_equal(motion_flow(ev, 6_500, SENSOR), [0.0, 0.0])


@pytest.mark.parametrize("flow", [(0.2, -0.1), (0.0, 0.25), (-0.15, 0.15)])
def test_slow_flow_recovers_a_drift_within_its_reach(flow):
    rng = np.random.default_rng(3)
    ev = _outline(rng, 20_000, 0, 13_000, (60, 40), 80, flow, lambda n: -np.ones(n, np.int8))
    assert np.allclose(slow_flow(ev, 13_000, SENSOR, 0.3), flow, atol=0.05)


def test_slow_flow_never_exceeds_its_reach():
    rng = np.random.default_rng(4)
    ev = _outline(rng, 20_000, 0, 13_000, (60, 40), 80, (2.0, 0.0), lambda n: -np.ones(n, np.int8))
    assert np.hypot(*slow_flow(ev, 13_000, SENSOR, 0.3)) <= 0.3 + 1e-9


def test_events_between_keeps_one_polarity_across_parts():
    ev = _moving_marker(np.zeros(2))
    parts = np.array_split(ev, 5)
    both = events_between(parts, 10_000.5, 40_000)
    off = events_between(parts, 10_000.5, 40_000, polarity=-1)
    assert both["t"].min() >= 10_001 and both["t"].max() < 40_000
    assert np.array_equal(off, both[both["p"] < 0])


def test_warped_counts_move_each_event_along_the_flow():
    ev = make_events(np.array([0, 2_000, 4_000]), np.array([10, 10, 10]), np.array([5, 5, 5]), 1)
    box = Box(8, 4, 20, 10)
    counts = warped_counts([ev], 0, 5_000, 1, 4_000.0, np.array([1.0, 0.5]), box)
    # To 4 ms at (1, 0.5) px/ms: (14, 7), (12, 6), (10, 5).
    assert counts.sum() == 3 and counts[3, 6] == counts[2, 4] == counts[1, 2] == 1
    assert warped_counts([ev], 0, 5_000, -1, 4_000.0, np.zeros(2), box).sum() == 0


def _latest(ev: np.ndarray) -> float:
    """The latest whole burst of ``_moving_marker``'s events (its bursts at whole periods)."""
    return latest_burst_us([ev], 0.0, PERIOD_US)


@pytest.mark.parametrize("flow", [(0.0, 0.0), (0.5, 0.3), (-1.0, 1.0)])
def test_compensated_burst_outlines_the_blinking_square_not_the_swept_ring(flow):
    ev = _moving_marker(np.array(flow))
    burst = compensated_burst([ev], _latest(ev), PERIOD_US, SENSOR)
    assert np.allclose(burst.flow, flow, atol=0.15)
    quad = quadrilateral(locator_blob(burst.image, cell_px=60 / 18))
    move = np.array(flow) * burst.t_us / 1e3
    truth = np.array([[90, 60], [150, 60], [150, 120], [90, 120]]) + move
    nearest = np.linalg.norm(truth[:, None] - quad[None], axis=2).min(axis=1)
    assert nearest.max() < 4, quad.round(1)  # every corner found (orientation is not read here)


def test_densest_burst_finds_the_burst_the_phase_places_off():
    # A burst of ON events over 12 ms from 100 ms on (the rows' scan-out), amid ON events at
    # every time (moving edges) and OFF events (not counted); the phase says 104.5 ms.
    rng = np.random.default_rng(0)
    burst = rng.uniform(100_000, 112_000, 4000)
    edges = rng.uniform(60_000, 150_000, 4000)
    t = np.concatenate([burst, edges, rng.uniform(100_000, 112_000, 4000)])
    p = np.r_[np.ones(8000), -np.ones(4000)]
    order = np.argsort(t)
    ev = make_events(t[order].astype(np.int64), np.full(len(t), 50), np.full(len(t), 60), p[order])
    found = densest_burst_us([ev], 104_500.0, PERIOD_US, SENSOR)
    # The burst's middle, to within the slack of a 13.3 ms window around a 12 ms burst.
    assert abs(found - 106_000) < 800, found
    # Too few ON events near the phase's time: the phase stands.
    assert densest_burst_us([ev[:50]], 104_500.0, PERIOD_US, SENSOR) == 104_500.0


def test_an_image_without_a_blob_is_a_clear_miss():
    with pytest.raises(MarkerNotFound, match="spatial: nothing brightens"):
        locator_blob(np.zeros(SHAPE, bool), cell_px=4.0)


def test_compensated_burst_works_in_a_box_of_the_sensor():
    ev = _moving_marker(np.array([0.5, 0.3]))
    box = Box(60, 30, 200, 160)
    burst = compensated_burst([ev], _latest(ev), PERIOD_US, box)
    assert burst.image.shape == box.shape
    full = compensated_burst([ev], _latest(ev), PERIOD_US, SENSOR)
    assert np.array_equal(burst.image, full.image[30:160, 60:200])


@pytest.mark.parametrize("flow", [(0.0, 0.0), (1.0, -0.5)])
def test_blinking_region_boxes_the_square_and_finds_its_burst_phase(flow):
    region = blinking_region([_moving_marker(np.array(flow))], CONFIG)
    box = region.box
    (x0, y0), (x1, y1) = np.array([[90, 60], [150, 120]]) + np.array(flow) * 70  # at the end
    assert box.x0 <= x0 and box.y0 <= y0 and box.x1 >= x1 and box.y1 >= y1
    assert box.x1 - box.x0 < 200  # the square and its path, not the whole sensor
    # Bursts are centred on whole periods: the phase is 0 (mod one period).
    off = (region.burst_us + PERIOD_US / 2) % PERIOD_US - PERIOD_US / 2
    assert abs(off) < 1000 and region.harmonic_ratio > 0.3


def test_blinking_region_of_noise_is_a_clear_miss():
    rng = np.random.default_rng(4)
    ev = _noise(rng, 50_000, 70_000, rng.choice([-1, 1], 50_000))
    with pytest.raises(MarkerNotFound, match="temporal: nothing blinks at 30 Hz"):
        blinking_region([ev], CONFIG)


def test_a_tile_blinks_only_above_the_least_harmonic_ratio():
    """``DetectorParams.min_tile_ratio``: no tile's signed events reach a ratio above 1."""
    strict = replace(CONFIG, detector=replace(CONFIG.detector, min_tile_ratio=1.01))
    marker = _moving_marker(np.zeros(2))
    assert blinking_region([marker], CONFIG).harmonic_ratio > 0.3
    with pytest.raises(MarkerNotFound, match="temporal: nothing blinks at 30 Hz"):
        blinking_region([marker], strict)


def _locator_image(geometry: MarkerGeometry, cell_px: int, border_px: int) -> np.ndarray:
    """Lit pixels of a data frame's locator region: the ring, a random payload, a dark gap of
    one ring, and the white ring's two edges as thin lines (what a swept ring leaves)."""
    n = geometry.locator_side
    cells = geometry.inner_locator.copy()
    cells[1:-1, 1:-1] = np.random.default_rng(5).integers(0, 2, (n - 2, n - 2)).astype(bool)
    image = np.zeros((n * cell_px + 2 * border_px,) * 2, bool)
    inner = render(cells, cell_px) > 0
    image[border_px:-border_px, border_px:-border_px] = inner
    for gap in (geometry.ring * cell_px, 2 * geometry.ring * cell_px):
        lo, hi = border_px - gap, border_px + n * cell_px + gap - 1
        image[lo, lo:hi], image[hi, lo:hi], image[lo:hi, lo], image[lo:hi, hi] = (True,) * 4
    return image


@pytest.mark.parametrize("cell", [4, 23])
def test_fit_square_pins_a_blurred_outline_to_the_locator(cell):
    """At the small sensors' 4 px per cell to a pixel or two; at the 23 px of the 1280x720
    camera 0.6 m from the marker, where the blob's outline starts more than a cell off, to a
    quarter cell (the bands lie inside cells, so the contrast is flat over a few pixels there;
    the capture of the ring's edges pins the pose after it)."""
    geo, border = MarkerGeometry(16), 5 * cell
    image = _locator_image(geo, cell, border)
    side = geo.locator_side * cell
    truth = border + np.array([[0, 0], [side, 0], [side, side], [0, side]], float) - 0.5
    centre = truth.mean(axis=0)
    # A blob grown by blur and off-centre by most of a cell and a half.
    start = centre + 1.12 * (truth - centre) + cell * np.array([1.3, -0.5])
    found = fit_square(image, start, geo.locator_side, geo.ring)
    assert np.abs(found - truth).max() < max(1.5, cell / 4), found.round(1)


@pytest.mark.parametrize("oblique", [True, False])
def test_a_locator_seen_obliquely_is_fitted_where_no_square_fits(oblique):
    geo, cell, border = MarkerGeometry(16), 8, 40
    image = _locator_image(geo, cell, border)
    side = geo.locator_side * cell
    truth = border + np.array([[0, 0], [side, 0], [side, side], [0, side]], float) - 0.5
    if oblique:  # the locator's image sheared and foreshortened
        square, truth = truth, truth + np.array([[30, 10], [-10, 25], [-35, 0], [5, -20]], float)
        H = cv2.getPerspectiveTransform(square.astype(np.float32), truth.astype(np.float32))
        nearest = cv2.INTER_NEAREST
        image = cv2.warpPerspective(image.astype(np.uint8), H, image.shape[::-1], flags=nearest)
        image = image > 0
    centre = truth.mean(axis=0)
    blob = centre + 1.06 * (truth - centre) + cell * np.array([0.6, -0.4])

    def cells_off(quad: np.ndarray) -> float:
        return min(np.abs(np.roll(quad, k, axis=0) - truth).max() for k in range(4)) / cell

    square = fit_square(image, blob, geo.locator_side, geo.ring)
    fits = locator_fits(image, blob, geo.locator_side, geo.ring)
    assert (cells_off(square) > geo.ring) == oblique
    assert len(fits) == (2 if oblique else 1) and np.array_equal(fits[-1], square)
    assert cells_off(fits[0]) < 0.3


@pytest.mark.parametrize("start", range(4))
def test_orient_reads_the_locator_at_four_pixels_per_cell(start):
    geo, cell, border = MarkerGeometry(16), 4, 20
    image = _locator_image(geo, cell, border)
    side = geo.locator_side * cell
    canonical = border + np.array([[0, 0], [side, 0], [side, side], [0, side]], float) - 0.5
    corners, score = orient(np.roll(canonical, -start, axis=0), image, geo)
    assert np.array_equal(corners, canonical) and score > 0.5


def test_a_quarter_turn_of_the_corners_turns_the_locator_grid():
    """What ``turn_readings`` relies on: the grid of the corners rolled by r samples the cells
    of the canonical grid turned by r quarter turns."""
    side = MarkerGeometry(16).locator_side
    image = np.random.default_rng(7).random((120, 120)).astype(np.float32)
    quad = np.array([[20.3, 15.2], [95.1, 22.7], [90.4, 100.1], [14.2, 92.6]])
    cells = locator_cells(quad, image, side)
    for r in range(4):
        turned = locator_cells(np.roll(quad, -r, axis=0), image, side)
        assert np.allclose(turned, np.rot90(cells, r), atol=1e-4), r


@pytest.mark.parametrize("turn", range(4))
def test_turn_readings_name_the_turn_of_a_locator_grid(turn):
    geo = MarkerGeometry(16)
    readings = turn_readings(np.rot90(geo.inner_locator.astype(float), -turn), geo)
    assert readings[turn] == 1.0  # every white ring cell lit, every black one dark
    assert np.delete(readings, turn).max() < 0.5, readings.round(2)


def test_turn_readings_of_a_blank_grid_name_no_turn():
    geo = MarkerGeometry(16)
    ring, _ = ring_cells(geo)
    assert len(ring) == 4 * (geo.locator_side - 1)
    assert np.array_equal(turn_readings(np.ones((geo.locator_side,) * 2), geo), np.zeros(4))


def _attempts(rx: Receiver) -> int:
    return sum(rx.stats.detection_failures.values())


def _push_noise(rx: Receiver, chunks: int) -> None:
    rng = np.random.default_rng(3)
    for k in range(chunks):
        t = np.sort(rng.integers(k * 10_000, (k + 1) * 10_000, 500))
        rx.push(make_events(t, rng.integers(0, 240, 500), rng.integers(0, 180, 500), 1))


@pytest.fixture
def slow_cpu(monkeypatch):
    """Every CPU clock reading is 10 s after the previous one: a hopelessly loaded machine."""
    clock = iter(np.arange(0.0, 1e9, 10.0))
    monkeypatch.setattr(receiver_module.time, "process_time", lambda: float(next(clock)))


def test_detection_retries_are_spaced_in_event_time_whatever_the_machine(slow_cpu):
    rx = Receiver(CONFIG)
    _push_noise(rx, 30)  # 300 ms: attempts from 70 ms on, every 17.5 ms of event time
    assert _attempts(rx) == 14  # 70, 87.5, 105, ..., 297.5 ms
    assert not rx.stats.lock_times_us


def test_a_live_receiver_spaces_failing_attempts_by_their_cpu_cost(slow_cpu):
    rx = Receiver(ReceiverConfig(CAMERA, detector=DetectorParams(max_cpu_share=0.5)))
    _push_noise(rx, 30)
    assert _attempts(rx) == 1  # each attempt "took" 10 s: the next one waits 20 s


def _clip(flow_px_per_ms: float, duration_s: float, seed: int = 0) -> tuple[Recording, list]:
    rec = simulate(hand_held_scene(flow_px_per_ms, seed), duration_s=duration_s, chunk_us=10_000)
    return rec, list(rec)


def _run(flow_px_per_ms: float, duration_s: float, seed: int = 0) -> dict:
    return _replay(*_clip(flow_px_per_ms, duration_s, seed))


def _replay(
    rec: Recording,
    chunks: list[np.ndarray],
    config: ReceiverConfig | None = None,
    stream: StreamDecoder | None = None,
) -> dict:
    rx = Receiver(config or hand_held_config())
    if stream is not None:
        rx.stream = stream
    poses: list[PoseEstimate] = []
    changes: list[StateChange] = []
    frames: list[FrameOutput] = []
    for out in [o for chunk in chunks for o in rx.push(chunk)] + rx.finish():
        if isinstance(out, PoseEstimate):
            poses.append(out)
        elif isinstance(out, StateChange):
            changes.append(out)
        elif isinstance(out, FrameOutput):
            frames.append(out)
    t = np.array([p.t_us for p in poses], np.int64)
    err = np.array([])
    if len(t):
        truth = rec.pose_at(t)
        est = np.stack([p.T_world_cam for p in poses])
        err = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
    return {"t": t, "err": err, "changes": changes, "frames": frames, "stats": rx.stats}


@pytest.fixture(scope="module")
def slow_clip() -> tuple[Recording, list]:
    return _clip(0.5, 0.6)


@pytest.fixture(scope="module")
def slow_hand(slow_clip) -> dict:
    return _replay(*slow_clip)


def _wrong_lock_spans_us(run: dict) -> list[int]:
    """Per lock: from its first pose more than ``WRONG_LOCK_M`` off to the lock's end."""
    t, err, changes = run["t"], run["err"], run["changes"]
    spans = []
    for lock in (c for c in changes if c.state == TRACKING):
        end = next((c.t_us for c in changes if c.t_us > lock.t_us), int(t[-1]))
        wrong = t[(t >= lock.t_us) & (t < end) & (err > WRONG_LOCK_M)]
        spans.append(int(end - wrong[0]) if len(wrong) else 0)
    return spans


def test_a_wrong_lock_under_motion_is_dropped_quickly(slow_hand):
    """Whatever detection does under motion, a pose far from the truth must not keep tracking:
    the tracker's fit ratio (events off the ring's edges) or the 'L' check has to end it."""
    spans = _wrong_lock_spans_us(slow_hand)
    assert max(spans, default=0) <= WRONG_LOCK_DROPPED_US, f"wrong poses tracked for {spans} us"


def test_edge_polarities_follow_the_flow_across_each_edge():
    """The marker moving right: the white ring's right outer edge moves onto the black ring
    (those pixels brighten: ON), its right inner edge away from the dark gap (OFF), and the
    top and bottom edges slide along themselves (unknown)."""
    outer = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    inner = np.array([[2, 2], [8, 2], [8, 8], [2, 8]], float)
    a = np.vstack([outer, inner])
    b = np.vstack([np.roll(outer, -1, axis=0), np.roll(inner, -1, axis=0)])
    polarities = edge_polarities(a, b, np.array([1.0, 0.0]))
    assert polarities.tolist() == [0, 1, 0, -1, 0, -1, 0, 1]


def test_the_ring_fires_as_the_flow_says_at_the_true_pose_only(slow_clip):
    """At the true pose the ring's events agree with the polarities the flow gives its edges;
    at the pose that takes the ring's inner edge for the locator's outline (a ring width too
    near, the fit that once read the white ring as the 'L') they do not."""
    rec, chunks = slow_clip
    config = hand_held_config()
    t = 300_000
    events = np.concatenate(chunks)
    events = to_columns(events[np.abs(events["t"] - t) <= 1000], config.camera.undistort_table)
    truth = np.linalg.inv(rec.pose_at(np.array([t - 1000, t, t + 1000])))
    geo = config.geometry
    world = geo.locator_corners(config.marker_size_m)
    centre = world.mean(axis=0)[None]
    before, after = (project_ideal(T, config.camera.K, centre)[0] for T in truth[[0, 2]])
    flow = (after - before) / 2.0  # px/ms
    larger = centre + (world - centre) * (geo.locator_side + 2 * geo.ring) / geo.locator_side
    corners = config.camera.project(larger @ truth[1][:3, :3].T + truth[1][:3, 3])
    too_near = pnp(corners, world, config.camera)
    on, agree, worst = ring_support(truth[1], events, flow, config)
    assert on > 100 and agree >= 0.9 and worst >= 0.9
    assert ring_support(too_near, events, flow, config)[1] < config.detector.min_edge_polarity


def test_at_1_px_per_ms_the_first_lock_is_the_right_one():
    """Seed 3 at 1 px/ms: the capture took the black ring around the white one for the ring,
    and the lock (a quarter turn off, 11 cm too near) passed every check for 1.5 s, then came
    back. Now only events with the polarity the flow gives an edge pull the capture onto it."""
    run = _run(1.0, 0.4, seed=3)
    locks = [c for c in run["changes"] if c.state == TRACKING]
    assert locks and locks[0].t_us <= LOCK_WITHIN_US, [c.reason for c in run["changes"]]
    assert run["stats"].losses == 0
    assert np.median(run["err"]) <= TRACKED_RMS_M


@pytest.fixture(scope="module")
def drifting() -> dict:
    """Seed 3 at 0.25 px/ms, the slowest flow of ``bench.tracking``."""
    return _run(0.25, 0.2, seed=3)


def test_a_camera_drifting_too_slowly_for_a_flow_is_not_locked_on_its_smeared_image(drifting):
    """Seed 3 at 0.25 px/ms: the burst gave no flow, and the still path fitted its quadrilateral
    to the smeared phase-locked image, 11 cm off, its 'L' leading at 0.33 where a still
    marker's leads by 1.2 or more (``DetectorParams.min_still_orientation_score``)."""
    assert any(c.state == TRACKING for c in drifting["changes"]), dict(
        drifting["stats"].detection_failures
    )
    assert drifting["err"].max() <= FIRST_POSE_MAX_M


def _assert_locked_right_within_100_ms(run: dict) -> None:
    """Locked within 100 ms, no pose further off than a first pose may be, and tracked to the
    hand-held promise of 1 cm (the median: a re-lock may start a few cm off)."""
    stats = run["stats"]
    assert stats.lock_times_us, dict(stats.detection_failures)
    assert stats.lock_times_us[0] - stats.first_event_us <= 100_000
    assert run["err"][0] <= FIRST_POSE_MAX_M
    assert run["err"].max() <= FIRST_POSE_MAX_M
    assert np.median(run["err"]) <= HAND_HELD_ATE_M


def test_a_slowly_drifting_camera_locks_on_its_burst_square_within_100_ms(drifting):
    """The slow ring fires too little for the capture onto its edges, which settled a ring
    width off and hid the 'L' (first lock at 158 ms); the burst's square reads it clearly
    (``DetectorParams.max_square_flow_px_per_ms``)."""
    _assert_locked_right_within_100_ms(drifting)


def test_a_drift_that_misleads_the_flow_search_locks_on_the_slow_square_within_100_ms():
    """Seed 4 at 0.25 px/ms: the display's OFF tail, whose times follow the scan-out's rows,
    lined up best at flows of 1-2 px/ms, or the burst gave none and the still path's image was
    smeared; nine attempts failed and the first lock came at 248 ms. The square of the burst
    compensated by the sharpest slow flow (``detector._detect_slow``) reads the 'L' at once."""
    _assert_locked_right_within_100_ms(_run(0.25, 0.2, seed=4))


def test_when_the_latest_burst_is_smeared_the_one_before_gives_the_lock():
    """Seed 4 at 1 px/ms: the camera turns about its axis at the first attempt's burst, whose
    corners then move up to 0.5 px/ms apart, and no flow compensates it; the next burst read,
    and with its postponed check the first lock came at 123 ms. The burst a blink before
    reads, and its frames after it are already buffered: the lock stands at the first
    attempt."""
    _assert_locked_right_within_100_ms(_run(1.0, 0.2, seed=4))


def test_a_burst_the_phase_places_off_is_read_where_its_events_lie():
    """Seed 1 at 1 px/ms: the blink map's phase put the first attempts' burst windows a
    millisecond or two off the bursts, none read, and the first lock came at 153 ms. The window
    where the latest burst's ON events lie densest (``locate.densest_burst_us``) reads at the
    first attempt."""
    _assert_locked_right_within_100_ms(_run(1.0, 0.2, seed=1))


def _turned(found: Detection, config: ReceiverConfig, turns: int) -> Detection:
    """``found`` with its corners rolled ``turns`` quarter turns and its pose solved again."""
    corners = np.roll(found.corners_px, -turns, axis=0)
    world = config.geometry.locator_corners(config.marker_size_m)
    return replace(found, corners_px=corners, T_cam_world=pnp(corners, world, config.camera))


def _turned_detections(monkeypatch, turns: int, oriented: bool) -> None:
    """Every detection whose burst showed the 'L' clearly (the others fail) comes back ``turns``
    quarter turns off (corners rolled, pose solved again), as fast motion made them: the ring
    is square, so the turned pose lies on its edges too. ``oriented``: whether it claims its
    burst showed the 'L' that way."""
    detect = receiver_module.detect

    def turned(events, config):
        found = detect(events, config)
        if not found.oriented:  # its turn is a guess: turning it need not make it wrong
            raise MarkerNotFound("no clear 'L'")
        return replace(_turned(found, config, turns), oriented=oriented)

    monkeypatch.setattr(receiver_module, "detect", turned)


@pytest.fixture
def quarter_turned_detection(monkeypatch):
    _turned_detections(monkeypatch, 1, oriented=True)


@pytest.mark.parametrize("turns", [0, 1])
def test_a_burst_without_a_clear_l_locks_only_if_the_frames_read_it_that_way_up(
    slow_clip, monkeypatch, turns
):
    """Where the burst shows the ring but no clear 'L', its best guess of the turn stands only
    if the frames read through the pose confirm it: a quarter turn off they read the 'L' turned,
    or the ring too faintly for a moving lock."""
    _turned_detections(monkeypatch, turns, oriented=False)
    run = _replay(*slow_clip)
    if turns == 0:
        assert [c.state for c in run["changes"]] == [TRACKING], [c.reason for c in run["changes"]]
        assert run["err"][0] <= FIRST_POSE_MAX_M
        assert sum(f.accepted for f in run["frames"]) > 10
    else:
        assert not run["changes"]
        refused = ("'L' this way up", "inner locator reads at")
        assert any(r in f for f in run["stats"].detection_failures for r in refused)


def test_a_lock_a_quarter_turn_off_is_dropped_within_a_few_frames(
    slow_clip, quarter_turned_detection
):
    """Issue 4: such a lock passed the locator score and the fit ratio, and read garbage to the
    clip's end; the lock's verification on the frames after its burst, or the 'L' read through
    the pose, must end it."""
    run = _replay(*slow_clip)
    config = hand_held_config()
    changes = run["changes"]
    locks = [c for c in changes if c.state == TRACKING]
    drops = [c for c in changes if c.state == DETECTING]
    failures = run["stats"].detection_failures
    refused = ("'L'", "inner locator reads at")
    assert locks or any(r in reason for reason in failures for r in refused), dict(failures)
    within_us = (config.decoder.turn_frames + 1) * config.frame_us
    judged = [c for c in locks if c.t_us + within_us <= slow_clip[0].duration_us]
    assert judged or not locks, "no lock early enough in the clip to judge"
    assert len(drops) >= len(judged), "a quarter-turned lock stood to the clip's end"
    for lock, drop in zip(judged, drops[: len(judged)], strict=True):
        assert "'L' does not read" in drop.reason
        assert drop.t_us - lock.t_us <= within_us
    accepted = sum(f.accepted for f in run["frames"])
    assert accepted <= config.decoder.turn_frames * len(locks)


def _detection(config: ReceiverConfig, T_cam_world: np.ndarray, turns: int) -> Detection:
    """A detection of the locator seen from ``T_cam_world``, its corners ``turns`` off."""
    world = config.geometry.locator_corners(config.marker_size_m)
    corners = config.camera.project(world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3])
    found = Detection(corners, T_cam_world, 0, 0.0, config.blink_hz, 1.0, 1.0, np.zeros(2))
    return _turned(found, config, turns)


@pytest.mark.parametrize("turns", range(4))
def test_a_detection_takes_the_quarter_turn_nearest_a_recent_pose(turns):
    config = hand_held_config()
    centre = config.geometry.locator_corners(config.marker_size_m).mean(axis=0)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [8, -12, 25], degrees=True).as_matrix()
    T[:3, 3] = [0.03, -0.02, 0.6] - T[:3, :3] @ centre
    prior = T.copy()  # a verified frame's pose, the camera having turned a little since
    prior[:3, :3] = Rotation.from_euler("z", 6, degrees=True).as_matrix() @ T[:3, :3]
    found = nearest_turn(_detection(config, T, turns), prior, config)
    truth = _detection(config, T, 0)
    assert np.allclose(found.corners_px, truth.corners_px)
    assert np.allclose(found.T_cam_world, truth.T_cam_world, atol=1e-6)
    assert found.oriented == (turns == 0)  # a changed turn must be confirmed by the frames


def test_a_relock_soon_after_a_verified_frame_keeps_its_turn(slow_clip, monkeypatch):
    """Every detection after the first comes back half a turn off, as two relocks of
    0.25 px/ms paths did (and then tracked 20 cm off): the pose of the latest verified frame
    must turn it back. The first lock is lost once after its first verified frame."""
    detect, calls = receiver_module.detect, []

    def misread(events, config):
        found = detect(events, config)
        calls.append(found)
        return found if len(calls) == 1 else _turned(found, config, 2)

    off_edges, push, lost, verified = EdgeTracker.off_edges, StreamDecoder.push, [], []

    def noting_verified(self, bits, confidence):
        messages = push(self, bits, confidence)
        verified.append(self.verified_bits > 0)
        return messages

    def lose_once(self):
        if not lost and any(verified):
            lost.append(True)
            return "lost once by the test"
        return off_edges(self)

    monkeypatch.setattr(receiver_module, "detect", misread)
    monkeypatch.setattr(StreamDecoder, "push", noting_verified)
    monkeypatch.setattr(EdgeTracker, "off_edges", lose_once)
    run = _replay(*slow_clip)
    locks = [c.t_us for c in run["changes"] if c.state == TRACKING]
    assert lost and len(locks) == 2, [(c.t_us, c.reason) for c in run["changes"]]
    relocked = run["err"][run["t"] >= locks[1]]
    assert len(relocked) and relocked.max() <= FIRST_POSE_MAX_M


def test_the_l_check_needs_at_least_one_frame():
    with pytest.raises(ValueError, match="turn_frames must be at least 1"):
        DecoderParams(turn_frames=0)


def test_a_correct_lock_under_motion_stands(slow_hand):
    """The 'L' check must not fire on a pose that tracks the marker."""
    assert slow_hand["stats"].losses == 0, [c.reason for c in slow_hand["changes"]]


class _NeverVerifies(StreamDecoder):
    """The stream decoder of a lock that reads garbage: no frame passes its check."""

    def push(self, bits: np.ndarray, confidence: np.ndarray | None = None) -> list:
        return []


def _unverifiable(rec: Recording, chunks: list[np.ndarray], probation_frames: int) -> dict:
    """``_replay`` with the given probation, where no frame ever passes its check."""
    base = hand_held_config()
    config = replace(base, decoder=replace(base.decoder, probation_frames=probation_frames))
    return _replay(rec, chunks, config, _NeverVerifies(profile=config.profile, cells=config.cells))


def test_a_lock_under_motion_ends_its_probation_at_its_first_verified_frame(slow_hand):
    """The right lock's frames pass their check well within the probation."""
    frames = slow_hand["frames"]
    first = next(k for k, f in enumerate(f for f in frames if f.accepted) if f.payload_bits)
    assert first < hand_held_config().decoder.probation_frames


def test_a_lock_under_motion_whose_frames_never_verify_is_dropped(slow_clip):
    """A quarter-turned lock a ring width too near reads the static ring as the 'L' and passes
    every other check; only the frame check can tell. Here the check always fails."""
    run = _unverifiable(*slow_clip, probation_frames=3)
    changes = run["changes"]
    drops = [c for c in changes if c.state == DETECTING]
    assert drops, "the lock stood without a single verified frame"
    assert changes[0].state == TRACKING and changes[1] == drops[0]
    assert drops[0].reason == "no frame passed its check since the lock"
    read = [f for f in run["frames"] if f.read.t_us <= drops[0].t_us and f.accepted]
    assert len(read) == 3  # the lock's frames (from its burst, before the lock's StateChange)


def test_a_verified_frame_settles_a_lock_under_motion_whatever_its_fit_ratio(slow_clip):
    """A slow ring's few events can leave a right pose's fit ratio low; only a right pose reads
    a frame that passes its check (here no fit ratio is high enough)."""
    base = hand_held_config()
    config = replace(base, detector=replace(base.detector, min_lock_fit_ratio=1.01))
    assert _replay(*slow_clip, config)["stats"].lock_times_us
    never = _replay(*slow_clip, config, _NeverVerifies(profile=config.profile, cells=config.cells))
    assert not never["stats"].lock_times_us
    assert any("lie on its edges" in r for r in never["stats"].detection_failures)


def test_a_still_lock_whose_frames_never_verify_is_dropped_soon():
    """A still camera reads a right lock's frames cleanly from the first: frames that keep
    failing their check mean a wrong lock, which goes within ``still_probation_us`` of frames
    (its poses all tentative), and detection resumes."""
    scene = replace(hand_held_scene(0.5, 0), motion=StaticMotion(distance_m=0.6))
    rec = simulate(scene, duration_s=0.4, chunk_us=10_000)
    run = _unverifiable(rec, list(rec), probation_frames=20)
    changes = run["changes"]
    assert [c.state for c in changes[:2]] == [TRACKING, DETECTING]
    assert changes[1].reason == "no frame passed its check since the lock"
    assert changes[1].t_us - changes[0].t_us <= 110_000


def test_the_probation_needs_at_least_one_frame():
    with pytest.raises(ValueError, match="probation_frames must be at least 1"):
        DecoderParams(probation_frames=0)


@pytest.mark.slow
def test_the_paper_profile_at_4_px_per_ms_drops_its_wrong_lock():
    """Issue 4's first case, the comparison experiment's ``paper`` run at 4 px/ms (seed 1): it
    locked a quarter turn off with the ring fitted two cells too large and read garbage (BER
    47 %) for the whole clip. The wrong lock must end within a few frames, and a right one
    follow."""
    scene = paper_hand_held_scene(
        StreamEncoder(clip_message("paper", 16, 60.0, 2.0, 1), profile="paper", cells=16),
        4.0,
        1,
        (480, 270),
    )
    config = ReceiverConfig(
        scene.camera, profile="paper", marker_size_m=scene.marker_size_m, tracker=HAND_HELD_TRACKER
    )
    rec = simulate(scene, duration_s=2.0, chunk_us=10_000)
    run = _replay(rec, list(rec), config)
    limit = (config.decoder.turn_frames + 1) * config.frame_us
    assert max(_wrong_lock_spans_us(run), default=0) <= limit
    good = run["err"] < FIRST_POSE_MAX_M
    assert good.mean() > 0.5, f"{good.mean():.0%} of the poses within 5 cm"


def _assert_locks_and_tracks(run: dict) -> None:
    locks = run["stats"].lock_times_us
    assert locks and locks[0] <= LOCK_WITHIN_US, (
        f"no lock within {LOCK_WITHIN_US / 1e3:.0f} ms: {dict(run['stats'].detection_failures)}"
    )
    err = run["err"]
    assert err[0] <= FIRST_POSE_MAX_M, f"first pose {err[0] * 100:.1f} cm off"
    assert np.sqrt(np.mean(err**2)) <= TRACKED_RMS_M, f"RMS {np.sqrt(np.mean(err**2)):.3f} m"
    p95 = np.percentile(err, 95)
    assert p95 <= TRACKED_P95_M, f"95% of the tracked poses within {p95:.3f} m"


def test_detects_and_tracks_at_half_a_pixel_per_ms(slow_hand):
    _assert_locks_and_tracks(slow_hand)


@pytest.mark.slow
def test_detects_and_tracks_at_1_px_per_ms():
    """Seed 1 locked at 665 ms before its burst's 'L' was left to the frames when unclear."""
    _assert_locks_and_tracks(_run(1.0, 1.0, seed=1))


@pytest.mark.slow
@pytest.mark.xfail(
    reason="at 2 px/ms and 4 px per cell wrong ring fits agree with the flow's polarities as "
    "well as right ones (+0.97 to +1.0): five 1 s clips tracked poses more than 5 cm off for "
    "0.5 s, and this one first locks 9 cm off at 333 ms",
    strict=False,
)
def test_detects_and_tracks_at_2_px_per_ms():
    _assert_locks_and_tracks(_run(2.0, 1.0, seed=1))
