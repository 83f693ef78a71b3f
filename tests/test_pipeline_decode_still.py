"""Decoding with a still camera: a cell reads as the share of its own (counted) pixels that
fired, the payload threshold follows the payload's own two clusters, and only cells that could
go either way lose confidence. No simulator: bursts are placed on the pixels directly."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench.tracking import CAMERA
from eventocc.occ.profiles import get_profile
from eventocc.receiver.pipeline import decoder
from eventocc.receiver.pipeline.buffer import EventColumns
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.decoder import CellReader
from eventocc.receiver.poses import invert
from eventocc.receiver.sim.motion import look_at
from tests.cells import locator_block, on_only

CONFIG = ReceiverConfig(CAMERA, cells=16)
"""About 4 px per cell at 0.6 m: a cell's inner part holds 4 to 9 pixel centres."""


def _pose(distance_m: float = 0.6, tilt_deg: float = 10.0) -> np.ndarray:
    """T_cam_world of a camera looking at the marker's centre, a little oblique so that the
    cells' pixel counts vary across the marker."""
    size = CONFIG.marker_size_m
    return invert(look_at(np.array([size / 2, size / 2, 0.0]), distance_m, tilt_deg, 5.0, 3.0))


def _still(T: np.ndarray):
    """``CellReader.read``'s ``pose_at`` for a camera that holds pose ``T``."""
    return lambda t_us: np.broadcast_to(T, (len(t_us), 4, 4))


def _white_bursts(
    reader: CellReader, T_cam_world: np.ndarray, cells: np.ndarray, m: int = 0
) -> EventColumns:
    """One ON burst, at frame ``m``'s burst time, on every pixel whose centre lies in a white
    locator-grid cell (a still camera and a sharp image: every such pixel fires)."""
    x0, x1, y0, y1 = reader.box(T_cam_world)
    y, x = (a.ravel() for a in np.mgrid[y0:y1, x0:x1])
    xu, yu = CAMERA.undistort_table[y, x].T
    g = reader._to_grid(T_cam_world) @ np.stack([xu, yu, np.ones_like(xu)])
    u, v = g[:2] / g[2]
    n = reader.n
    inside = (u >= 0) & (u < n) & (v >= 0) & (v < n)
    lit = inside.copy()
    lit[inside] = cells[v[inside].astype(int), u[inside].astype(int)]
    k = int(lit.sum())
    f32 = np.float32
    return EventColumns(
        np.full(k, int(reader.clock.mid(m)), np.int64),
        x[lit].astype(np.uint16),
        y[lit].astype(np.uint16),
        np.ones(k, np.int8),
        xu[lit].astype(f32),
        yu[lit].astype(f32),
    )


def test_a_still_cell_reads_as_the_share_of_its_own_pixels():
    reader = CellReader(CONFIG, first_burst_us=0.0)
    T = _pose()
    to_grid = reader._to_grid(T)
    pixels = reader._inner_pixels(T, to_grid, still=True)
    assert pixels.min() <= 5 and pixels.max() >= 8  # an area would misjudge cells by ~2x
    payload = np.random.default_rng(0).integers(0, 2, (16, 16)).astype(bool)
    cells = locator_block(reader.config.geometry, payload)
    ev = _white_bursts(reader, T, cells)
    g = to_grid @ np.stack([ev.xu, ev.yu, np.ones(len(ev))])
    u, v = (g[:2] / g[2]).astype(np.float32)
    count = reader._count(ev.t, ev.p, u, v, 0)[0, 0]  # ON bursts
    assert np.array_equal(count[cells], pixels[cells]) and not count[~cells].any()


def test_a_still_frame_reads_exactly_with_full_confidence():
    reader = CellReader(CONFIG, first_burst_us=0.0)
    T = _pose()
    payload = np.random.default_rng(1).integers(0, 2, (16, 16)).astype(bool)
    read = reader.read(
        0, _white_bursts(reader, T, locator_block(reader.config.geometry, payload)), _still(T)
    )
    assert np.array_equal(read.bits, payload)
    assert read.confidence.min() == 1.0 and read.locator_score == pytest.approx(1.0)


def test_pixel_counts_are_kept_while_the_grid_stands_and_redone_when_it_moves():
    reader = CellReader(CONFIG, first_burst_us=0.0)
    T = _pose()
    first = reader._inner_pixels(T, reader._to_grid(T), still=True)
    jitter = _pose(distance_m=0.6 + 1e-6)  # a tracked pose's noise, far below a pixel
    assert reader._inner_pixels(jitter, reader._to_grid(jitter), still=True) is first
    moved = _pose(tilt_deg=12.0)
    recount = reader._inner_pixels(moved, reader._to_grid(moved), still=True)
    assert recount is not first and not np.array_equal(recount, first)


def _density(payload_density: np.ndarray) -> np.ndarray:
    """A locator-grid density map: ring cells at exactly 0 or 1, the given payload inside."""
    density = CONFIG.geometry.inner_locator.astype(float)
    density[1:-1, 1:-1] = payload_density
    return on_only(density)


def test_the_threshold_follows_a_dim_payload():
    # Under motion a white payload cell's border pixels fire late: it reads at about half of a
    # ring cell, so the ring's own midpoint would split the white cells.
    rng = np.random.default_rng(2)
    payload = rng.integers(0, 2, (16, 16)).astype(bool)
    dim = np.where(
        payload, rng.normal(0.5, 0.05, payload.shape), rng.uniform(0, 0.05, payload.shape)
    )
    assert (dim[payload] < 0.5).sum() > 20
    read = CellReader(CONFIG, first_burst_us=0.0)._classify(0, _density(dim), 1000)
    assert np.array_equal(read.bits, payload)


def test_what_lit_neighbours_spill_into_a_dark_cell_is_taken_off(monkeypatch):
    # Blur: each lit 4-neighbour adds 0.25 of the contrast to a cell, each diagonal one 0.1,
    # so a dark cell amid lit ones reads 1.4 and a lone lit cell 1.0.
    rng = np.random.default_rng(5)
    payload = rng.integers(0, 2, (16, 16)).astype(bool)
    lit = CONFIG.geometry.inner_locator.copy()
    lit[1:-1, 1:-1] = payload
    padded = np.pad(lit, 1).astype(float)
    sides = padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]
    corners = padded[:-2, :-2] + padded[:-2, 2:] + padded[2:, :-2] + padded[2:, 2:]
    blurred = lit + 0.25 * sides + 0.1 * corners + rng.normal(0, 0.02, lit.shape)
    reader = CellReader(CONFIG, first_burst_us=0.0)
    read = reader._classify(0, on_only(blurred), 1000)
    assert np.array_equal(read.bits, payload)
    # Taken as they are, the densities misread the dark cells amid lit ones.
    monkeypatch.setattr(decoder, "_less_spill", lambda density, lit: density)
    assert (reader._classify(0, on_only(blurred), 1000).bits != payload).sum() >= 3


@pytest.mark.parametrize("colour", [0, 1])
def test_a_payload_of_one_colour_reads_as_that_colour(colour):
    rng = np.random.default_rng(3)
    flat = np.abs(colour - rng.uniform(0, 0.1, (16, 16)))
    read = CellReader(CONFIG, first_burst_us=0.0)._classify(0, _density(flat), 1000)
    assert np.all(read.bits == colour)


def test_only_cells_that_could_go_either_way_become_erasures():
    payload = np.tile([0.0, 1.0], (16, 8))
    payload[0, :4] = [0.5 - 1 / 10, 0.5 + 1 / 10, 0.5 - 1 / 200, 0.5 + 1 / 200]
    read = CellReader(CONFIG, first_burst_us=0.0)._classify(0, _density(payload), 1000)
    erasure_below = get_profile("robust").erasure_below  # the framed profiles' RS erasures
    assert np.all(read.confidence[0, :2] >= erasure_below)
    assert np.all(read.confidence[0, 2:4] < erasure_below)
    assert read.confidence[1:].min() == 1.0
    # Below full confidence the confidences rank the cells, for the decoder's extra erasures.
    assert read.confidence[0, 2:4].max() < read.confidence[0, :2].min() < 1.0
    # Sure a 32nd of the contrast away (``DecoderParams.sure_contrast``): only the two nearest
    # fall short of full confidence.
    narrow = replace(CONFIG, decoder=replace(CONFIG.decoder, sure_contrast=1 / 32))
    read = CellReader(narrow, first_burst_us=0.0)._classify(0, _density(payload), 1000)
    assert np.all(read.confidence[0, :2] == 1.0)
    assert np.all(read.confidence[0, 2:4] < 1.0)


def test_a_frame_read_before_any_burst_timed_the_clock_is_not_seen():
    # ``fast`` shows the locator on every other refresh: the first frame the lock reads back
    # may be one where it does not rise, so the scan-out slope is still unknown.
    reader = CellReader(ReceiverConfig(CAMERA, cells=16, profile="fast"), first_burst_us=0.0)
    T = _pose()
    payload = np.random.default_rng(4).integers(0, 2, (16, 16)).astype(bool)
    cells = locator_block(reader.config.geometry, payload)
    untimed = reader.read(-1, _white_bursts(reader, T, cells, m=-1), _still(T))
    assert untimed.locator_score == 0.0
    timed = reader.read(0, _white_bursts(reader, T, cells, m=0), _still(T))
    assert timed.locator_score > 0.9 and np.array_equal(timed.bits, payload)


def _fast_frame(on: np.ndarray, off: np.ndarray, m: int) -> np.ndarray:
    """(2, n, n) ON and OFF densities of ``fast`` frame ``m``: the payload's as given, the
    ring's white cells switching on (even ``m``) or off in full, its black ones quiet."""
    ring = CONFIG.geometry.inner_locator.astype(float)
    density = np.zeros((2, *ring.shape))
    density[m % 2] = ring
    density[:, 1:-1, 1:-1] = on, off
    return density


def test_a_fast_cell_that_just_went_dark_reads_in_its_switch_on_alone():
    # A display whose fall outlasts the refresh (an LCD falling over 4.4 ms at 165 Hz): a fall
    # starts OFF bursts in some of its pixels within the gate, and almost as many late, in the
    # next refresh's gate, where that cell can only switch on.
    reader = CellReader(replace(CONFIG, profile="fast"), first_burst_us=0.0)
    rng = np.random.default_rng(7)
    lit = rng.integers(0, 2, (16, 16)).astype(bool)
    late = np.zeros((16, 16))
    reads = []
    for m in range(2):
        toggles = rng.integers(0, 2, (16, 16)).astype(bool)
        on = np.where(toggles & ~lit, 0.9, 0.0)
        off = np.where(toggles & lit, 0.6, 0.0) + late
        late = np.where(toggles & lit, 0.5, 0.0)
        lit ^= toggles
        density = _fast_frame(on, off, m) + rng.uniform(0.0, 0.05, (2, 18, 18))
        reads.append((m, density, toggles))
    for m, density, toggles in reads:
        assert np.array_equal(reader._classify(m, density, 1000).bits, toggles)
    # Read without the frame before, the late bursts pass for switches.
    fresh = CellReader(replace(CONFIG, profile="fast"), first_burst_us=0.0)
    m, density, toggles = reads[1]
    assert (fresh._classify(m, density, 1000).bits != toggles).sum() >= 10


def test_a_fast_cell_whose_last_switch_was_misread_still_reads_its_next_one(monkeypatch):
    # Frame 0 read a fifth of the cells as switched the wrong way: in frame 1 those switch the
    # way they were not expected to, at a whole switch's level, above the late bursts and the
    # spill that the other cells of known state fire in that polarity.
    config = replace(CONFIG, profile="fast")
    rng = np.random.default_rng(8)
    lit = rng.integers(0, 2, (16, 16)).astype(bool)  # after frame 0
    misread = rng.random((16, 16)) < 0.2
    toggles = rng.integers(0, 2, (16, 16)).astype(bool)
    on = np.where(toggles & ~lit, 0.9, 0.0) + rng.uniform(0.0, 0.1, lit.shape)
    off = np.where(toggles & lit, 0.9, 0.0) + rng.uniform(0.0, 0.1, lit.shape)
    density = _fast_frame(on, off, 1)

    def read() -> np.ndarray:
        reader = CellReader(config, first_burst_us=0.0)
        reader._switched = (0, np.where(lit ^ misread, 1, -1).astype(np.int8))
        return reader._classify(1, density, 1000).bits

    assert np.array_equal(read(), toggles)
    # Read in the expected polarity alone, the misread cells that switch are lost.
    monkeypatch.setattr(decoder, "_OTHER_FLOOR", 100.0)
    assert (read() != toggles).sum() >= 10
