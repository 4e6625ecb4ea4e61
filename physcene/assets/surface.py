"""Surface points of a mesh and trilinear sampling of an SDF grid, both in the normalised frame.

Surface points (default 1024) are deterministic for a seed and mix three kinds, so that a corner
or an edge pushed into a neighbour is seen by the penetration energy:

- corners: vertices where three or more sharp edges meet (all of them, up to 10 % of the budget);
- sharp edges: points uniformly along edges whose dihedral angle exceeds ``edge_angle_deg``
  (default 30 deg), and along boundary edges of open meshes (20 % of the budget, by length);
- the rest area-weighted over the faces.

Areas and lengths are weighed in the object's real proportions (``scale``, the half-extents) so a
flat plate does not spend its points on its rim, then the points are returned in the normalised
frame (barycentric sampling is affine-invariant, so the per-face distribution is unchanged).
"""

from __future__ import annotations

import numpy as np
import trimesh

from physcene.assets.asset import Asset

__all__ = ["sample_sdf", "sharp_edges", "surface_points"]


def sharp_edges(mesh: trimesh.Trimesh, edge_angle_deg: float = 30.0) -> np.ndarray:
    """(E, 2) vertex indices of edges sharper than ``edge_angle_deg`` plus open boundary edges."""
    angles = mesh.face_adjacency_angles
    sharp = mesh.face_adjacency_edges[angles > np.radians(edge_angle_deg)]
    edges = np.sort(mesh.edges, axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    out = (
        np.concatenate([np.sort(sharp, axis=1), boundary])
        if len(sharp) or len(boundary)
        else np.zeros((0, 2))
    )
    return np.unique(out.astype(np.int64), axis=0) if len(out) else np.zeros((0, 2), dtype=np.int64)


def surface_points(
    mesh: trimesh.Trimesh,
    n_points: int = 1024,
    seed: int = 0,
    *,
    scale=None,
    edge_angle_deg: float = 30.0,
    edge_fraction: float = 0.2,
    corner_fraction: float = 0.1,
) -> np.ndarray:
    """(n_points, 3) float32 points on ``mesh`` (normalised frame), corners and sharp edges included.

    Args:
        mesh: the mesh in the normalised frame.
        n_points: how many points.
        seed: the random seed; the same mesh and seed always give the same points.
        scale: (3,) half-extents of the real object (any unit) used to weigh areas and lengths;
            None weighs them in the normalised frame.
    """
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    rng = np.random.default_rng(seed)
    scale = np.ones(3) if scale is None else np.asarray(scale, dtype=np.float64)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    real = verts * scale

    edges = sharp_edges(mesh, edge_angle_deg)
    corners = np.zeros((0, 3))
    if len(edges):
        degree = np.bincount(edges.ravel(), minlength=len(verts))
        corner_ids = np.flatnonzero(degree >= 3)
        budget = int(corner_fraction * n_points)
        if len(corner_ids) > budget:
            corner_ids = np.sort(rng.choice(corner_ids, size=budget, replace=False))
        corners = verts[corner_ids]

    on_edges = np.zeros((0, 3))
    n_edge = int(edge_fraction * n_points) if len(edges) else 0
    if n_edge:
        lengths = np.linalg.norm(real[edges[:, 1]] - real[edges[:, 0]], axis=1)
        pick = rng.choice(len(edges), size=n_edge, p=lengths / lengths.sum())
        t = rng.random((n_edge, 1))
        on_edges = verts[edges[pick, 0]] * (1 - t) + verts[edges[pick, 1]] * t

    n_area = n_points - len(corners) - len(on_edges)
    tri = real[mesh.faces]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if areas.sum() <= 0:
        raise ValueError("mesh has zero surface area")
    pick = rng.choice(len(areas), size=n_area, p=areas / areas.sum())
    r1, r2 = rng.random((2, n_area, 1))
    s = np.sqrt(r1)  # uniform over the triangle
    a, b, c = (verts[mesh.faces[pick, k]] for k in range(3))
    on_faces = (1 - s) * a + s * (1 - r2) * b + s * r2 * c
    return np.concatenate([corners, on_edges, on_faces]).astype(np.float32)


def sample_sdf(asset: Asset | np.ndarray, q: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of an asset's SDF grid at normalised points q (..., 3) -> (...,).

    Node-aligned grid over [-1, 1]^3. Points outside the cube are clamped to it and the distance
    to the cube is added (an upper bound of the true distance there, exact in the far field's
    direction of the cube face).
    """
    grid = asset.sdf if isinstance(asset, Asset) else np.asarray(asset)
    res = grid.shape[0]
    q = np.asarray(q, dtype=np.float64)
    clamped = np.clip(q, -1.0, 1.0)
    outside = np.linalg.norm(q - clamped, axis=-1)
    u = (clamped + 1.0) * 0.5 * (res - 1)  # continuous node index
    i0 = np.clip(np.floor(u).astype(np.int64), 0, res - 2)
    f = u - i0
    value = np.zeros(q.shape[:-1])
    for dx in (0, 1):
        wx = f[..., 0] if dx else 1 - f[..., 0]
        for dy in (0, 1):
            wy = f[..., 1] if dy else 1 - f[..., 1]
            for dz in (0, 1):
                wz = f[..., 2] if dz else 1 - f[..., 2]
                value += wx * wy * wz * grid[i0[..., 0] + dx, i0[..., 1] + dy, i0[..., 2] + dz]
    return value + outside
