"""Interior samples of an asset: where its own SDF is negative, one per cell of a coarse lattice.

Surface samples alone read a deep overlap as shallow and two coincident objects as clean: every
surface point of one lies on (or just off) the other's surface. Interior samples close that hole
(docs/physics.md, "Sound penetration"): the engine treats them like surface samples, so an object
placed inside another reads as deep as its samples reach into it.

The lattice splits the normalised cube [-1, 1]^3 into ``per_axis``^3 cells; each cell that holds
grid nodes inside the shape (φ < 0) contributes the inside node nearest its centre. A solid shape
gets a regular lattice (a box: every cell, the centre cell's sample at the centre); a thin wall
(a bowl, a pen holder) gets a node inside the wall in every cell the wall crosses, and a cavity
(the bowl's inside, where φ > 0) gets none.
"""

from __future__ import annotations

import numpy as np

__all__ = ["INTERIOR_PER_AXIS", "interior_points"]

INTERIOR_PER_AXIS = 7
"""Lattice cells per axis (odd: a symmetric solid gets a sample at its centre). docs/physics.md
measures 5, 7 and 9 against the analytic sweep and the engine's cost."""


def interior_points(sdf: np.ndarray, per_axis: int = INTERIOR_PER_AXIS) -> np.ndarray:
    """(Q, 3) float32 interior samples of the SDF grid ``sdf`` (R, R, R), normalised frame.

    Q <= per_axis^3; deterministic (no randomness), ordered by cell. ``per_axis`` = 0 gives none.
    """
    if per_axis < 0:
        raise ValueError(f"interior samples per axis must be >= 0, got {per_axis}")
    grid = np.asarray(sdf)
    if grid.ndim != 3 or len(set(grid.shape)) != 1 or grid.shape[0] < 2:
        raise ValueError(f"sdf must be an (R, R, R) grid, got shape {grid.shape}")
    if per_axis == 0:
        return np.zeros((0, 3), np.float32)
    res = grid.shape[0]
    inside = np.argwhere(grid < 0.0)  # (M, 3) node indices
    if not len(inside):
        return np.zeros((0, 3), np.float32)
    q = -1.0 + inside * (2.0 / (res - 1))  # node coordinates
    cell3 = np.clip(np.floor((q + 1.0) * 0.5 * per_axis), 0, per_axis - 1).astype(np.int64)
    centre = -1.0 + (2.0 * cell3 + 1.0) / per_axis
    distance = np.abs(q - centre).sum(axis=1)  # L1: ties broken by the node order below
    cell = (cell3[:, 0] * per_axis + cell3[:, 1]) * per_axis + cell3[:, 2]
    order = np.lexsort((distance, cell))  # by cell, nearest the centre first
    first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    return q[first].astype(np.float32)
