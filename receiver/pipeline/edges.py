"""Sub-pixel corners of the inner locator from the image of pixels that fire with the bursts.

The outline of those pixels sits outside the locator's true edges: blur, and the sensor's
answer to the log of the light, make a dark pixel next to a lit cell fire in phase too, by a
pixel or more. The outline's four corners then make the marker look nearer than it is, and at a
few hundred pixels across, a pixel of such spread costs centimetres of pose.

The locator measures its own spread: each lit dash of its dashed top row and right column lies
between two dark ones, so its lit width is a cell plus the spread on both sides. Each outer edge
of a lit border cell sits where the lit length from the cell's centre outwards says, less that
spread; every length is a share of the lit level along that edge, since events thin out across
the marker (vignetting, the scan-out's phase gate). Straight lines through the border cells' edges,
in ideal pixels, meet at the corners.
"""

from __future__ import annotations

import cv2
import numpy as np

from eventocc.occ.marker import MarkerGeometry
from eventocc.receiver.camera import CameraModel

_SAMPLES = 16
"""Samples per cell along a profile."""
_ALONG = np.linspace(0.15, 0.85, 6)
"""Where across a cell its profiles run: its middle, clear of its neighbours' blur."""
_ACROSS = np.array([0.35, 0.5, 0.65])
"""Where across a dash the profiles along it run."""
_MIN_LEVEL = 0.25
"""A cell lit less than this share of the border's median level above the dark ring is not
seen (the phase gate missed its rows, or the view cut it) and gives no edge."""
_MIN_CELLS = 3
"""Cells an edge needs for its line."""
_MAX_SCATTER = 0.1
"""Median distance, in cells, of the border cells' edges from their line, beyond which the
image does not show the locator's border as it is (frames mixed in the window, a cell
misread): then the outline's corners stand."""
_ROUNDS = 2
"""Refinements, each on the grid the last one gave: the first moves the samples onto the cells."""


class _Grid:
    """The locator's cell grid, (column, row) in 0..L, as seen through a quadrilateral of its
    outer corners (TL, TR, BR, BL, distorted pixels): a homography onto ideal pixels."""

    def __init__(self, corners: np.ndarray, side: int, camera: CameraModel) -> None:
        square = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
        ideal = camera.undistort_points(corners).astype(np.float32)
        self.H = cv2.getPerspectiveTransform(square, ideal).astype(np.float64)
        self.camera = camera

    def ideal(self, uv: np.ndarray) -> np.ndarray:
        p = uv @ self.H[:, :2].T + self.H[:, 2]
        return p[..., :2] / p[..., 2:]

    def sensor(self, ideal: np.ndarray) -> np.ndarray:
        """Distorted (sensor) pixels of ideal pixels (..., 2)."""
        cam = self.camera
        xy = (ideal - cam.K[:2, 2]) / cam.K[[0, 1], [0, 1]]
        return cam.project(np.concatenate([xy, np.ones_like(xy[..., :1])], -1))

    def sample(self, image: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """``image`` (float32) at grid points ``uv`` (..., 2), bilinear, 0 outside."""
        flat = self.sensor(self.ideal(uv)).astype(np.float32).reshape(-1, 1, 2)
        out = cv2.remap(image, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderValue=0)
        return out.reshape(uv.shape[:-1])


def refine_corners(
    corners: np.ndarray, lit: np.ndarray, geometry: MarkerGeometry, camera: CameraModel
) -> np.ndarray:
    """(4, 2) corners (TL, TR, BR, BL in canonical order, distorted pixels) of the inner
    locator, refined from the rough ``corners`` on ``lit`` (1 where a pixel fires with the
    bursts); the rough ones where the image cannot say (too few border cells seen, their edges
    off straight lines, or a move of more than half a cell)."""
    image = np.ascontiguousarray(lit, np.float32)
    side = geometry.locator_side
    cell_px = np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).min() / side
    refined = corners
    for _ in range(_ROUNDS):
        found = _fit(_Grid(refined, side, camera), image, geometry, cell_px)
        if found is None:
            return corners
        refined = found
    return refined if np.abs(refined - corners).max() <= cell_px / 2 else corners


def _fit(
    grid: _Grid, image: np.ndarray, geometry: MarkerGeometry, cell_px: float
) -> np.ndarray | None:
    """The corners that the border cells' edges on ``image`` give through ``grid``, or None."""
    side, loc = geometry.locator_side, geometry.inner_locator
    dark = _dark_level(grid, image, geometry)
    spread = _spread(grid, image, loc, dark)
    if spread is None:
        return None
    # Profiles from across each cell (its inner side) to a cell outside it.
    steps = (np.arange(int(2 * _SAMPLES)) + 0.5) / _SAMPLES - 0.5
    inside, outer = np.abs(steps) < 0.35, steps >= 0
    lines = []
    for start, normal in _border(side, loc):
        # (cells, along, steps, 2) grid points of the profiles through each cell's centre.
        along = np.array([normal[1], -normal[0]]) * (_ALONG - 0.5)[:, None]
        uv = start[:, None, None] + along[None, :, None] + steps[:, None] * normal
        values = grid.sample(image, uv).mean(axis=1)
        level = _smooth_level(values[:, inside].mean(axis=1) - dark)
        if level is None:
            return None
        seen = level > 0
        lit = (values[seen][:, outer].sum(axis=1) / _SAMPLES - dark * steps[-1]) / level[seen]
        edge = start[seen] + (lit - spread)[:, None] * normal
        points = grid.ideal(edge).astype(np.float32)
        vx, vy, x0, y0 = cv2.fitLine(points, cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        scatter = np.median(np.abs((points[:, 0] - x0) * vy - (points[:, 1] - y0) * vx))
        if scatter > _MAX_SCATTER * cell_px:
            return None
        lines.append(np.cross([x0, y0, 1.0], [x0 + vx, y0 + vy, 1.0]))
    # TL is where the left edge (last) meets the top one (first), and so on clockwise.
    meet = np.cross(np.roll(lines, 1, axis=0), lines)
    if np.any(np.abs(meet[:, 2]) < 1e-9):
        return None
    return grid.sensor(meet[:, :2] / meet[:, 2:])


def _smooth_level(level: np.ndarray) -> np.ndarray | None:
    """Each cell's lit level above the dark ring, as a straight line along its edge through the
    cells seen: a cell's own few pixels are too few when a pixel fires now and then, while the
    level drifts across the marker with vignetting and the scan-out's phase gate. 0 where a cell
    is not seen; None when too few are."""
    seen = level >= _MIN_LEVEL * max(float(np.median(level)), 1e-6)
    if np.count_nonzero(seen) < _MIN_CELLS:
        return None
    k = np.arange(level.size)
    slope, offset = np.polyfit(k[seen], level[seen], 1)
    return np.where(seen, np.maximum(offset + slope * k, 1e-6), 0.0)


def _border(side: int, loc: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per outer edge (top, right, bottom, left): the grid centres of its lit border cells,
    corners left out, and its outward normal."""
    j = np.arange(1, side - 1)
    mid = side - 0.5
    edges = [
        (np.c_[j + 0.5, np.full(j.size, 0.5)], (0, -1), loc[0, j]),
        (np.c_[np.full(j.size, mid), j + 0.5], (1, 0), loc[j, -1]),
        (np.c_[j + 0.5, np.full(j.size, mid)], (0, 1), loc[-1, j]),
        (np.c_[np.full(j.size, 0.5), j + 0.5], (-1, 0), loc[j, 0]),
    ]
    return [(centres[lit], np.array(normal, float)) for centres, normal, lit in edges]


def _dark_level(grid: _Grid, image: np.ndarray, geometry: MarkerGeometry) -> float:
    """Mean of the image over the middle of the dark ring around the locator."""
    side, half = geometry.locator_side, geometry.ring / 2
    s = (np.arange(side * 4) + 0.5) / 4
    rims = [np.c_[s, np.full_like(s, -half)], np.c_[s, np.full_like(s, side + half)]]
    rims += [r[:, ::-1] for r in rims]
    return float(grid.sample(image, np.concatenate(rims)).mean())


def _spread(grid: _Grid, image: np.ndarray, loc: np.ndarray, dark: float) -> float | None:
    """How far, in cells, the lit area spreads past a lit cell's edge: half the median excess
    width of the dashes that lie between two dark cells, each width a share of its own lit
    level."""
    side = loc.shape[0]
    j = np.arange(2, side - 2)
    dashes = [
        np.c_[j[loc[0, j]], np.zeros(np.count_nonzero(loc[0, j]))],
        np.c_[np.full(np.count_nonzero(loc[j, -1]), side - 1), j[loc[j, -1]]],
    ]
    # Along each dash from half a cell before it to half a cell after, on lines across it.
    steps = (np.arange(2 * _SAMPLES) + 0.5) / _SAMPLES - 0.5
    widths = []
    for axis, cells in enumerate(dashes):
        solo = _between_dark(cells, axis, loc)
        if not solo.any():
            continue
        start = cells[solo][:, None, None].astype(float)
        uv = np.repeat(np.repeat(start, _ACROSS.size, 1), steps.size, 2)
        uv[..., axis] += steps
        uv[..., 1 - axis] += _ACROSS[:, None]
        values = grid.sample(image, uv).mean(axis=1)
        middle = (steps > 0.2) & (steps < 0.8)
        level = values[:, middle].mean(axis=1) - dark
        seen = level > 1e-6
        widths.append((values[seen].sum(axis=1) / _SAMPLES - 2 * dark) / level[seen])
    widths = np.concatenate(widths) if widths else np.empty(0)
    if widths.size < _MIN_CELLS:
        return None
    return float((np.median(widths) - 1) / 2)


def _between_dark(cells: np.ndarray, axis: int, loc: np.ndarray) -> np.ndarray:
    """Which dashes (column, row) have dark cells on both sides along ``axis``."""
    c, r = cells[:, 0].astype(int), cells[:, 1].astype(int)
    if axis == 0:
        return ~loc[r, c - 1] & ~loc[r, c + 1]
    return ~loc[r - 1, c] & ~loc[r + 1, c]
