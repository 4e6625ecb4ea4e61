"""The asset contract shared by the library, the bakers and the physics engine.

An asset is a shape in a canonical frame normalised to the box [-1, 1]^3 (z up, centred on its
bounding-box centre, each axis stretched to fill [-1, 1]) with
- ``sdf``: a signed distance grid, shape (R, R, R), float32, indexed [ix, iy, iz]; node k of an
  axis sits at -1 + 2k/(R-1) (node-aligned, both faces of the cube are nodes). Values are in
  normalised units, negative inside.
- ``points``: surface points, shape (P, 3), float32, in the same frame, including corners and
  sharp edges where the shape has them.

A posed object scales the asset to its ``size`` [w, d, h] (cm) and yaws it; how the engine turns
normalised distances into centimetres under non-uniform scale is documented in docs/physics.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Asset", "grid_coordinates"]


def grid_coordinates(resolution: int) -> np.ndarray:
    """The node coordinates of one grid axis, (R,) float64 over [-1, 1]."""
    if resolution < 2:
        raise ValueError(f"SDF resolution must be >= 2, got {resolution}")
    return np.linspace(-1.0, 1.0, resolution)


@dataclass(frozen=True, eq=False)
class Asset:
    """One shape of the library (see the module docstring for the frame and the arrays)."""

    asset_id: str
    """Unique id: ``primitive:box``, ``procedural:mug``, or a mesh folder's uid."""
    category: str
    """Category name (``mug``, ``book`` ...), as in the scene's objects."""
    source: str
    """Where it came from: ``primitive``, ``procedural`` or ``folder:<path>``."""
    sdf: np.ndarray = field(repr=False)
    """(R, R, R) float32 signed distances, normalised units."""
    points: np.ndarray = field(repr=False)
    """(P, 3) float32 surface points, normalised frame."""
    mesh: object | None = field(default=None, repr=False)
    """A ``trimesh.Trimesh`` in the normalised frame, when the asset has one."""
    description: str = ""
    extents: tuple[float, float, float] | None = None
    """The source mesh's real extents (w, d, h) in cm, when known; size priors come from here."""

    def __post_init__(self):
        sdf = np.ascontiguousarray(self.sdf, dtype=np.float32)
        points = np.ascontiguousarray(self.points, dtype=np.float32)
        if sdf.ndim != 3 or len(set(sdf.shape)) != 1 or sdf.shape[0] < 2:
            raise ValueError(f"asset {self.asset_id!r}: sdf must be (R, R, R), got {sdf.shape}")
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise ValueError(f"asset {self.asset_id!r}: points must be (P, 3), got {points.shape}")
        if not (np.all(np.isfinite(sdf)) and np.all(np.isfinite(points))):
            raise ValueError(f"asset {self.asset_id!r}: non-finite values in sdf or points")
        object.__setattr__(self, "sdf", sdf)
        object.__setattr__(self, "points", points)

    @property
    def resolution(self) -> int:
        return self.sdf.shape[0]

    @property
    def voxel(self) -> float:
        """Grid spacing in normalised units."""
        return 2.0 / (self.resolution - 1)
