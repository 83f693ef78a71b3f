"""Geometry and rendering of the dynamic marker (paper Fig. 2, authors' generator).

From the centre outwards, in cells:

- payload, ``N x N`` data cells (1 = white);
- the inner locator ring, 1 cell wide: solid left column and bottom row (the "L"), dashed top row
  and right column (white at even positions), top-right corner white;
- the exterior locator: three static rings ``ring`` cells wide, black, white, black.

Data frames show everything; blank frames show the exterior rings only. The marker frame (metres)
has its origin at the top-left outer corner of the white ring, x right, y down, z into the screen.
``size_m`` is the physical side of the white ring's outer boundary, which spans
``N + 2 + 4 * ring`` cells.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

MIN_CELLS, MAX_CELLS = 8, 128


def default_ring(cells: int) -> int:
    return max(1, math.ceil(cells / 16))


@dataclass(frozen=True)
class MarkerGeometry:
    cells: int = 16
    """N, the payload side in cells."""
    ring: int = 0
    """Width of each exterior ring in cells; 0 picks ``max(1, ceil(N / 16))``."""

    def __post_init__(self) -> None:
        if not MIN_CELLS <= self.cells <= MAX_CELLS:
            raise ValueError(f"cells must be {MIN_CELLS}..{MAX_CELLS}, got {self.cells}")
        if self.ring == 0:
            object.__setattr__(self, "ring", default_ring(self.cells))
        if self.ring < 1:
            raise ValueError(f"ring width must be >= 1 cell, got {self.ring}")

    # --- sizes in cells -------------------------------------------------------------------
    @property
    def side(self) -> int:
        """Cells across the whole marker, outer black ring included."""
        return self.cells + 2 + 6 * self.ring

    @property
    def locator_side(self) -> int:
        """Cells across the inner locator ring (payload included)."""
        return self.cells + 2

    @property
    def tracked_side(self) -> int:
        """Cells across the white ring's outer boundary: the span of ``size_m``."""
        return self.cells + 2 + 4 * self.ring

    @property
    def payload_offset(self) -> int:
        """Row/column of the first payload cell in the full cell matrix."""
        return 3 * self.ring + 1

    @property
    def bits_per_frame(self) -> int:
        return self.cells * self.cells

    # --- cell matrices ------------------------------------------------------------------
    @cached_property
    def inner_locator(self) -> np.ndarray:
        """Boolean (N+2, N+2) ring, canonical orientation, interior False."""
        n = self.locator_side
        loc = np.zeros((n, n), dtype=bool)
        idx = np.arange(n)
        loc[0, :] = idx % 2 == 0  # dashed top row
        loc[:, -1] = idx % 2 == 1  # dashed right column
        loc[0, -1] = loc[1, -1] = True  # top-right corner: two whites on both dashed edges
        loc[:, 0] = True  # solid left column
        loc[-1, :] = True  # solid bottom row
        return loc

    @cached_property
    def blank_frame(self) -> np.ndarray:
        """Boolean (side, side) matrix of a blank frame: exterior rings only."""
        m = np.zeros((self.side, self.side), dtype=bool)
        r = self.ring
        m[r : self.side - r, r : self.side - r] = True
        m[2 * r : self.side - 2 * r, 2 * r : self.side - 2 * r] = False
        m.setflags(write=False)
        return m

    def data_frame(self, payload: np.ndarray, locator: bool = True) -> np.ndarray:
        """Full (side, side) cell matrix of a data frame showing ``payload`` (N x N, 1 = white)."""
        payload = np.asarray(payload)
        if payload.shape != (self.cells, self.cells):
            raise ValueError(f"payload must be {self.cells}x{self.cells}, got {payload.shape}")
        m = self.blank_frame.copy()
        o = 3 * self.ring
        if locator:
            m[o : o + self.locator_side, o : o + self.locator_side] = self.inner_locator
        p = self.payload_offset
        m[p : p + self.cells, p : p + self.cells] = payload.astype(bool)
        return m

    def payload_of(self, frame: np.ndarray) -> np.ndarray:
        """The N x N payload block of a full cell matrix."""
        p = self.payload_offset
        return frame[p : p + self.cells, p : p + self.cells]

    # --- world coordinates (metres, marker frame) ------------------------------------------
    def cell_size_m(self, size_m: float) -> float:
        return size_m / self.tracked_side

    def cell_to_world(self, size_m: float, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Marker-frame points (..., 3) of cell-grid coordinates (column, row), full matrix."""
        c = self.cell_size_m(size_m)
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        return np.stack([(col - self.ring) * c, (row - self.ring) * c, np.zeros_like(col)], -1)

    def tracked_edges(self, size_m: float) -> np.ndarray:
        """(8, 2, 3) segments: the outer then the inner boundary of the white ring, each as
        top, right, bottom, left, running clockwise (paper Sec. IV-C, edges E0..E7)."""
        s = size_m
        c = self.ring * self.cell_size_m(size_m)
        edges = []
        for lo, hi in ((0.0, s), (c, s - c)):
            corners = [(lo, lo), (hi, lo), (hi, hi), (lo, hi)]
            edges += [(corners[i], corners[(i + 1) % 4]) for i in range(4)]
        out = np.zeros((8, 2, 3))
        out[:, :, :2] = np.array(edges)
        return out

    def locator_corners(self, size_m: float) -> np.ndarray:
        """(4, 3) outer corners of the inner locator ring: TL, TR, BR, BL (canonical)."""
        c = self.cell_size_m(size_m)
        lo = 2 * self.ring * c
        hi = lo + self.locator_side * c
        return np.array([[lo, lo, 0.0], [hi, lo, 0.0], [hi, hi, 0.0], [lo, hi, 0.0]])

    def marker_corners(self, size_m: float) -> np.ndarray:
        """(4, 3) outer corners of the whole marker (outer black ring): TL, TR, BR, BL."""
        c = self.cell_size_m(size_m)
        lo, hi = -self.ring * c, (self.tracked_side + self.ring) * c
        return np.array([[lo, lo, 0.0], [hi, lo, 0.0], [hi, hi, 0.0], [lo, hi, 0.0]])


def render(frame: np.ndarray, cell_px: int, border_px: int = 0) -> np.ndarray:
    """Rasterise a cell matrix to a uint8 image (255 white), ``cell_px`` pixels per cell, crisp
    edges, on a black border of ``border_px`` pixels."""
    if cell_px < 1:
        raise ValueError(f"cell size must be >= 1 px, got {cell_px}")
    img = np.repeat(np.repeat(np.asarray(frame, dtype=np.uint8) * 255, cell_px, 0), cell_px, 1)
    if border_px:
        img = np.pad(img, border_px)
    return img
