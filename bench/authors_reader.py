"""The authors' cell reader, as their published code reads, on a ``bench.realistic`` clip.

It answers where the bit errors of the paper's real camera come from: the camera, or the
reader. The `paper` profile's still clip at ``P`` pixels per cell (``bench.realistic``'s
scene: 1.25 m, 250 lux, 60 Hz) is simulated once, and its ON events are read the way the
authors' decoder reads them:

- a surface of each pixel's latest ON event, normalised to the newest ON event anywhere on
  the sensor over a third of a data frame's period, warped bilinearly onto 10 x 10 pixels per
  cell and binarised at 0.1 (an ON event within 0.9 of that span);
- a cell is 1 when more than 60% of its pixels are on;
- three such reads per data frame, spread over the scan-out found by a search of 50 checks
  over half a period (the first check whose first payload row, then last, is a quarter
  lit, plus a tenth of a period), one data-frame period apart from then on, and ORed.

Where their receiver would estimate, this one is given the truth, so its errors are the
reader's alone: the locator's true image corners (no tracking error, no affine approximation
of the locator from the tracked ring), the display's exact period (no clock slip), and the
scan-out search started at a data refresh whose first and last payload rows are lit. Each
read is scored against the data refresh it sees.

The same reads are also scored with the 60% rule applied to each cell's inner part only (a
fifth of each side left out, as our reader's ``DecoderParams.cell_margin``), and the black
cells read 1 are counted by how many of their four neighbours are white.

Run: ``NUMBA_NUM_THREADS=1 nice .venv/bin/python -m bench.authors_reader --px 7 10 13``
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import cv2
import numpy as np

from bench.realistic import CLIP_S, scene_for
from eventocc.receiver.pipeline.report import FrameTruth
from eventocc.receiver.sim import simulate
from eventocc.receiver.sim.motion import project_points

REFRESH_HZ = 60.0
CANVAS_PX = 10
"""Canvas pixels per cell side."""
ON_LEVEL = 0.1
"""A canvas pixel is on above this normalised surface level."""
CELL_SHARE = 0.6
"""A cell is 1 when more than this share of its canvas pixels is on."""
READS = 3
CHECKS = 50
ROW_SHARE = 0.25
"""The scan-out search's check: more than this share of the locator's side lit in a row."""
INNER_MARGIN = 0.2


@dataclass(frozen=True)
class Result:
    preset: str
    px_per_cell: float
    cells: int
    frames: int
    errors: int
    """Bit errors of the authors' rule over ``frames`` data frames..."""
    zero_to_one: int
    """...of which black cells read 1."""
    errors_inner: int
    """Bit errors with the same rule over each cell's inner part."""
    black_read_one: tuple[tuple[int, int], ...]
    """Per count of white 4-neighbours (0-4): (black cells read 1, black cells)."""
    wall_s: float

    @property
    def bits(self) -> int:
        return self.frames * self.cells**2


class SurfaceReader:
    """The authors' read of one instant: latest-ON surface, warp, binarise, cell share."""

    def __init__(self, corners_px: np.ndarray, side_cells: int, shape: tuple[int, int]):
        self.side = side_cells
        s = CANVAS_PX * side_cells
        canvas = np.float32([[0, 0], [s - 1, 0], [s - 1, s - 1], [0, s - 1]])
        self.H = cv2.getPerspectiveTransform(corners_px.astype(np.float32), canvas)
        self.size = s
        self.latest_on = np.full(shape[0] * shape[1], -np.inf)
        self.width = shape[1]

    def feed(self, events: np.ndarray) -> None:
        on = events[events["p"] > 0]
        idx = on["y"].astype(np.int64) * self.width + on["x"]
        np.maximum.at(self.latest_on, idx, on["t"].astype(np.float64))

    def cells(self, span_us: float, margin: float = 0.0) -> np.ndarray:
        """(side, side) bools: the cells read 1 now."""
        newest = self.latest_on.max()
        level = (self.latest_on - (newest - span_us)) / span_us
        level[~(level > 0)] = 0.0
        image = level.reshape(-1, self.width).astype(np.float32)
        warped = cv2.warpPerspective(image, self.H, (self.size, self.size), flags=cv2.INTER_LINEAR)
        on = (warped > ON_LEVEL).reshape(self.side, CANVAS_PX, self.side, CANVAS_PX)
        m = round(CANVAS_PX * margin)
        on = on[:, m : CANVAS_PX - m, :, m : CANVAS_PX - m]
        return on.sum(axis=(1, 3)) > CELL_SHARE * on.shape[1] * on.shape[3]


def run(preset: str, px: float, seed: int = 0) -> Result:
    t0 = time.perf_counter()
    scene = scene_for(preset, "paper", REFRESH_HZ, px, seed)
    enc, cam = scene.encoder, scene.camera
    geo = enc.geometry
    n, side = geo.cells, geo.locator_side
    pose = scene.motion.trajectory(scene.rig).pose_at(np.zeros(1))[0]
    reader = SurfaceReader(
        project_points(cam, pose, geo.locator_corners(scene.marker_size_m)),
        side,
        (cam.height, cam.width),
    )
    truth = FrameTruth(enc, REFRESH_HZ, scene.start_refresh)
    period = enc.profile.data_every * 1e6 / REFRESH_HZ
    span = period / READS
    clip_us = CLIP_S[REFRESH_HZ] * 1e6

    def lit(k: int) -> bool:
        sent = truth.sent(k)
        return enc.is_data_frame(k) and min(sent[0].sum(), sent[-1].sum()) > ROW_SHARE * side

    first = next(k for k in range(2, 1000) if lit(k))  # after a frame's worth of events
    checks = [first * 1e6 / REFRESH_HZ + j * period / 2 / (CHECKS - 1) for j in range(CHECKS)]
    start = end = None
    reads: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    queue = [(t, -1) for t in checks]
    for chunk in simulate(scene, CLIP_S[REFRESH_HZ]):
        while queue and len(chunk) and queue[0][0] <= chunk["t"][-1]:
            t, slot = queue.pop(0)
            before = chunk["t"] <= t
            reader.feed(chunk[before])
            chunk = chunk[~before]
            if slot >= 0:
                reads[slot] = (reader.cells(span), reader.cells(span, INNER_MARGIN))
                continue
            rows = reader.cells(span)
            if start is None:
                start = t if rows[1].sum() > ROW_SHARE * side else None
            elif end is None and rows[n].sum() > ROW_SHARE * side:
                end = t + 0.1 * period
                m = 0
                while start + (m + 1) * period + (end - start) < clip_us:
                    for i in range(READS):
                        t_read = start + (m + 1) * period + i * (end - start) / (READS - 1)
                        queue.append((t_read, m * READS + i))
                    m += 1
                queue.sort()
        reader.feed(chunk)

    frames = errors = zero_to_one = errors_inner = 0
    black = np.zeros((5, 2), int)
    for m in range(len(reads) // READS):
        ored = [np.zeros((side, side), bool) for _ in range(2)]
        for i in range(READS):
            for j in range(2):
                ored[j] |= reads[m * READS + i][j]
        got, got_inner = (g[1 : n + 1, 1 : n + 1] for g in ored)
        matched = truth.match(got, start + (m + 1) * period)
        if matched is None:
            continue
        sent = truth.sent(matched[0]).astype(bool)
        frames += 1
        errors += int((got != sent).sum())
        zero_to_one += int((got & ~sent).sum())
        errors_inner += int((got_inner != sent).sum())
        padded = np.pad(sent, 1)
        white = padded[:-2, 1:-1].astype(int) + padded[2:, 1:-1] + padded[1:-1, :-2]
        white += padded[1:-1, 2:]
        for c in range(5):
            cells = ~sent & (white == c)
            black[c] += (int((got & cells).sum()), int(cells.sum()))
    return Result(
        preset,
        px,
        n,
        frames,
        errors,
        zero_to_one,
        errors_inner,
        tuple((int(a), int(b)) for a, b in black),
        time.perf_counter() - t0,
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--px", type=float, nargs="+", default=(7.0, 10.0, 13.0))
    parser.add_argument("--presets", nargs="+", default=("evk4",))
    args = parser.parse_args(argv)
    print(
        "| camera | px/cell | N | frames | BER, authors' rule (0->1 share) | BER, rule on the "
        "inner part | black cells read 1, by white neighbours 0/1/2/3/4 |"
    )
    print("|---|---|---|---|---|---|---|")
    for preset in args.presets:
        for px in args.px:
            r = run(preset, px)
            bits = max(r.bits, 1)
            black = " / ".join(f"{a} of {b}" for a, b in r.black_read_one)
            share = r.zero_to_one / r.errors if r.errors else 0.0
            print(
                f"| {preset} | {px:g} | {r.cells} | {r.frames} | {100 * r.errors / bits:.3f}% "
                f"({share:.0%}) | {100 * r.errors_inner / bits:.3f}% | {black} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
