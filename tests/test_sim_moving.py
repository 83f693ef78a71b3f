"""The moving-camera renderer's shortcuts against slower, more literal versions of its model."""

from __future__ import annotations

import numpy as np
import pytest

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.events import concat
from eventocc.receiver.poses import make_pose, write_tum
from eventocc.receiver.sim import (
    Display,
    HandHeldMotion,
    Optics,
    Scene,
    SensorModel,
    TumMotion,
    moving,
    simulate,
)
from eventocc.receiver.sim.optics import flat_poses, rays_to_plane, sample_rays
from eventocc.receiver.sim.render import plane_geometry, regions
from eventocc.receiver.sim.sensor import EventBuffer

CAM = CameraModel.paper().resized(200, 150)
MESSAGE = bytes(range(256))


def _scene(**kw) -> Scene:
    base = {
        "encoder": StreamEncoder(MESSAGE, profile="paper", cells=16),
        "camera": CAM,
        "motion": HandHeldMotion(distance_m=3.2, flow_px_per_ms=1.0, seed=3),
        "sensor": SensorModel.preset("ideal"),
    }
    return Scene(**(base | kw))


def _edges_only() -> Scene:
    """Instant switches and a 3 s blank preamble: every event comes from a moving edge."""
    enc = StreamEncoder(MESSAGE, profile="paper", cells=16, preamble=True)
    return _scene(encoder=enc, display=Display(rise_ms=0.0, fall_ms=0.0))


def _per_pixel(ev: np.ndarray) -> dict[int, np.ndarray]:
    pix = ev["y"].astype(np.int64) * CAM.width + ev["x"]
    order = np.lexsort((ev["t"], pix))
    pix, t = pix[order], ev["t"][order]
    cuts = np.flatnonzero(np.diff(pix)) + 1
    return {int(p[0]): ts for p, ts in zip(np.split(pix, cuts), np.split(t, cuts), strict=True)}


def test_the_linearised_footprint_lands_on_the_regions_of_the_exact_rays():
    scene = _scene(optics=Optics(blur_px=0.5, supersample=4))
    T = scene.motion.trajectory(scene.rig).pose_at(np.array([0, 150_000, 400_000]))
    path = np.column_stack([flat_poses(T), np.zeros(len(T))])  # times unused here
    ys, xs = np.mgrid[0 : CAM.height : 3, 0 : CAM.width : 3].reshape(2, -1)
    rays = sample_rays(CAM, scene.optics, xs, ys)  # (n, S, 2)
    centre = rays.mean(axis=1)
    offsets = rays[0] - centre[0]
    geo = plane_geometry(scene.layout)
    regs, counts = np.empty(16, np.int64), np.empty(16)
    agree = total = kept = shifted = 0
    for step, Ti in enumerate(T):
        points = rays_to_plane(rays, Ti)
        exact = regions(points, scene.layout)
        free = np.empty(len(xs))
        for j in range(len(xs)):
            nd, free[j] = moving._content(
                centre[j, 0], centre[j, 1], path, step, 0, 0.0, 0.0, offsets, geo, regs, counts
            )
            found, n = np.unique(exact[j], return_counts=True)
            agree += np.array_equal(regs[:nd], found) and np.array_equal(counts[:nd], n)
            total += 1
        # The returned room is how far every sample may move along either axis and stay put.
        for direction in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            moved = points + 0.99 * free[:, None, None] * np.array(direction)
            same = regions(moved, scene.layout) == exact
            kept += same.sum()
            shifted += same.size
    assert total > 5000
    assert agree / total > 0.998  # misses: samples within a hair of a cell edge
    assert kept / shifted > 0.998


def test_sub_step_interpolation_converges_on_a_moving_edge(monkeypatch):
    # A sampled sub-step moves the footprint weights linearly from one end to the other (ESIM),
    # spreading each sample's crossing of an edge over the step: 0.5 ms at 1 px/ms. Against a
    # four times finer solution, event times move by about a quarter of that (median) and
    # rarely by more than a step.
    coarse = _per_pixel(concat(simulate(_edges_only(), 0.012)))
    monkeypatch.setattr(moving, "MAX_STEP_PX", moving.MAX_STEP_PX / 4)
    fine = _per_pixel(concat(simulate(_edges_only(), 0.012)))
    same_count = [p for p in coarse if p in fine and len(coarse[p]) == len(fine[p])]
    assert len(same_count) > 0.9 * len(coarse) > 300
    shift = np.concatenate([np.abs(coarse[p] - fine[p]) for p in same_count])
    assert np.median(shift) < 150
    assert np.quantile(shift, 0.99) < 500


def test_pixels_rendered_blocks_ahead_give_the_events_of_window_by_window(monkeypatch):
    # Each pixel renders several windows at a visit, staggered, and its later events wait for
    # their window; rendering every pixel window by window must give the same events but for
    # the sub-step grid (planned over more windows, it is finer where the camera is slower).
    scene = _scene(motion=HandHeldMotion(distance_m=3.2, flow_px_per_ms=0.5, seed=2))
    blocks = concat(simulate(scene, 0.04, chunk_us=5_000))
    monkeypatch.setattr(moving, "BLOCK_US", 5_000)
    windows = concat(simulate(scene, 0.04, chunk_us=5_000))
    assert len(windows) > 5000
    assert np.all(np.diff(blocks["t"]) >= 0)
    assert len(blocks) == pytest.approx(len(windows), rel=0.01)
    per_pixel = [
        np.bincount(e["y"].astype(int) * CAM.width + e["x"], minlength=CAM.width * CAM.height)
        for e in (blocks, windows)
    ]
    assert np.mean(np.abs(per_pixel[0] - per_pixel[1]) <= 1) > 0.97


def test_a_full_output_buffer_reruns_the_pixel_and_loses_nothing(monkeypatch):
    scene = _scene(motion=HandHeldMotion(distance_m=3.2, flow_px_per_ms=0.5, seed=1))
    roomy = concat(simulate(scene, 0.03))
    monkeypatch.setattr(moving, "EventBuffer", lambda: EventBuffer(capacity=64))
    cramped = concat(simulate(scene, 0.03))
    assert len(roomy) > 5000
    assert np.array_equal(roomy, cramped)


def test_a_moving_camera_that_does_not_see_the_screen_gives_no_signal(tmp_path):
    # Facing the screen's plane but 5 m to its side: the screen's image box is empty.
    poses = np.stack([make_pose(np.eye(3), [x, 0.1, -1.0]) for x in (5.0, 5.01)])
    write_tum(tmp_path / "aside.tum", np.array([0, 100_000]), poses)
    scene = _scene(motion=TumMotion(str(tmp_path / "aside.tum")))
    assert len(concat(simulate(scene, 0.03))) == 0
