"""Unit tests of the pipeline's building blocks on hand-made inputs (no simulator)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from eventocc.occ.marker import MarkerGeometry
from eventocc.occ.profiles import get_profile
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.events import make_events
from eventocc.receiver.pipeline import decoder, detector
from eventocc.receiver.pipeline.buffer import EventBuffer, first_at, to_columns
from eventocc.receiver.pipeline.config import DecoderParams, FilterParams, ReceiverConfig
from eventocc.receiver.pipeline.decoder import (
    CellReader,
    FrameClock,
    cell_side_px,
    on_events_per_pixel,
    read_stride,
)
from eventocc.receiver.pipeline.detector import (
    MarkerNotFound,
    _binned_blink,
    _period_match,
    blink_heatmap,
    blink_phase,
    check_quadrilateral,
    largest_region,
    locator_band,
    quadrilateral,
)
from eventocc.receiver.pipeline.filters import EventFilter
from eventocc.receiver.pipeline.locate import Box
from eventocc.receiver.pipeline.metrics import pose_errors, umeyama
from eventocc.receiver.pipeline.pose import (
    DARK_SIDE,
    PoseHistory,
    pnp,
    project_ideal,
    refine_pose,
)
from eventocc.receiver.pipeline.report import FrameTruth
from eventocc.receiver.pipeline.triage import EventTriage
from eventocc.receiver.poses import make_pose
from tests.cells import locator_block, on_only

K = np.array([[300.0, 0, 173], [0, 300.0, 130], [0, 0, 1]])
SIZE = 0.272


def _looking_at_marker(distance: float = 0.6) -> np.ndarray:
    """T_cam_world of a camera facing the marker's centre from ``distance`` metres."""
    return make_pose(np.eye(3), [-SIZE / 2, -SIZE / 2, distance])


def test_refractory_filter_drops_bursts_and_keeps_spaced_events():
    ev = make_events([0, 100, 2000, 2100, 5000], [3] * 5, [4] * 5, [1, 1, -1, 1, 1])
    f = EventFilter(
        FilterParams(refractory=True, same_polarity_us=1000, opposite_polarity_us=500), 8, 8
    )
    assert f(ev)["t"].tolist() == [0, 2000, 5000]


def test_neighbourhood_filter_needs_supporting_neighbours():
    ev = make_events([0, 10, 20, 30, 40], [1, 2, 1, 2, 6], [1, 1, 2, 2, 6], [1] * 5)
    f = EventFilter(FilterParams(neighbourhood=True, min_neighbours=3), 8, 8)
    assert f(ev)["t"].tolist() == [30]  # the 4th of a 2x2 block; the far one stays alone


def test_filter_rejects_bad_parameters():
    with pytest.raises(ValueError, match="radius"):
        EventFilter(FilterParams(neighbourhood=True, radius_px=0), 8, 8)


@settings(max_examples=25, deadline=None)
@given(phase=st.floats(0, 0.999), jitter=st.floats(0, 300))
def test_blink_phase_recovers_burst_time(phase, jitter):
    rng = np.random.default_rng(0)
    period = 1e6 / 30
    bursts = 1000 + phase * period + period * np.arange(15)
    t = np.repeat(bursts, 50) + rng.normal(0, jitter + 1, 750)
    burst, ratio = blink_phase(t, 0, 500_000, 30.0)
    err = (burst - bursts[0] + period / 2) % period - period / 2
    assert abs(err) < 200 and ratio > 0.8


def test_quadrilateral_orders_corners_clockwise_and_checks_shape():
    pts = np.array([[10, 10], [60, 12], [58, 62], [9, 59], [30, 30]])
    quad = quadrilateral(pts)
    assert len(quad) == 4
    x, y = quad[:, 0], quad[:, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0
    cfg = ReceiverConfig(CameraModel(346, 260, K))
    check_quadrilateral(quad, cfg.detector, cfg.camera)
    with pytest.raises(MarkerNotFound, match="not square"):
        check_quadrilateral(
            np.array([[0, 0], [100, 0], [100, 20], [0, 20.0]]), cfg.detector, cfg.camera
        )


@pytest.mark.parametrize("view_deg", [0.0, 30.0, 45.0, 60.0])
def test_a_square_passes_at_any_view_a_skewed_quadrilateral_does_not(view_deg):
    # A near square seen at 45-60 deg shows image corners far from right angles (cos > 0.4),
    # which the camera's intrinsics undo; an image parallelogram of the same size does not pass.
    cam = CameraModel(640, 480, np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]]))
    cfg = ReceiverConfig(cam)
    turn = Rotation.from_euler("xy", [view_deg, 20.0], degrees=True).as_matrix()
    square = np.array([[-0.1, -0.1, 0], [0.1, -0.1, 0], [0.1, 0.1, 0], [-0.1, 0.1, 0]])
    quad = cam.project(square @ turn.T + [0.05, 0.03, 0.35])
    check_quadrilateral(quad, cfg.detector, cam)
    sheared = quad + np.array([[0, 0], [0, 0], [100, 0], [100, 0]])
    with pytest.raises(MarkerNotFound, match=r"not right angles|not square"):
        check_quadrilateral(sheared, cfg.detector, cam)


def test_pnp_solves_a_square_seen_head_on():
    """OpenCV's IPPE returns NaN for these corners of a still test scene's locator: a square
    centred on the principal point, its sides equal to within 1e-4 px."""
    cam = CameraModel(346, 260, K, np.zeros(5))
    lo, hi = 0.02472727272727273, 0.2472727272727273
    world = np.array([[lo, lo, 0], [hi, lo, 0], [hi, hi, 0], [lo, hi, 0]])
    near, far = 116.88774108886719, 229.11233520507812
    top, bottom = 73.88774108886719, 186.1122589111328
    corners = np.array([[near, top], [far, top], [far, bottom], [near, bottom]])
    T = pnp(corners, world, cam)
    assert np.allclose(project_ideal(T, K, world), corners, atol=1e-3)


def test_refine_pose_recovers_a_perturbed_pose_from_edge_points():
    geo = MarkerGeometry(16)
    edges = geo.tracked_edges(SIZE)
    T_true = _looking_at_marker() @ make_pose(
        Rotation.from_euler("xyz", [5, -8, 3], degrees=True).as_matrix(), [0.01, -0.02, 0.0]
    )
    s = np.linspace(0.05, 0.95, 40)
    world = edges[:, :1] + s[None, :, None] * (edges[:, 1:] - edges[:, :1])  # (8, 40, 3)
    pts = project_ideal(T_true, K, world).reshape(-1, 2)
    edge = np.repeat(np.arange(8), 40)
    T0 = T_true @ make_pose(
        Rotation.from_euler("xyz", [1, -1, 2], degrees=True).as_matrix(), [0.01, 0.005, 0.02]
    )
    T, cost, dark, _ = refine_pose(T0, K, pts, edge, edges, 1.0, 20)
    assert cost < 1e-6
    assert abs(dark) < 1e-4
    assert np.allclose(T[:3, 3], T_true[:3, 3], atol=1e-4)


def test_refine_pose_fits_the_events_offset_to_the_dark_side_of_unevenly_firing_edges():
    """A log sensor's events of a moving edge lie on its dark side. When the edges fire unevenly
    (here the right side of the ring ten times as much as the others) that offset tilts a pose
    fitted to the edges themselves; fitted with the pose, it leaves the pose where it is."""
    geo = MarkerGeometry(16)
    edges = geo.tracked_edges(SIZE)
    T_true = _looking_at_marker() @ make_pose(
        Rotation.from_euler("xyz", [5, -8, 3], degrees=True).as_matrix(), [0.01, -0.02, 0.0]
    )
    counts = np.array([8, 80, 8, 8, 8, 80, 8, 8])
    edge = np.repeat(np.arange(8), counts)
    s = np.concatenate([np.linspace(0.05, 0.95, n) for n in counts])
    world = edges[edge, 0] + s[:, None] * (edges[edge, 1] - edges[edge, 0])
    pts = project_ideal(T_true, K, world)
    a, b = project_ideal(T_true, K, edges[edge, 0]), project_ideal(T_true, K, edges[edge, 1])
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    right = np.stack([-d[:, 1], d[:, 0]], axis=1)  # the sign of positive distances
    pts += 0.8 * DARK_SIDE[edge, None] * right

    T, _, dark, _ = refine_pose(T_true, K, pts, edge, edges, 1.0, 30)
    assert dark == pytest.approx(0.8, abs=0.01)
    assert np.allclose(T[:3, 3], T_true[:3, 3], atol=1e-4)
    outer = edge < 4  # one boundary alone: the offset is the distance's, and stays as given
    _, _, kept, _ = refine_pose(T_true, K, pts[outer], edge[outer], edges, 1.0, 30, 0.3)
    assert kept == 0.3


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-6, 1e-3, 0.5, 3.0, np.pi - 1e-2, np.pi - 1e-5])
def test_pose_history_turns_and_moves_evenly_between_its_poses(angle):
    """Rotations as slerp gives them at any angle between two poses: a tiny one (which
    OpenCV's Rodrigues rounds to none below 1e-5 rad) and one near a half turn (where the
    rotation's antisymmetric part vanishes)."""
    rng = np.random.default_rng(7)
    axis = rng.normal(size=3)
    R0 = Rotation.random(random_state=rng)
    R1 = R0 * Rotation.from_rotvec(angle * axis / np.linalg.norm(axis))
    t0, t1 = rng.normal(size=3), rng.normal(size=3)
    history = PoseHistory()
    history.restart(1000, make_pose(R0.as_matrix(), t0))
    history.append(2000, make_pose(R1.as_matrix(), t1))
    times = np.array([1000.0, 1250.0, 1500.0, 1999.0])
    T = history.at(times)
    f = (times - 1000) / 1000
    turned = Slerp([1000, 2000], Rotation.concatenate([R0, R1]))(times).as_matrix()
    assert np.abs(T[:, :3, :3] - turned).max() < 1e-12
    assert np.allclose(T[:, :3, 3], t0 + f[:, None] * (t1 - t0), rtol=0, atol=1e-12)


def test_pose_history_holds_its_ends_outside_them_and_forgets_only_what_is_not_needed():
    history = PoseHistory()
    with pytest.raises(ValueError, match="empty"):
        history.at([0])
    poses = [make_pose(np.eye(3), [i, 0.0, 0.0]) for i in range(100)]
    history.restart(0, poses[0])
    for i in range(1, 100):
        history.append(10 * i, poses[i])
    assert np.array_equal(history.at([-5, 995, 2000]), [poses[0], poses[99], poses[99]])
    history.forget_before(505)  # the pose at 500 still places 505
    assert history.at([505])[0, 0, 3] == pytest.approx(50.5)
    assert len(history) < 100
    history.restart(3000, poses[7])
    assert len(history) == 1 and np.array_equal(history.at([0, 5000]), [poses[7], poses[7]])


def test_umeyama_undoes_a_rigid_motion_and_ate_is_zero():
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(50, 3))
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    Rf, tf = umeyama(pos, pos @ R.T + [1, 2, 3])
    assert np.allclose(Rf, R) and np.allclose(tf, [1, 2, 3])
    T = make_pose(np.broadcast_to(np.eye(3), (50, 3, 3)), pos)
    err = pose_errors(np.arange(50) * 10_000, T, T)
    assert err.ate_rmse_m < 1e-9 and err.rpe_rot_rmse_deg < 1e-6
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(pos[:2], pos[:2])


def test_buffer_keeps_raw_chunks_and_cuts_time_windows():
    buf = EventBuffer()
    first = make_events([0, 10, 20], [1, 2, 3], [4, 5, 6], [1, -1, 1])
    buf.append(first)
    buf.append(make_events([30, 40], [7, 0], [1, 2], [1, 1]))
    assert np.shares_memory(buf.between(0, 15), first)  # kept as they came, not copied
    window = buf.between(10, 35)
    assert window["t"].tolist() == [10, 20, 30] and window["x"].tolist() == [2, 3, 7]
    assert len(buf.between(50, 60)) == 0
    buf.append(make_events([300], [0], [0], [1]))
    buf.forget_before(25)  # the chunks that end before go
    assert buf.span == (30, 300) and buf.between(0, 400)["t"].tolist() == [30, 40, 300]


def test_columns_carry_ideal_coordinates_from_the_undistortion_table():
    cam = CameraModel(8, 8, K, np.array([-0.1, 0.0, 0.0, 0.0, 0.0]))
    cols = to_columns(
        make_events([0, 10, 20], [1, 2, 3], [4, 5, 6], [1, -1, 1]), cam.undistort_table
    )
    assert np.allclose(cols["xu"], cam.undistort_table[[4, 5, 6], [1, 2, 3], 0])
    assert cols[cols["p"] > 0]["t"].tolist() == [0, 20]


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(0, 50), max_size=30), st.integers(-5, 60))
def test_first_at_matches_searchsorted(times, value):
    t = np.sort(np.array(times, np.int64))
    assert first_at(t, value) == np.searchsorted(t, value)


def _triage(both: bool = False) -> EventTriage:
    cam = CameraModel(32, 24, K)
    return EventTriage(cam.undistort_table, gap_us=1000, both_polarities=both, epoch_us=0)


def test_triage_keeps_when_each_pixel_burst_began():
    triage = _triage()
    triage.marks_us = (50, 2000)  # a frame's window begins, and a time within it
    # pixel (3, 4): bursts at 100..300, 3000 and 5000; pixel (5, 6): ON at 400, OFF at 5100
    triage(
        make_events(
            [100, 200, 300, 400, 3000, 5000, 5100],
            [3, 3, 3, 5, 3, 3, 5],
            [4, 4, 4, 6, 4, 4, 6],
            [1, 1, 1, 1, 1, 1, -1],
        )
    )
    # (3, 4) began again at 5000, but its first bursts from each mark on are kept too; (5, 6)
    # went off at 5100, which an ON-only surface does not keep
    bursts = triage.bursts(0, 1000, (0, 32, 0, 24))
    assert bursts["t"].tolist() == [100, 400] and bursts["x"].tolist() == [3, 5]
    later = triage.bursts(1000, 6000, (0, 32, 0, 24))
    assert later["t"].tolist() == [3000, 5000] and later["p"].tolist() == [1, 1]
    assert len(triage.bursts(0, 6000, (0, 3, 0, 24))) == 0  # outside the box
    both = _triage(both=True)
    both(make_events([100, 5100], [5, 5], [6, 6], [1, -1]))
    assert sorted(both.bursts(0, 6000, (0, 32, 0, 24))["p"].tolist()) == [-1, 1]


def test_an_event_of_the_other_polarity_ends_a_burst():
    """An edge's image that darkens a pixel and relights it within the gap (a moving camera)
    starts a new burst: the switch after it is seen at its own time."""
    triage = _triage()
    triage(make_events([100, 200, 600, 700], [3] * 4, [4] * 4, [1, -1, 1, 1]))
    assert triage.bursts(0, 1000, (0, 32, 0, 24))["t"].tolist() == [100, 600]
    triage.reset(epoch_us=0)
    triage(make_events([100, 200, 600], [3] * 3, [4] * 3, [1, 1, 1]))  # no OFF: one burst
    assert triage.bursts(0, 1000, (0, 32, 0, 24))["t"].tolist() == [100]


def test_a_burst_running_into_its_pixels_read_gate_ends_there():
    """A pixel that the moving camera turned onto a fading cell's light fires ON before its own
    cell switches on; with no OFF between, the switch would only continue that burst and go
    unread. The gate's opening (a plane over the raw pixels) cuts the burst."""
    events = make_events([100, 500, 900, 1300], [10] * 4, [4] * 4, [1, 1, 1, 1])
    triage = _triage()
    triage(events)
    assert triage.bursts(0, 2000, (0, 32, 0, 24))["t"].tolist() == [100]
    triage.reset(epoch_us=0)
    triage.cut_plane = (700.0, 20.0, 0.0)  # the gate opens at x = 10 at 900 us
    triage(events)
    assert triage.bursts(0, 2000, (0, 32, 0, 24))["t"].tolist() == [100, 900]  # first, latest
    triage.reset(epoch_us=0)
    assert triage.cut_plane is None
    both = _triage(both=True)  # ``fast`` reads both polarities and is never cut
    both.cut_plane = (700.0, 20.0, 0.0)
    both(events)
    assert both.bursts(0, 2000, (0, 32, 0, 24))["t"].tolist() == [100]


def test_triage_passes_only_events_near_the_tracked_edges():
    triage = _triage()
    events = make_events([1, 2, 3], [2, 30, 16], [2, 20, 2], [1, -1, 1])
    assert len(triage(events)) == 0  # nothing tracked yet
    triage.track_near(np.array([[0.0, 0.0]]), np.array([[31.0, 0.0]]), reach_px=4.0)
    near = triage(events)
    assert near["t"].tolist() == [1, 3]  # the top row; the far corner stays out
    assert np.allclose(near["xu"], [2, 16]) and near["p"].tolist() == [1, 1]


def test_triage_reset_forgets_bursts_and_edges():
    triage = _triage()
    triage.track_near(np.array([[0.0, 0.0]]), np.array([[31.0, 0.0]]), reach_px=4.0)
    triage(make_events([10], [2], [2], [1]))
    triage.reset(epoch_us=100)
    assert len(triage.bursts(0, 200, (0, 32, 0, 24))) == 0
    assert len(triage(make_events([150], [2], [2], [1]))) == 0  # no edges tracked any more


def test_triage_surface_survives_a_long_stream():
    triage = _triage()
    late = (1 << 31) + 123  # beyond int32 microseconds since the epoch
    triage(make_events([late, late + 10], [1, 1], [1, 1], [1, 1]))
    assert triage.bursts(late - 5, late + 5, (0, 32, 0, 24))["t"].tolist() == [late]


def test_locator_band_is_the_outer_cell_of_the_blinking_square():
    region = np.zeros((60, 60), np.uint8)
    region[10:50, 10:50] = 1  # 40 px for a 10-cell locator: 4 px cells
    band = locator_band(region, locator_side=10)
    assert band[10, 30] and band[30, 13] and not band[30, 30] and not band[30, 15]
    assert not band[5, 5]


def test_burst_image_tells_a_pixel_that_fires_at_two_bursts_from_one_switch():
    """A static ring that lit up when the marker appeared fires several ON events in phase
    once; a blinking cell fires at every burst, however few events each time."""
    period = 10_000
    events = sorted(
        [(10_000, 1), (20_000, 1)]  # blinks: one event at each of two bursts
        + [(20_000 + 50 * i, 2) for i in range(6)]  # one switch, six events
        + [(15_000, 3), (25_000, 3)]  # fires twice, in antiphase
    )
    t, x = zip(*events, strict=True)
    image, blinks = detector.burst_image(
        [make_events(t, x, [0] * len(t), [1] * len(t))], 0.0, period, np.ones((1, 4), np.uint8)
    )
    assert image[0, 1] > 0 and image[0, 2] > 0 and image[0, 3] == 0
    assert blinks.tolist() == [[False, True, False, False]]


def test_in_company_drops_stray_pixels_and_keeps_a_sparse_square_and_its_corners():
    rng = np.random.default_rng(0)
    lit = np.zeros((80, 80), bool)
    lit[20:60, 20:60] = rng.random((40, 40)) < 0.3  # 10 cells of 4 px, sparse
    lit[20, 20] = lit[59, 59] = True
    strays = [(8, 8), (21, 66), (70, 40)]
    for y, x in strays:
        lit[y, x] = True
    kept = detector._in_company(lit, 4.0)
    assert not any(kept[y, x] for y, x in strays)
    assert np.array_equal(kept[20:60, 20:60], lit[20:60, 20:60])
    alone = np.zeros_like(lit)
    alone[tuple(zip(*strays, strict=True))] = True
    assert not detector._in_company(alone, 4.0).any()


def test_frame_clock_follows_a_slightly_fast_display():
    clock = FrameClock(first_burst_us=1000.0, frame_us=10_000.0, rows=18)
    assert not clock.timed
    for m in range(6):
        clock.observe(m, 1000.0 + m * 10_010.0, slope_us=50.0)
    assert clock.timed
    assert clock.period_us == pytest.approx(10_010.0) and clock.mid(10) == pytest.approx(101_100.0)


@pytest.mark.parametrize("profile", ["paper", "fast"])
def test_read_window_narrows_as_soon_as_one_frame_timed_the_clock(profile):
    # Under motion pixels fire again within the wide search gate, and only their latest burst
    # is kept: every frame read after the first timed one must use the narrow read gate.
    config = ReceiverConfig(CameraModel(346, 260, K), cells=16, profile=profile)
    reader = CellReader(config, first_burst_us=0.0)
    searching = np.diff(reader.window(1))[0]
    reader.clock.observe(0, 200.0, slope_us=0.0)
    reading = np.diff(reader.window(1))[0]
    assert reading == pytest.approx(np.diff(reader.gate)[0], abs=1)
    assert reading < 0.8 * searching


def test_the_read_gate_opens_row_by_row_down_the_locator():
    config = ReceiverConfig(CameraModel(346, 260, K), cells=16, profile="robust")
    geo, size = config.geometry, config.marker_size_m
    centre = geo.locator_corners(size).mean(axis=0)
    facing = make_pose(np.eye(3), np.array([-centre[0], -centre[1], 0.5]))
    reader = CellReader(config, first_burst_us=0.0)
    assert reader.gate_opens(3, facing) is None  # no clock yet
    for m in range(3):
        reader.clock.observe(m, 100.0 + m * config.frame_us, slope_us=50.0)
    assert reader.gate_opens(3, facing) is None  # the gate is not narrowed yet
    reader.gate = (-400.0, 600.0)
    reader._spans = {1: np.array(reader.gate)}  # the ON bursts' spread, fitted
    a, b, c = reader.gate_opens(3, facing)
    n = geo.locator_side
    for v in (0.5, n / 2, n - 0.5):  # row centres on the grid, then their pixels
        plane = np.linalg.inv(reader._plane_to_grid) @ [n / 2, v, 1]
        x, y = config.camera.project((facing[:3, :3] @ [*plane[:2], 0] + facing[:3, 3])[None])[0]
        want = reader.clock.mid(3) + (v - 0.5 - n / 2) * 50.0 - 400.0
        assert a + b * x + c * y == pytest.approx(want, abs=1.0)
    reader.clock.observe(3, reader.clock.mid(3) + 300.0, slope_us=50.0)  # 300 us off
    assert reader.gate_opens(4, facing) is None  # more than half the gate's 400 us lead


@pytest.mark.parametrize(
    ("px_per_cell", "want", "stride"),
    [(7, 8.0, 1), (20, 8.0, 2), (30, 8.0, 3), (40, 8.0, 5), (40, None, 1)],
)
def test_large_cells_are_read_with_a_pixel_stride(px_per_cell, want, stride):
    config = ReceiverConfig(
        CameraModel(346, 260, K), cells=16, decoder=DecoderParams(read_px_per_cell=want)
    )
    geo, size = config.geometry, config.marker_size_m
    centre = geo.locator_corners(size).mean(axis=0)
    distance = K[0, 0] * geo.cell_size_m(size) / px_per_cell
    facing = make_pose(np.eye(3), np.array([-centre[0], -centre[1], distance]))
    assert read_stride(config, cell_side_px(config, facing)) == stride
    assert cell_side_px(config, facing) == pytest.approx(px_per_cell)
    behind = make_pose(np.eye(3), np.array([-centre[0], -centre[1], -distance]))
    assert (
        read_stride(config, cell_side_px(config, behind)) == 1 and cell_side_px(config, behind) == 0
    )


@pytest.mark.parametrize(("on_per_pixel", "stride"), [(None, 3), (8.0, 3), (3.0, 2), (1.5, 1)])
def test_a_thinned_readout_is_read_with_a_finer_stride(on_per_pixel, stride):
    # 24 px per cell keep 3 x 3 blocks to 8 px per side; a pixel firing half as often as a
    # dense sensor's says half as much, so it takes a finer stride to read the same.
    config = ReceiverConfig(CameraModel(346, 260, K), cells=16)
    assert read_stride(config, 24.0, on_per_pixel) == stride


def test_on_events_per_pixel_counts_the_lit_half_of_the_locator_per_blink():
    # 40 x 40 px locator, 10 blinks at 60 Hz over 20 x 40 lit pixels, 3 ON events each, plus
    # OFF events and ON events outside it, which do not count.
    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.arange(100, 120), np.arange(50, 90))
    lit = np.repeat(np.c_[xs.ravel(), ys.ravel()], 30, axis=0)
    t = np.sort(rng.integers(0, 10 * 16_667, len(lit)))
    ev = make_events(
        np.r_[t, t[:100], t[:100]],
        np.r_[lit[:, 0], lit[:100, 0], np.full(100, 300)],
        np.r_[lit[:, 1], lit[:100, 1], np.full(100, 200)],
        np.r_[np.ones(len(t)), -np.ones(100), np.ones(100)],
    )
    ev = ev[np.argsort(ev["t"], kind="stable")]
    corners = np.array([[99.5, 49.5], [139.5, 49.5], [139.5, 89.5], [99.5, 89.5]])
    assert on_events_per_pixel([ev[:5000], ev[5000:]], corners, 60.0) == pytest.approx(3.0, rel=0.1)
    assert on_events_per_pixel([], corners, 60.0) == 0.0


def test_cells_read_against_the_locator_ring_and_score_its_contrast():
    config = ReceiverConfig(CameraModel(346, 260, K), cells=8)
    reader = CellReader(config, first_burst_us=0.0)
    geo = config.geometry
    truth = np.random.default_rng(2).integers(0, 2, (8, 8))
    frame = geo.inner_locator.astype(float) * 12.0 + 0.5  # white ring cells ~12 events/px
    frame[1:-1, 1:-1] = truth * 9.0 + 0.8  # a bit dimmer payload, a noise floor
    read = reader._classify(0, on_only(frame), 1000)
    assert np.array_equal(read.bits, truth) and read.locator_score > 0.9
    absent = reader._classify(0, on_only(np.full_like(frame, 0.3)), 10)
    assert absent.locator_score < config.decoder.min_locator_score


def test_white_cells_that_a_capped_readout_spreads_read_on_the_square_root_scale():
    # Densities as a 7-8 Mev/s cap leaves a `robust` frame's, one ON event per lit pixel per
    # transition: its white cells spread over 0.12-0.6, its black ones fire hardly at all. A
    # threshold midway between the clusters' means (~0.18) reads the dimmest white cells black;
    # the square root's does not. A dense readout's reader keeps the linear scale.
    config = ReceiverConfig(CameraModel(346, 260, K), cells=16)
    rng = np.random.default_rng(3)
    n = config.geometry.locator_side
    truth = rng.integers(0, 2, (n - 2, n - 2))
    frame = config.geometry.inner_locator * rng.uniform(0.2, 0.6, (n, n))
    shape = truth.shape
    black = np.where(rng.random(shape) < 0.05, rng.uniform(0.0, 0.04, shape), 0.0)
    frame[1:-1, 1:-1] = np.where(truth, rng.uniform(0.12, 0.6, shape), black)
    sparse = CellReader(config, first_burst_us=0.0, sparse=True)
    assert np.array_equal(sparse._classify(0, on_only(frame), 1000).bits, truth)
    dense = CellReader(config, first_burst_us=0.0)
    assert (dense._classify(0, on_only(frame), 1000).bits != truth).sum() >= 5


def _fast_reader(seed: int) -> tuple[CellReader, np.random.Generator, np.ndarray]:
    """A ``fast`` reader of N = 16, a generator seeded ``seed`` and the payload cells it
    toggled (its first draw)."""
    config = ReceiverConfig(CameraModel(346, 260, K), cells=16, profile="fast")
    rng = np.random.default_rng(seed)
    n = config.geometry.locator_side
    return CellReader(config, first_burst_us=0.0), rng, rng.integers(0, 2, (n - 2, n - 2))


def _fast_frame(reader: CellReader, ring: np.ndarray, on: np.ndarray, off: np.ndarray):
    """(2, n, n) ON and OFF densities of frame 0 (the locator rises): the ring's white cells at
    ``ring`` (n, n) on the ON side, the payload's ``on`` and ``off`` inside."""
    white = reader.config.geometry.inner_locator
    frame = np.stack([np.where(white, ring, 0.0), np.zeros_like(ring)])
    frame[:, 1:-1, 1:-1] = on, off
    return frame


def test_fast_reads_toggles_of_both_polarities_under_a_thinning_readout():
    # Densities as a 7.4 Mev/s cap leaves them at 24 px per cell: the cells toggled on fire
    # 0.2-0.4, those toggled off 0.4-0.95, the untoggled ones a few hundredths at most.
    reader, rng, toggled = _fast_reader(5)
    n = reader.n
    rising = rng.random((n - 2, n - 2)) < 0.5
    shape = rising.shape
    level = np.where(rising, rng.uniform(0.2, 0.4, shape), rng.uniform(0.4, 0.95, shape))
    on, off = (
        np.where(toggled & up, level, rng.uniform(0.0, 0.03, shape)) for up in (rising, ~rising)
    )
    frame = _fast_frame(reader, rng.uniform(0.7, 0.95, (n, n)), on, off)
    read = reader._classify(0, frame, 1000)
    assert np.array_equal(read.bits, toggled)
    assert read.confidence.min() > get_profile("fast").erasure_below
    assert read.locator_score > 0.9


def test_fast_reads_dark_cells_lit_by_their_toggling_neighbours_on_the_linear_scale():
    # Blur without a cap: every toggled cell fires, while a third of the untoggled ones fire
    # for their neighbours, up to 0.45; a square root would spread those across the middle.
    reader, rng, toggled = _fast_reader(6)
    n = reader.n
    shape = toggled.shape
    spilled = rng.random(shape) < 0.35
    dark = np.where(spilled, rng.uniform(0.1, 0.45, shape), rng.uniform(0, 0.02, shape))
    level = np.where(toggled, rng.uniform(0.85, 1.0, shape), dark)
    up = rng.random(shape) < 0.5  # the direction of a cell's own switch, or its neighbours'
    frame = _fast_frame(reader, rng.uniform(0.9, 1.0, (n, n)), level * up, level * ~up)
    assert np.array_equal(reader._classify(0, frame, 1000).bits, toggled)


def test_fast_reads_each_polarity_less_what_the_neighbours_switching_its_way_spill(monkeypatch):
    # Blur: a dark cell fires with each switching 4-neighbour, 0.15 of a toggle, in that
    # neighbour's direction (ON as it lights, OFF as it darkens); a lit one does not notice.
    reader, rng, toggled = _fast_reader(7)
    geo, n = reader.config.geometry, reader.n
    lit_before = np.zeros((n, n), bool)  # the ring's white cells rise in frame 0
    lit_before[1:-1, 1:-1] = rng.random(toggled.shape) < 0.5
    switched = locator_block(geo, toggled).astype(bool)
    rising, falling = switched & ~lit_before, switched & lit_before
    quiet_dark = ~switched & ~lit_before

    def spill(source: np.ndarray) -> np.ndarray:
        p = np.pad(source, 1).astype(float)
        return 0.15 * (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:]) * quiet_dark

    noise = rng.uniform(0, 0.03, (2, n, n))
    on, off = rising + spill(rising) + noise[0], falling + spill(falling) + noise[1]
    frame = np.stack([on, off])
    assert np.array_equal(reader._classify(0, frame, 1000).bits, toggled)

    # The two polarities added up, a dark cell between a rising and a falling neighbour
    # reads as much as a toggle.
    def summed(self: CellReader, on: np.ndarray, off: np.ndarray, bits: np.ndarray, shown):
        return [decoder._less_spill(on + off, self._lit(bits))]

    monkeypatch.setattr(CellReader, "_levels", summed)
    assert (reader._classify(0, frame, 1000).bits != toggled).sum() >= 3


def test_detection_retries_each_finer_binning_after_the_coarsest(monkeypatch):
    # A still marker of 20 px cells whose every other path fails: binned 4 x 4 first, then
    # 2 x 2, whose corners a thinned readout can leave straight where the coarser ones are not.
    config = ReceiverConfig(CameraModel(640, 480, K), cells=16, profile="fast")
    side = 20 * config.geometry.locator_side + 2 * detector.TILE_PX
    region = detector.BlinkRegion(Box(100, 100, 100 + side, 100 + side), 0.0, 0.5)
    monkeypatch.setattr(detector, "blinking_region", lambda parts, config: region)
    monkeypatch.setattr(detector, "latest_burst_us", lambda parts, burst, period: burst)
    monkeypatch.setattr(detector, "burst_flow", lambda *_: np.zeros(2))

    def miss(*_):
        raise MarkerNotFound("spatial: the blinking region is not square")

    for path in ("_detect_moving", "_detect_still", "_detect_slow"):
        monkeypatch.setattr(detector, path, miss)
    tried = []
    found = detector.Detection(np.zeros((4, 2)), np.eye(4), 0, 0.0, 30.0, 1.0, 1.0, np.zeros(2))

    def binned(parts, config, b):
        tried.append(b)
        if b > 2:
            miss()
        return found

    monkeypatch.setattr(detector, "_detect_binned", binned)
    events = make_events(np.arange(200), np.zeros(200), np.zeros(200), np.ones(200))
    assert detector.detect(events, config) is found
    assert tried == [4, 2]


def test_fast_truth_is_the_toggles_and_key_refreshes_are_not_scored():
    enc = StreamEncoder(b"toggle" * 20, profile="fast", cells=16)
    truth = FrameTruth(enc, refresh_hz=60.0)
    geo = enc.geometry
    k = 5  # a data refresh: its toggle bits are the symbol
    assert np.array_equal(truth.sent(k), enc.payload_bits(k))
    t_us = int((k + 0.5) * 1e6 / 60)
    assert truth.errors(enc.payload_bits(k), t_us) == 0
    key = enc.profile.key_every  # the key refresh blanks the payload: toggles but no symbol
    toggles = geo.payload_of(enc.frame(key - 1))
    assert truth.errors(toggles, int((key + 0.5) * 1e6 / 60)) is None


@pytest.mark.parametrize(("profile", "expected"), [("robust", 0), ("fast", None)])
def test_frame_truth_scores_the_streams_first_refresh(profile, expected):
    """Refresh 0 follows blank frames: ``robust``'s is scored as shown, ``fast``'s is a key
    refresh (no symbol). It used to be matched to refresh 1, ``fast``'s at half its bits wrong."""
    truth = FrameTruth(StreamEncoder(bytes(300), profile=profile, cells=16), 60.0)
    assert truth.errors(truth.sent(0), 8_300) == expected


def test_the_blinking_region_joins_blobs_less_than_a_cell_apart():
    """At a few pixels per cell a row of cells that stayed dark for the window can cut a whole
    side off the marker's heat: it is still the marker. Another blob several cells away is not."""
    heat = np.zeros((400, 400), np.float32)
    heat[110:300, 50:250] = 1.0  # most of a 34-cell locator, ~6 px per cell
    heat[60:105, 50:250] = 1.0  # its top, one dark row of cells apart
    heat[60:105, 300:340] = 1.0  # something else blinking, eight cells away
    hull = largest_region(heat, 0.2, locator_side=34)
    assert hull[:, 1].min() == 60 and hull[:, 1].max() == 299
    assert hull[:, 0].max() == 249


def _thinned_blink(blink_hz: float, side: int, keep: float, seed: int = 0) -> np.ndarray:
    """A square of pixels blinking at ``blink_hz``, four ON events per burst within 0.5 ms and
    four OFF events half a period later within 4 ms (a slow fall), of which ``keep`` survive."""
    rng = np.random.default_rng(seed)
    period = 1e6 / blink_hz
    y, x = np.mgrid[:side, :side]
    t, p = [], []
    for k in range(8):
        for pol, start, spread in ((1, 0.0, 500.0), (-1, period / 2, 4000.0)):
            t.append(k * period + start + rng.uniform(0, spread, (4, side, side)))
            p.append(np.full((4, side, side), pol))
    t, p = np.concatenate(t).ravel(), np.concatenate(p).ravel()
    x, y = np.tile(x.ravel(), 16 * 4), np.tile(y.ravel(), 16 * 4)
    kept = np.flatnonzero(rng.random(t.size) < keep)
    kept = kept[np.argsort(t[kept], kind="stable")]
    return make_events(np.rint(t[kept]).astype(np.int64), x[kept], y[kept], p[kept])


@pytest.mark.parametrize("refresh_hz, blinks", [(240.0, True), (200.0, False), (280.0, False)])
def test_a_thinned_blink_is_timed_on_binned_pixels(refresh_hz, blinks):
    """A readout that keeps a tenth of the events leaves a pixel a burst's one event or none:
    its own periods spread and miss the told blink, while 2 x 2 pixels' still match it. The
    binned pixels still refuse a display a sixth off, and the same events at random times."""
    side = 64
    config = ReceiverConfig(
        CameraModel(side, side, np.array([[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]])),
        refresh_hz=240.0,
    )
    ev = _thinned_blink(refresh_hz / 2, side, keep=0.1)
    mask = np.ones((side, side), np.uint8)
    heat, triplets = blink_heatmap([ev], side, side, config.blink_hz, config.detector.sigma_frac)
    least = config.detector.min_period_match
    assert _period_match(heat, triplets, mask) < least
    assert _binned_blink([ev], mask, config) == blinks
    rng = np.random.default_rng(1)
    noise = ev[rng.permutation(len(ev))]
    noise["t"] = np.sort(rng.integers(ev["t"][0], ev["t"][-1], len(ev)))
    assert not _binned_blink([noise], mask, config)


def _blinking_everywhere(monkeypatch, flow_px_per_ms: float) -> tuple[ReceiverConfig, np.ndarray]:
    """(config, events) for ``detect`` on a 64x48 camera whose whole view blinks, its burst
    showing ``flow_px_per_ms`` sideways: the paths it tries are the test's to set."""
    config = ReceiverConfig(CameraModel(64, 48, [[50, 0, 32], [0, 50, 24], [0, 0, 1]]))
    region = detector.BlinkRegion(detector.Box(0, 0, 64, 48), 0.0, 1.0)
    monkeypatch.setattr(detector, "blinking_region", lambda parts, config: region)
    monkeypatch.setattr(detector, "latest_burst_us", lambda parts, burst, period: 50_000.0)
    monkeypatch.setattr(detector, "burst_flow", lambda *args: np.array([flow_px_per_ms, 0.0]))
    monkeypatch.setattr(detector, "region_cell_px", lambda region, config: 10.0)
    events = make_events(np.arange(200) * 500, np.arange(200) % 64, np.arange(200) % 48, 1)
    return config, events


def test_detection_prefers_a_path_that_reads_the_l(monkeypatch):
    # A still camera's noise can fake a flow: the moving path's burst then shows no 'L'
    # (``oriented`` false) where the still path reads it. The reading path wins; an unoriented
    # detection stands only where no path reads the 'L'.
    config, events = _blinking_everywhere(monkeypatch, 0.1)

    def found(oriented: bool) -> detector.Detection:
        return detector.Detection(
            np.zeros((4, 2)), np.eye(4), 0, 0.0, 30.0, 1.0, 0.5, np.zeros(2), oriented=oriented
        )

    def miss(*args):
        raise detector.MarkerNotFound("spatial: nothing here")

    unoriented, still = found(False), found(True)
    monkeypatch.setattr(detector, "_detect_moving", lambda *args: unoriented)
    monkeypatch.setattr(detector, "_detect_densest", miss)
    monkeypatch.setattr(detector, "_detect_slow", miss)
    monkeypatch.setattr(detector, "_detect_still", lambda *args: still)
    assert detector.detect(events, config) is still
    monkeypatch.setattr(detector, "_detect_still", miss)
    assert detector.detect(events, config) is unoriented


@pytest.mark.parametrize(
    "moving_score, still_score, winner",
    [(0.3, 0.9, "still"), (0.3, 0.2, "moving"), (0.3, None, "moving"), (0.7, 0.9, "moving")],
)
def test_a_burst_whose_l_reads_faintly_yields_to_a_sharper_still_reading(
    monkeypatch, moving_score, still_score, winner
):
    # Noise on a still camera can fake a flow whose burst shows a faint 'L': the still path then
    # decides, if it reads the 'L' more clearly. A burst that reads it as clearly as a still
    # marker would stands without the still path running.
    config, events = _blinking_everywhere(monkeypatch, 10.0)

    def found(score: float, flow: tuple[float, float]) -> detector.Detection:
        return detector.Detection(
            np.zeros((4, 2)), np.eye(4), 0, 0.0, 30.0, 1.0, score, np.array(flow)
        )

    def still_path(*args):
        if still_score is None:
            raise detector.MarkerNotFound("temporal: the blinking region's period does not match")
        return detections["still"]

    detections = {"moving": found(moving_score, (10.0, 0.0))}
    if still_score is not None:
        detections["still"] = found(still_score, (0.0, 0.0))
    monkeypatch.setattr(detector, "_detect_moving", lambda *args: detections["moving"])
    monkeypatch.setattr(detector, "_detect_still", still_path)
    assert detector.detect(events, config) is detections[winner]
