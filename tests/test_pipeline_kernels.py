"""The receiver's per-event kernels against plain reference implementations: the triage pass, the
burst read-out, the tracker mask, the columns, cluster re-binning and ageing, the pose solver's
normal equations, the projection, the detector's event selection and corner fit. Each reference
is the obvious (slow) way to compute the same thing."""

from __future__ import annotations

import copy
import itertools

import cv2
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from eventocc.receiver.camera import CameraModel
from eventocc.receiver.events import make_events
from eventocc.receiver.pipeline.buffer import to_columns
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.locate import Box, events_between, outline, quadrilateral
from eventocc.receiver.pipeline.pose import DARK_SIDE, _residuals, project_ideal
from eventocc.receiver.pipeline.tracker import (
    EdgeTracker,
    _assign,
    _capture_points,
    _nearest_edge,
    _reassign,
)
from eventocc.receiver.pipeline.triage import TILE, EventTriage
from eventocc.receiver.poses import make_pose

K = np.array([[300.0, 0, 173], [0, 300.0, 130], [0, 0, 1]])
WIDTH, HEIGHT = 64, 48
DISTORTED = CameraModel(WIDTH, HEIGHT, K, np.array([-0.3, 0.1, 0.0, 0.0, 0.0]))
SIZE = 0.272
GAP_US = 100


def _stream(rng: np.random.Generator, n: int) -> np.ndarray:
    """Time-sorted events on a few pixels (so that bursts form), both polarities."""
    t = np.sort(rng.integers(0, 2000, n))
    x, y = rng.integers(0, 6, n), rng.integers(0, 4, n)
    return make_events(t, x, y, rng.choice([-1, 1], n))


def _reference_bursts(
    events: np.ndarray, polarities: int, marks: tuple[int, ...] = (0,)
) -> set[tuple]:
    """(x, y, polarity index, start) of each pixel's latest burst and of its first burst from
    each of the ``marks`` on, event by event: a burst ends at an event of the other polarity,
    and an ON burst (with one polarity kept, the only one) also after a gap of ``GAP_US``."""
    latest: dict[tuple, int] = {}
    firsts: list[dict[tuple, int]] = [{} for _ in marks]
    last: dict[tuple, int] = {}
    for t, x, y, p in zip(events["t"], events["x"], events["y"], events["p"], strict=True):
        key = (int(x), int(y), 0 if p > 0 else 1)
        last.pop((key[0], key[1], 1 - key[2]), None)
        if key[2] >= polarities:
            continue
        if key not in last or (key[2] == 0 and t - last[key] > GAP_US):
            latest[key] = int(t)
            for mark, first in zip(marks, firsts, strict=True):
                if t >= mark and key not in first:
                    first[key] = int(t)
        last[key] = int(t)
    return {(*key, t) for kept in (latest, *firsts) for key, t in kept.items()}


def _on_grid(bursts: set[tuple], stride: int) -> set[tuple]:
    return {b for b in bursts if b[0] % stride == b[1] % stride == 0}


def _as_tuples(bursts) -> list[tuple]:
    """The bursts read out, (x, y, polarity index, start) each, in their order."""
    fields = (bursts["x"], bursts["y"], bursts["p"], bursts["t"])
    return [(int(x), int(y), 0 if p > 0 else 1, int(t)) for x, y, p, t in zip(*fields, strict=True)]


@settings(max_examples=25, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 3000),  # the triage gathers on-grid events by blocks of 1024
    st.booleans(),
    st.integers(1, 3),
    st.sampled_from([1, 2, 3, 4]),
    st.integers(0, 2000),
    st.integers(0, 2000),
)
def test_triage_keeps_each_pixels_latest_and_first_marked_burst_starts(
    seed, n, both, pieces, stride, mark, later
):
    """Of the pixels on every ``stride``-th row and column (the others are not kept); a burst
    that is the latest and the first from a mark on, or the first from both, is read out
    once."""
    marks = (mark, mark + later)
    rng = np.random.default_rng(seed)
    events = _stream(rng, n)
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, both)
    triage.reset(0, stride)
    triage.marks_us = marks
    for part in np.array_split(events, pieces):  # chunking must not matter
        triage(part)
    expected = _on_grid(_reference_bursts(events, 2 if both else 1, marks), stride)
    got = _as_tuples(triage.bursts(-(1 << 20), 1 << 20, (0, WIDTH, 0, HEIGHT)))
    assert len(got) == len(set(got)) and set(got) == expected


def test_with_both_polarities_a_reversal_or_a_late_on_event_starts_a_burst():
    """A toggling cell's pixels reverse polarity at each switch. A lone OFF event long after the
    pixel went dark (its slow settling) is no switch, while the same pixel turning on again is
    one, and so is its own switch on after a neighbour's light made it fire ON a refresh
    before (no OFF event between)."""
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, True)
    triage.reset(0)
    t = [0, 40, 80, 5_000, 9_000, 9_050]  # a switch off, a lone OFF, a switch on
    triage(make_events(t, [3] * 6, [2] * 6, [-1, -1, -1, -1, 1, 1]))
    late = triage.bursts(1_000, 20_000, (0, WIDTH, 0, HEIGHT))
    assert _as_tuples(late) == [(3, 2, 0, 9_000)]
    first = triage.bursts(0, 1_000, (0, WIDTH, 0, HEIGHT))
    assert _as_tuples(first) == [(3, 2, 1, 0)]
    # A neighbour's light (ON at 20,000), then the pixel's own switch (ON at 30,000).
    t = [20_000, 20_030, 20_060, 30_000, 30_040]
    triage(make_events(t, [3] * 5, [2] * 5, [1] * 5))
    own = triage.bursts(25_000, 40_000, (0, WIDTH, 0, HEIGHT))
    assert _as_tuples(own) == [(3, 2, 0, 30_000)]


@pytest.mark.parametrize("stride", [1, 2, 3, 4])
def test_triage_keeps_every_on_grid_pixel_of_a_long_chunk(stride):
    """Each pixel fires once, in random order, over several of the triage's blocks: every
    on-grid one, however the grid pixels fall in the blocks, is a burst of its own."""
    rng = np.random.default_rng(stride)
    pixels = rng.permutation(WIDTH * HEIGHT)
    events = make_events(np.arange(len(pixels)), pixels % WIDTH, pixels // WIDTH, [1] * len(pixels))
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, False)
    triage.reset(0, stride)
    triage(events)
    bursts = triage.bursts(0, len(pixels), (0, WIDTH, 0, HEIGHT))
    keys = zip(bursts["x"].tolist(), bursts["y"].tolist(), strict=True)
    got = dict(zip(keys, bursts["t"].tolist(), strict=True))
    expected = {
        (int(e["x"]), int(e["y"])): int(e["t"])
        for e in events
        if e["x"] % stride == e["y"] % stride == 0
    }
    assert got == expected


@settings(max_examples=25, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(0, 2000),
    st.integers(0, 2000),
    st.sampled_from([1, 2, 3]),
)
def test_bursts_are_those_that_began_in_the_window_inside_the_box(seed, t0, span, stride):
    rng = np.random.default_rng(seed)
    events = _stream(rng, 300)
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, True)
    triage.reset(0, stride)
    triage.marks_us = (t0, t0 + span // 2)
    triage(events)
    box = (1, 4, 1, 4)  # odd edges: the stride's grid starts inside the box
    expected = {
        (x, y, d, t)
        for x, y, d, t in _on_grid(_reference_bursts(events, 2, (t0, t0 + span // 2)), stride)
        if t0 <= t < t0 + span and box[0] <= x < box[1] and box[2] <= y < box[3]
    }
    bursts = triage.bursts(t0, t0 + span, box)
    got = _as_tuples(bursts)
    assert len(got) == len(set(got)) and set(got) == expected
    for x, y, xu, yu in zip(*(bursts[f] for f in ("x", "y", "xu", "yu")), strict=True):
        assert (xu, yu) == tuple(DISTORTED.undistort_table[y, x].astype(np.float32))


def _tile_centres_ideal() -> np.ndarray:
    """(rows, cols, 2) ideal pixel of every tile's centre pixel."""
    table = DISTORTED.undistort_table
    cy = np.minimum(np.arange(0, HEIGHT, TILE) + TILE // 2, HEIGHT - 1)
    cx = np.minimum(np.arange(0, WIDTH, TILE) + TILE // 2, WIDTH - 1)
    return table[cy[:, None], cx[None, :]].astype(np.float64)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    w = np.clip(((p - a) @ d) / max(d @ d, 1e-12), 0.0, 1.0)
    return np.linalg.norm(a + w[..., None] * d - p, axis=-1)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.tuples(*[st.floats(-20, 80, allow_nan=False)] * 4), min_size=1, max_size=8),
    st.floats(0.0, 10.0),
)
def test_tracker_mask_holds_exactly_the_tiles_near_an_edge(segments, reach_px):
    """Tiles are raw pixels and the edges ideal ones; the lens here bends the corners by
    several pixels, so a search box that ignored the distortion would miss tiles."""
    seg = np.array(segments, float)
    a, b = seg[:, :2].copy(), seg[:, 2:].copy()
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, False)
    triage.track_near(a, b, reach_px)
    reach = reach_px + TILE * 0.75
    centres = _tile_centres_ideal()
    dist = np.min([_segment_distance(centres, a[e], b[e]) for e in range(len(a))], axis=0)
    tiles = triage._tiles
    assert tiles[dist < reach - 1e-6].all()
    assert not tiles[dist > reach + 1e-6].any()


def test_tracker_mask_of_edges_far_off_the_view_is_empty():
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, False)
    for far in (1e30, -1e30):
        triage.track_near(np.array([[far, far]]), np.array([[far, -far]]), reach_px=4.0)
        assert not triage._tiles.any()


@pytest.mark.parametrize("share", [1.0, 0.0])
def test_triage_hands_the_tracker_the_events_on_marked_tiles_as_columns(share):
    """The same events whether few lay near the edges last time (tested with a branch) or many
    (without one)."""
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, False)
    triage._near_share = share
    triage.track_near(np.array([[0.0, 30.0]]), np.array([[63.0, 30.0]]), reach_px=2.0)
    rng = np.random.default_rng(3)
    n = 500
    events = make_events(
        np.sort(rng.integers(0, 1000, n)),
        rng.integers(0, WIDTH, n),
        rng.integers(0, HEIGHT, n),
        rng.choice([-1, 1], n),
    )
    on_tile = triage._tiles[events["y"] // TILE, events["x"] // TILE]
    assert 0 < on_tile.sum() < n
    near = triage(events)
    expected = to_columns(events[on_tile], DISTORTED.undistort_table)
    for field in ("t", "x", "y", "p", "xu", "yu"):
        assert np.array_equal(near[field], expected[field])


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize("per_ms", [50.0, 120.0, 1000.0])
def test_the_trackers_events_are_thinned_evenly_to_their_budget(per_ms, stride):
    """Every k-th near-edge event, k the least that keeps within ``per_ms`` per millisecond of
    the chunk, and every one of them when the chunk is within budget; the surfaces still take
    every (on-grid) event."""
    events = _stream(np.random.default_rng(4), 3000)  # several of the triage's blocks
    n = len(events)
    thinned, whole = (EventTriage(DISTORTED.undistort_table, GAP_US, True) for _ in range(2))
    for triage in (thinned, whole):
        triage.reset(0, stride)
        triage._tiles[:] = True
    near = thinned(events, per_ms=per_ms)
    every = whole(events)
    span_ms = (int(events["t"][-1]) - int(events["t"][0]) + 1) / 1000
    k = max(1, -(-n // int(per_ms * span_ms)))
    for field in ("t", "x", "y"):
        assert np.array_equal(near[field], every[field][::k])
    assert len(near["t"]) <= per_ms * span_ms
    assert np.array_equal(thinned.surface, whole.surface)


@pytest.mark.parametrize("stride", [1, 2])
def test_a_stretch_split_across_chunks_triages_as_one(stride):
    """The parts of a stretch of the stream (the end of one chunk, the start of the next) are
    read in place and give what one call on their concatenation gives: the same thinned events
    and surfaces, however the stream was cut into chunks."""
    events = _stream(np.random.default_rng(6), 3000)
    cuts = [0, 1, 1100, 1101, 1101, 2500, len(events)]
    whole, split = (EventTriage(DISTORTED.undistort_table, GAP_US, True) for _ in range(2))
    for triage in (whole, split):
        triage.reset(0, stride)
        triage._tiles[0, 0] = True  # pixels x < 4, y < 4: about two thirds of the events
    for _ in range(2):  # the second call's lookups are thinned by the first one's share
        one = whole(events, per_ms=300.0)
        parts = split(*(events[i:j] for i, j in itertools.pairwise(cuts)), per_ms=300.0)
        assert 0 < len(one) < 2000
        for field in ("t", "x", "y", "p", "xu", "yu"):
            assert np.array_equal(one[field], parts[field])
    assert np.array_equal(whole.surface, split.surface)


def test_the_tile_lookups_thin_to_the_budget_from_the_share_near_the_edges():
    """Once a chunk has shown how many events lie near the edges, the next is looked up only at
    every k-th event: it still yields close to the budget, spread over the whole chunk."""
    events = _stream(np.random.default_rng(5), 4000)
    triage = EventTriage(DISTORTED.undistort_table, GAP_US, True)
    triage._tiles[0, 0] = True  # pixels x < 4, y < 4: about two thirds of the events
    per_ms = 600.0
    span_ms = (int(events["t"][-1]) - int(events["t"][0]) + 1) / 1000
    first = triage(events, per_ms=per_ms)
    second = triage(events, per_ms=per_ms)
    assert len(first["t"]) <= per_ms * span_ms
    assert 0.7 * per_ms * span_ms <= len(second["t"]) <= per_ms * span_ms
    assert np.all(second["x"] < TILE) and np.all(second["y"] < TILE)
    assert second["t"][0] - events["t"][0] < 20 and events["t"][-1] - second["t"][-1] < 20


@pytest.mark.parametrize("stride", [1, 2])
@pytest.mark.parametrize(
    ("share", "every", "told"),
    [(0.002, 4, {}), (0.002, 2, {"still_every": 2}), (0.0, 1, {}), (0.05, 1, {})],
)
def test_a_still_cameras_few_events_near_the_edges_are_looked_up_at_every_fourth(
    share, every, told, stride
):
    """When few events lay near the edges last time (a still camera: its tracker waits for
    motion), only every fourth event (or as told) is looked up in the tiles, however large the
    budget; when none did, or enough, every one is. The surfaces take every event either way."""
    events = _stream(np.random.default_rng(7), 3000)
    sparse = EventTriage(DISTORTED.undistort_table, GAP_US, False, **told)
    whole = EventTriage(DISTORTED.undistort_table, GAP_US, False)
    for triage in (sparse, whole):
        triage.reset(0, stride)
        triage._tiles[:] = True
    sparse._near_share = share
    near = sparse(events)
    assert np.array_equal(near["t"], events["t"][::every])
    assert np.array_equal(near["xu"], whole(events)["xu"][::every])
    assert np.array_equal(sparse.surface, whole.surface)


def _edge_points(tracker: EdgeTracker, n_per_edge: int, rng: np.random.Generator):
    """Ideal pixels within a pixel of the tracker's projected edges."""
    s = rng.uniform(0.02, 0.98, (8, n_per_edge, 1))
    pts = tracker._a[:, None] + s * (tracker._b - tracker._a)[:, None]
    pts = pts.reshape(-1, 2) + rng.normal(0, 0.5, (8 * n_per_edge, 2))
    return rng.permutation(pts)


def test_rebinning_keeps_the_fresh_events_and_their_indicators():
    config = ReceiverConfig(CameraModel(346, 260, K))
    T = make_pose(np.eye(3), [-SIZE / 2, -SIZE / 2, 0.6])
    tracker = EdgeTracker(config, T, now_us=0)
    rng = np.random.default_rng(1)
    pts = _edge_points(tracker, 40, rng)
    t = np.sort(rng.integers(0, 40_000, len(pts)))
    tracker.push(pts[:, 0], pts[:, 1], t)
    before = [s.copy() for s in tracker._slots]
    now = 50_000
    # Same pose: the bins stay, the events older than max_age leave.
    tracker._rebin(tracker.T_cam_world, now)
    sx, _, st_, _, sum_d, n_valid = tracker._slots
    fresh = before[2] >= now - config.tracker.max_age_us
    assert 0 < fresh.sum() < (before[2] >= 0).sum()
    width = min(st_.shape[1], before[2].shape[1])
    assert np.array_equal(st_[:, :width], np.where(fresh, before[2], -1)[:, :width])
    assert np.array_equal(sx[st_ >= 0], before[0][fresh])
    assert n_valid.tolist() == fresh.sum(axis=1).tolist()
    assert np.allclose(sum_d, np.where(fresh, before[3], 0.0).sum(axis=1))


def test_pose_normal_equations_match_a_numeric_jacobian():
    """``_residuals`` accumulates J^T W J and J^T W r point by point in scalar loops; a
    finite-difference Jacobian of its own residuals must give the same system."""
    rng = np.random.default_rng(2)
    config = ReceiverConfig(CameraModel(346, 260, K))
    ends = config.geometry.tracked_edges(SIZE)
    c, s = np.cos(0.2), np.sin(0.2)
    R = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])  # tilted 11 degrees about x
    t = np.array([-SIZE / 2, -SIZE / 2, 0.6])
    k = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    edge = rng.integers(0, 8, 200)
    world = ends[edge, 0] + rng.uniform(0, 1, (200, 1)) * (ends[edge, 1] - ends[edge, 0])
    pc = world @ R.T + t
    pts = pc[:, :2] / pc[:, 2:] * k[:2] + k[2:] + rng.normal(0, 2.0, (200, 2))
    huber = 1.0

    def signed(step: np.ndarray) -> np.ndarray:
        """Signed point-line distances after the update exp(w) R, exp(w) t + v, each line moved
        ``dark + step[6]`` px to its dark side."""
        w, v = step[:3], step[3:6]
        theta = np.linalg.norm(w)
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        dR = np.eye(3) + (np.sin(theta) / theta * W if theta else W)
        if theta:
            dR += (1 - np.cos(theta)) / theta**2 * (W @ W)
        R2, t2 = dR @ R, dR @ t + v
        proj = ends @ R2.T + t2
        px = proj[..., :2] / proj[..., 2:] * k[:2] + k[2:]
        a, b = px[edge, 0], px[edge, 1]
        d = b - a
        cross = d[:, 0] * (pts[:, 1] - a[:, 1]) - d[:, 1] * (pts[:, 0] - a[:, 0])
        return cross / np.linalg.norm(d, axis=1) - DARK_SIDE[edge] * (dark + step[6])

    dark = 0.4
    r = signed(np.zeros(7))
    eps = 1e-7
    J = np.stack([(signed(eps * np.eye(7)[j]) - r) / eps for j in range(7)], axis=1)
    wgt = np.where(np.abs(r) <= huber, 1.0, huber / np.abs(r))
    _, H, g = _residuals(R, t, k, pts, edge.astype(np.int64), ends, huber, dark)
    assert np.allclose(H, H.T)
    assert np.allclose(H, J.T @ (wgt[:, None] * J), rtol=1e-4, atol=1e-3 * np.abs(H).max())
    assert np.allclose(g, J.T @ (wgt * r), rtol=1e-4, atol=1e-3 * np.abs(g).max())


def test_pose_normal_equations_do_not_depend_on_the_points_order():
    """The per-edge moments add up while points stay on one edge (the tracker's clusters come
    edge by edge, a capture's points in any order): both orders give one system."""
    rng = np.random.default_rng(5)
    config = ReceiverConfig(CameraModel(346, 260, K))
    ends = config.geometry.tracked_edges(SIZE)
    R, t = np.eye(3), np.array([-SIZE / 2, -SIZE / 2, 0.6])
    k = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    edge = np.sort(rng.integers(0, 8, 300))
    pts = rng.uniform(0, 346, (300, 2))  # far off the lines too: Huber's linear part
    grouped = _residuals(R, t, k, pts, edge, ends, 1.0, 0.5)
    order = rng.permutation(300)
    shuffled = _residuals(R, t, k, pts[order], edge[order], ends, 1.0, 0.5)
    for a, b in zip(grouped, shuffled, strict=True):
        assert np.allclose(a, b, rtol=1e-12, atol=0.0)


def test_projection_matches_the_pinhole_formula_and_marks_points_behind_the_camera():
    rng = np.random.default_rng(6)
    T = make_pose(np.eye(3), [-0.1, -0.1, 0.5])
    points = rng.uniform(-0.3, 0.3, (4, 2, 3))
    points[0, 0, 2] = -0.6  # behind the camera
    px = project_ideal(T, K, points)
    assert px.shape == (4, 2, 2)
    cam = points + T[:3, 3]
    expected = cam[..., :2] / cam[..., 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.isnan(px[0, 0]).all()
    assert np.allclose(px.reshape(-1, 2)[1:], expected.reshape(-1, 2)[1:], rtol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 5), st.integers(1, 200))
def test_events_between_filters_and_thins_as_if_joined_first(seed, pieces, most):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 600))
    events = make_events(
        np.sort(rng.integers(0, 1000, n)),
        rng.integers(0, WIDTH, n),
        rng.integers(0, HEIGHT, n),
        rng.choice([-1, 1], n),
    )
    parts = np.array_split(events, pieces)
    box = Box(5, 3, 40, 30)
    joined = events[(events["t"] >= 100) & (events["t"] < 900)]
    inside = (
        (joined["p"] == -1)
        & (joined["x"] >= 5)
        & (joined["x"] < 40)
        & (joined["y"] >= 3)
        & (joined["y"] < 30)
    )
    expected = joined[inside]
    assert np.array_equal(events_between(parts, 100, 900, polarity=-1, box=box), expected)
    thinned = events_between(parts, 100, 900, most=most)
    assert np.array_equal(thinned, joined[:: max(1, len(joined) // most)])


@settings(max_examples=25, deadline=None)
@given(
    st.floats(0, np.pi / 2),
    st.floats(8.0, 30.0),
    st.floats(-3.0, 3.0),
    st.floats(-3.0, 3.0),
    st.integers(0, 2**32 - 1),
)
def test_quadrilateral_of_a_blobs_outline_is_that_of_all_its_pixels(turn, half, dx, dy, seed):
    """The detector fits the locator's corners to the outlines of its blob: the same hull as
    all its pixels, started at the same vertex (the polygon fit depends on where it starts)."""
    c, s = np.cos(turn), np.sin(turn)
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1.0]]) * half @ [[c, s], [-s, c]]
    image = np.zeros((80, 80), np.uint8)
    centre = np.array([40 + dx, 40 + dy])
    cv2.fillConvexPoly(image, np.round(square + centre).astype(np.int32), 1)
    rng = np.random.default_rng(seed)
    image[rng.integers(34, 46, 20), rng.integers(34, 46, 20)] = 0  # holes: not on the outline
    assert np.array_equal(quadrilateral(outline(image)), quadrilateral(np.argwhere(image)[:, ::-1]))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40))
def test_rebinning_into_fewer_bins_keeps_each_bins_newest_event(seed, cap):
    """Re-binning onto ``cap`` bins events that sat in 40 (a camera backing off): each new bin
    keeps the newest of its events, although the old slots are in order along the edge, not in
    time; stale events, and those beyond the gate, leave."""
    rng = np.random.default_rng(seed)
    a, b = np.array([[10.0, 20.0]]), np.array([[110.0, 20.0]])
    old_x = np.sort(rng.uniform(10, 110, (1, 40)))
    old_y = 20 + rng.uniform(-3, 3, (1, 40))
    old_t = rng.integers(-1, 1000, (1, 40))  # -1: an empty slot
    gate, since = np.array([2.0]), 100
    slots = (np.zeros((1, cap)), np.zeros((1, cap)), np.full((1, cap), -1, np.int64))
    sd, sum_d, n_valid = np.zeros((1, cap)), np.zeros(1), np.zeros(1, np.int64)
    _reassign(old_x, old_y, old_t, since, a, b, gate, np.array([cap]), *slots, sd, sum_d, n_valid)
    newest: dict[int, tuple[int, float]] = {}
    for x, y, t in zip(old_x[0], old_y[0], old_t[0], strict=True):
        s = min(int((x - 10) * 100 * (1 / 100**2) * cap), cap - 1)  # as _to_segment rounds it
        if t >= since and abs(y - 20) <= gate[0] and t >= newest.get(s, (-1,))[0]:
            newest[s] = (int(t), x)
    sx, _, st_ = slots
    assert {s: (int(st_[0, s]), sx[0, s]) for s in np.flatnonzero(st_[0] >= 0)} == newest
    assert n_valid[0] == len(newest) and np.isclose(sum_d[0], sd[0][st_[0] >= 0].sum())


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 60_000))
def test_ageing_out_at_the_same_pose_is_a_full_rebinning(seed, now):
    """A still camera's tracker only drops its stale slots every millisecond; the state must be
    the one a full re-binning at the same pose leaves, indicator sums bit for bit."""
    config = ReceiverConfig(CameraModel(346, 260, K))
    tracker = EdgeTracker(config, make_pose(np.eye(3), [-SIZE / 2, -SIZE / 2, 0.6]), now_us=0)
    rng = np.random.default_rng(seed)
    pts = _edge_points(tracker, 40, rng)
    tracker.push(pts[:, 0], pts[:, 1], np.sort(rng.integers(0, 40_000, len(pts))))
    rebinned = copy.deepcopy(tracker)
    rebinned._rebin(rebinned.T_cam_world, now)
    tracker._age_out(now)
    for aged, full in zip(tracker._slots, rebinned._slots, strict=True):
        assert np.array_equal(aged, full)


def _tracker_and_points(seed: int, n: int):
    """A tracker at a tilted view and points near its edges, in the band and far off."""
    config = ReceiverConfig(CameraModel(346, 260, K))
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])  # swung 17 degrees: no edge is axis-aligned
    tracker = EdgeTracker(config, make_pose(R, [-SIZE / 2, -SIZE / 2, 0.6]), now_us=0)
    rng = np.random.default_rng(seed)
    e = rng.integers(0, 8, n)
    along = rng.uniform(-0.1, 1.1, (n, 1))
    pts = tracker._a[e] + along * (tracker._b[e] - tracker._a[e])
    pts += rng.normal(0, 1, (n, 2)) * rng.choice([0.5, 5.0, 30.0], (n, 1))
    return tracker, pts[:, 0], pts[:, 1]


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(1, 1500), min_size=1, max_size=60))
@example(0, [10] * 40)  # 40 poses within the span: more than the buffer first holds
def test_edge_velocity_is_the_slope_over_the_recent_poses(seed, gaps):
    """The edges' ends move at the least-squares slope of their positions over the poses of
    the last ``velocity_span_us`` (at least the last three), however densely they came (its
    buffer outgrows its first size); before three poses, at the flow it started with."""
    tracker, _, _ = _tracker_and_points(seed, 1)
    rng = np.random.default_rng(seed)
    times, ends = [], []
    for now in np.cumsum(gaps):
        tracker._a, tracker._b = rng.normal(100, 30, (8, 2)), rng.normal(100, 30, (8, 2))
        tracker._fit_velocity(int(now))
        times.append(now)
        ends.append(np.concatenate([tracker._a, tracker._b]))
    if len(times) < 3:
        assert not tracker._va.any() and not tracker._vb.any()
        return
    t = np.array(times, float)
    keep = max(np.count_nonzero(t[-1] - t <= tracker.config.tracker.velocity_span_us), 3)
    slope = np.polyfit(t[-keep:], np.stack(ends[-keep:]).reshape(keep, -1), 1)[0]
    assert np.allclose(np.concatenate([tracker._va, tracker._vb]).ravel(), slope)


def _distance(px: float, py: float, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    d = b - a
    w = min(max(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / (d @ d), 0.0), 1.0)
    return float(np.hypot(a[0] + w * d[0] - px, a[1] + w * d[1] - py)), w


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_cluster_assignment_matches_a_plain_loop(seed, moving):
    """The compiled assignment measures a block of events edge by edge and bins each event onto
    the edges of its mask; a loop over the events and their eight edges must give the same
    clusters, the same fit counts and the same polarity tallies. Moving edges (up to ~10 px/ms)
    carry each point back to the time the edges hold, by ``carry_us`` at most."""
    tracker, xu, yu = _tracker_and_points(seed, 300)
    q = tracker.config.tracker
    t = np.arange(len(xu), dtype=np.int64) * 10  # 0 .. 3 ms
    ref_us = 1000
    rng = np.random.default_rng(seed)
    va, vb = rng.normal(0, 0.005 * moving, (2, 8, 2))  # px/us
    pol = rng.choice(np.array([-1, 1], np.int8), len(t))
    polarity = rng.integers(-1, 2, 8)  # each edge's expected one, 0: unjudged
    expected_tally = np.zeros((8, 2), np.int64)
    gate, band, cap = tracker._gate, tracker._band, tracker._cap
    expected_t = np.full(tracker._slots[2].shape, -1)
    expected_spread = np.zeros((8, 4), np.int64)
    near_count = on_count = 0
    for i in range(len(t)):
        near = on = False
        dt = np.clip(t[i] - ref_us, -q.carry_us, q.carry_us)
        for e in range(8):
            a, b = tracker._a[e], tracker._b[e]
            w0 = _distance(xu[i], yu[i], a, b)[1]
            p = np.array([xu[i], yu[i]]) - (va[e] + w0 * (vb[e] - va[e])) * dt
            d, w = _distance(*p, a, b)
            near |= d <= band[e]
            if d <= 2 * gate[e]:  # by distance, in bins half a gate wide
                expected_spread[e, min(int(d * 2 / gate[e]), 3)] += 1
            if d <= gate[e]:
                on = True
                expected_t[e, min(int(w * cap[e]), cap[e] - 1)] = t[i]
                if polarity[e]:
                    expected_tally[e, int(pol[i] != polarity[e])] += 1
        near_count += near
        on_count += near and on
    sx, sy, st_, sd, sum_d, n_valid = tracker._slots
    fit, spread = np.zeros(3, np.int64), np.zeros((8, 4), np.int64)
    tally = np.zeros((8, 2), np.int64)
    a, b = tracker._a, tracker._b
    args = (a, b, va, vb, ref_us, gate, band, cap, sx, sy, st_, sd, sum_d, n_valid, fit, spread)
    args += (polarity, tally, 1 << 62, 1 << 62, q.min_fill, q.min_new_events, q.carry_us)
    _assign(xu, yu, t, pol, 0, *args)
    assert np.array_equal(st_, expected_t)
    assert fit[:2].tolist() == [near_count, on_count]
    assert np.array_equal(spread, expected_spread)
    assert np.array_equal(tally, expected_tally)
    assert n_valid.tolist() == (expected_t >= 0).sum(axis=1).tolist()
    assert np.allclose(sum_d, np.where(st_ >= 0, sd, 0.0).sum(axis=1))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.5, 3.0))
def test_capture_points_match_their_definition(seed, gate_scale):
    tracker, xu, yu = _tracker_and_points(seed, 400)
    a, b = tracker._a, tracker._b
    ring_px = tracker._band
    gate, deep = gate_scale * ring_px, 0.6 * ring_px
    centre = a.mean(axis=0)
    near, edge = _capture_points(xu, yu, a, b, gate, deep, centre)
    for i in range(len(xu)):
        dist = [_distance(xu[i], yu[i], a[e], b[e])[0] for e in range(8)]
        e = int(np.argmin(dist))
        d = b[e] - a[e]
        side = d[0] * (yu[i] - a[e, 1]) - d[1] * (xu[i] - a[e, 0])
        ref = d[0] * (centre[1] - a[e, 1]) - d[1] * (centre[0] - a[e, 0])
        inside_deep = e >= 4 and dist[e] > deep[e] and side * ref > 0
        assert near[i] == (dist[e] <= gate[e] and not inside_deep)
        assert edge[i] == e or dist[e] > gate.max()  # the nearest edge, where it can count


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.5, 20.0))
def test_nearest_edge_within_reach_is_the_nearest_edge(seed, reach):
    tracker, xu, yu = _tracker_and_points(seed, 400)
    a, b = tracker._a, tracker._b
    every_dist, every_edge = _nearest_edge(xu, yu, a, b)
    dist, edge = _nearest_edge(xu, yu, a, b, reach)
    within = every_dist <= reach
    assert np.array_equal(dist[within], every_dist[within])
    assert np.array_equal(edge[within], every_edge[within])
    assert np.all(np.isinf(dist[~within]))
