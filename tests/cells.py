"""Cell matrices the decoder tests draw their synthetic frames from."""

from __future__ import annotations

import numpy as np

from eventocc.occ.marker import MarkerGeometry


def locator_block(geometry: MarkerGeometry, payload: np.ndarray) -> np.ndarray:
    """The (N+2, N+2) cells the decoder reads: the inner locator around the payload."""
    cells = geometry.inner_locator.copy()
    cells[1:-1, 1:-1] = payload
    return cells


def on_only(density: np.ndarray) -> np.ndarray:
    """(2, n, n) ON and OFF densities (``CellReader._classify``) of cells that fired ON only."""
    return np.stack([density, np.zeros_like(density)])
