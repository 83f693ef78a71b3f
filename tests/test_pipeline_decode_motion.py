"""Decoding while a hand-held camera moves: the read gate that follows the locator's own burst
spread, the sub-cell grid alignment on the ring, and the receiver's bit error rate on the small
virtual event camera of ``bench.tracking``, with the tracked pose and with the true one."""

from __future__ import annotations

import os

import numpy as np
import pytest

from bench.tracking import CAMERA, MESSAGE, hand_held_config, hand_held_scene
from eventocc.receiver.pipeline.config import DecoderParams, ReceiverConfig
from eventocc.receiver.pipeline.decoder import _ALIGN_SHIFTS, CellReader
from eventocc.receiver.pipeline.receiver import MessageOutput, Receiver
from eventocc.receiver.pipeline.report import DecodeLog, FrameTruth, decode_events
from eventocc.receiver.poses import invert
from eventocc.receiver.sim import simulate
from tests.cells import locator_block

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

SLOPE_US = 600.0
"""Scan-out time per locator row (a 60 Hz screen filled by the marker, N = 16)."""
PX_PER_CELL = 5
INNER_PX = PX_PER_CELL**2 * (1 - 2 * DecoderParams().cell_margin) ** 2
"""Pixels inside a cell's inner part."""


def _reader() -> CellReader:
    reader = CellReader(ReceiverConfig(CAMERA), first_burst_us=0.0)
    reader.clock.slope_us = SLOPE_US
    return reader


def _frame(
    reader: CellReader,
    cells: np.ndarray,
    rng: np.random.Generator,
    late: np.ndarray | None = None,
    shift: tuple[float, float] = (0.0, 0.0),
    m: int = 0,
    polarity: int = 1,
):
    """(t, p, u, v) of frame ``m``: one burst of sign ``polarity`` per pixel of the lit
    ``cells`` (locator grid, 5x5 pixels a cell) at its row's scan-out time with 150 us of
    jitter, plus one a few ms late on the pixels of ``late``: cells that a neighbour's image
    sweeps over after the switch. ``shift`` moves every burst on the grid, as a pose that
    trails the camera does."""
    n = reader.n
    side = np.arange(PX_PER_CELL) / PX_PER_CELL + 0.5 / PX_PER_CELL
    grid_u, grid_v = np.meshgrid(np.arange(n)[:, None] + side, np.arange(n)[:, None] + side)
    u, v = grid_u.ravel(), grid_v.ravel()  # every pixel centre of the locator
    lit = cells[v.astype(int), u.astype(int)]
    t = reader.clock.mid(m) + (v - 0.5 - n / 2) * SLOPE_US + rng.normal(0, 150, u.size)
    keep = lit.copy()
    if late is not None:
        swept = late[v.astype(int), u.astype(int)]
        t[swept] += rng.uniform(3000, 8000, swept.sum())
        keep |= swept
    u, v, t = u[keep] + shift[0], v[keep] + shift[1], t[keep]
    order = np.argsort(t)
    f32 = np.float32
    return (
        t[order].astype(np.int64),
        np.full(order.size, polarity, np.int8),
        u[order].astype(f32),
        v[order].astype(f32),
    )


def _aligned_count(reader: CellReader, t, p, u, v) -> np.ndarray:
    """(2, n, n) cell counts on the shifted grid that ``CellReader.read`` picks for a moving
    camera."""
    counts = reader._count(t, p, u, v, 0, _ALIGN_SHIFTS)
    return counts[reader._sharpest(counts.sum(axis=1) / INNER_PX)]


def _read(reader: CellReader, t, p, u, v):
    """The frame as ``CellReader.read`` classifies it, from bursts already on the grid."""
    reader._retime(0, t, p, u, v)
    count = _aligned_count(reader, t, p, u, v)
    return reader._classify(0, count / INNER_PX, int(count.sum()))


def test_read_gate_narrows_to_the_locator_bursts_and_drops_swept_cells():
    rng = np.random.default_rng(0)
    reader = _reader()
    payload = rng.integers(0, 2, (16, 16)).astype(bool)
    cells = locator_block(reader.config.geometry, payload)
    late = np.zeros_like(cells)
    late[1:-1, 1:-1] = ~payload & (rng.random((16, 16)) < 0.5)  # half the black cells swept
    wide = reader.gate
    read = _read(reader, *_frame(reader, cells, rng, late))
    lo, hi = reader.gate
    assert wide[0] < lo < -300 and 300 < hi < 1500 < wide[1], reader.gate
    assert np.array_equal(read.bits, payload)


def test_fast_read_gate_spans_both_switches_of_the_locator_not_the_bursts_before_them():
    """``fast`` reads ON and OFF bursts: its gate spans the locator's ON switch (it lights up on
    even refreshes) and its OFF switch (odd ones), not the OFF bursts that a moving camera's
    edges start on the lit cells all through the refresh before they switch off."""
    rng = np.random.default_rng(3)
    reader = CellReader(ReceiverConfig(CAMERA, profile="fast"), first_burst_us=0.0)
    reader.clock.slope_us = SLOPE_US
    ring = locator_block(reader.config.geometry, np.zeros((16, 16), bool))
    wide = reader.gate
    t, p, u, v = _frame(reader, ring, rng)
    reader._retime(0, t, p, u, v)
    assert reader.gate == wide  # the ON switch alone: a narrow gate would cut the OFF one
    t, p, u, v = _frame(reader, ring, rng, m=1, polarity=-1)
    swept = rng.random(t.size) < 0.5  # half the lit pixels also fire as an edge passes
    rows = reader.clock.mid(1) + (v[swept] - 0.5 - reader.n / 2) * SLOPE_US
    t = np.r_[t, rows + rng.uniform(wide[0], 0.0, swept.sum())]
    order = np.argsort(t)
    p, u, v = (np.r_[a, a[swept]][order] for a in (p, u, v))
    reader._narrow_gate(1, t[order].astype(np.int64), p, u, v)
    lo, hi = reader.gate
    assert -800 < lo < -300 and 300 < hi < 800, reader.gate
    assert reader.gate_opens(2, np.eye(4)) is None  # the triage's cut is ON-only profiles'
    # The narrowed gate reads a moving grid's frames; a still one's read through the whole
    # read gate, and behind a sparse readout through the narrowed one too, where it separates
    # the cells better.
    mid, half = reader.clock.mid(2), abs(reader.clock.slope_us) * reader.n / 2
    reader._moving = True
    assert reader.window(2) == (int(mid - half + lo), int(mid + half + hi) + 1)
    assert reader._gates() == [reader.gate]
    reader._moving = False
    assert reader.window(2) == (int(mid - half + wide[0]), int(mid + half + wide[1]) + 1)
    assert reader._gates() == [wide]
    reader.sparse = True
    assert reader._gates() == [wide, reader.gate]


def test_a_grid_that_trails_by_a_third_of_a_cell_is_pulled_back_onto_the_ring():
    rng = np.random.default_rng(1)
    reader = _reader()
    cells = locator_block(reader.config.geometry, rng.integers(0, 2, (16, 16)).astype(bool))
    t, p, u, v = _frame(reader, cells, np.random.default_rng(2))
    reader._retime(0, t, p, u, v)
    truth = reader._count(t, p, u, v, 0)[0, 0]  # ON bursts
    shifted = (u + np.float32(0.35), v - np.float32(0.35))
    spilled = reader._count(t, p, *shifted, 0)[0, 0]
    assert spilled[~cells].max() > 0  # white spills into black cells
    aligned = _aligned_count(reader, t, p, *shifted)[0]
    assert aligned[~cells].max() == 0
    assert np.abs(aligned - truth).max() <= 1  # a pixel on a cell's inner border may flip


def test_a_non_positive_pose_step_is_refused():
    config = ReceiverConfig(CAMERA, decoder=DecoderParams(step_us=0))
    with pytest.raises(ValueError, match="step_us must be positive"):
        CellReader(config, first_burst_us=0.0)


def _decode(flow_px_per_ms: float, duration_s: float, true_pose: bool = False, seed: int = 0):
    """The hand-held scene decoded with the tracked pose, or with the true one injected (the
    decoder's own floor)."""
    scene = hand_held_scene(flow_px_per_ms, seed)
    rec = simulate(scene, duration_s=duration_s, chunk_us=10_000)
    rx = Receiver(hand_held_config())
    if true_pose:
        rx.pose_at = lambda t_us: invert(rec.pose_at(t_us))
    return decode_events(rx, rec, FrameTruth(scene.encoder, scene.display.refresh_hz))


@pytest.fixture(scope="module")
def tracked_half_px() -> DecodeLog:
    return _decode(0.5, 0.6)


def test_bits_under_half_a_pixel_per_ms_with_the_tracked_pose(tracked_half_px):
    log = tracked_half_px
    assert log.frames >= 12, f"only {log.frames} frames showed the inner locator"
    assert log.ber is not None and log.ber <= 0.04, f"BER {log.ber:.3f} before FEC"


def test_most_frames_pass_reed_solomon_under_half_a_pixel_per_ms(tracked_half_px):
    # Confidence erases only the cells that could go either way: with a quarter of the contrast
    # as the span of doubt, half of these frames failed RS on erasures of cells read right.
    log = tracked_half_px
    held = sum(s["symbols_held"] for s in log.receiver.stream.progress().values())
    assert held >= 0.75 * log.frames, f"{held} of {log.frames} frames passed RS and the CRC"


def test_the_decoders_own_floor_with_the_true_pose():
    log = _decode(0.5, 0.6, true_pose=True)
    assert log.frames >= 12 and log.ber is not None and log.ber <= 0.02, log.ber


@pytest.mark.slow
def test_the_message_decodes_under_half_a_pixel_per_ms():
    log = _decode(0.5, 3.0)
    assert [m.message.data for m in log.messages] == [MESSAGE], log.receiver.stream.progress()
    assert isinstance(log.messages[0], MessageOutput)


@pytest.mark.slow
@pytest.mark.parametrize("flow", [1.0])
def test_the_decoders_own_floor_at_a_pixel_per_ms(flow):
    log = _decode(flow, 1.0, true_pose=True)
    assert log.ber is not None and log.ber <= 0.05, log.ber
