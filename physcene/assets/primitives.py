"""Exact primitives ``box``, ``cylinder``, ``sphere``: analytic SDF grids and surface points.

Each fills the normalised cube [-1, 1]^3: the box is the cube, the cylinder has radius 1 and
half-height 1 about z, the sphere has radius 1. Points are deterministic (no randomness): a
regular sampling of faces plus every corner and sharp edge, so penetration by a corner is seen.
"""

from __future__ import annotations

import numpy as np
import trimesh

from physcene.assets.asset import Asset, grid_coordinates

__all__ = ["PRIMITIVES", "box_sdf", "cylinder_sdf", "primitive_asset", "sphere_sdf"]

PRIMITIVES = ("box", "cylinder", "sphere")


def box_sdf(q: np.ndarray) -> np.ndarray:
    """Exact SDF of the cube [-1, 1]^3 at points q (..., 3)."""
    d = np.abs(q) - 1.0
    outside = np.linalg.norm(np.maximum(d, 0.0), axis=-1)
    inside = np.minimum(d.max(axis=-1), 0.0)
    return outside + inside


def cylinder_sdf(q: np.ndarray) -> np.ndarray:
    """Exact SDF of the cylinder r <= 1, |z| <= 1 at points q (..., 3)."""
    d = np.stack([np.linalg.norm(q[..., :2], axis=-1) - 1.0, np.abs(q[..., 2]) - 1.0], axis=-1)
    return np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)


def sphere_sdf(q: np.ndarray) -> np.ndarray:
    """Exact SDF of the unit sphere at points q (..., 3)."""
    return np.linalg.norm(q, axis=-1) - 1.0


_SDF = {"box": box_sdf, "cylinder": cylinder_sdf, "sphere": sphere_sdf}


def _box_points(n: int) -> np.ndarray:
    k = max(2, int(round(np.sqrt(n / 6.0))))
    t = np.linspace(-1.0, 1.0, k)
    u, v = np.meshgrid(t, t, indexing="ij")
    u, v = u.ravel(), v.ravel()
    faces = []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        for sign in (-1.0, 1.0):
            p = np.zeros((u.size, 3))
            p[:, axis], p[:, a], p[:, b] = sign, u, v
            faces.append(p)
    return np.unique(np.round(np.concatenate(faces), 9), axis=0)


def _cylinder_points(n: int) -> np.ndarray:
    m = max(8, int(round(np.sqrt(n * np.pi / 2))))  # around
    theta = np.linspace(0, 2 * np.pi, m, endpoint=False)
    rows = max(2, m // 3)
    z = np.linspace(-1.0, 1.0, rows)
    side = np.stack([np.repeat(np.cos(theta)[None], rows, 0), np.repeat(np.sin(theta)[None], rows, 0),
                     np.repeat(z[:, None], m, 1)], axis=-1).reshape(-1, 3)
    rings = max(2, rows // 2)
    caps = []
    for r in np.linspace(0.0, 1.0, rings)[1:-1]:
        mm = max(6, int(m * r))
        th = np.linspace(0, 2 * np.pi, mm, endpoint=False)
        for zc in (-1.0, 1.0):
            caps.append(np.stack([r * np.cos(th), r * np.sin(th), np.full(mm, zc)], axis=-1))
    caps.append(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    return np.concatenate([side, *caps])


def _sphere_points(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=-1)


_POINTS = {"box": _box_points, "cylinder": _cylinder_points, "sphere": _sphere_points}


def _exactly(structured: np.ndarray, n: int, mesh: trimesh.Trimesh) -> np.ndarray:
    """``n`` points: the regular sampling (corners and edges first) cut to n, or topped up with
    area-weighted samples of the surface (fixed seed, so the asset stays deterministic)."""
    if len(structured) >= n:
        return structured[np.linspace(0, len(structured) - 1, n).round().astype(int)]
    extra, _ = trimesh.sample.sample_surface(mesh, n - len(structured), seed=0)
    return np.concatenate([structured, extra])


def primitive_asset(kind: str, resolution: int = 64, n_points: int = 1024) -> Asset:
    """The exact primitive ``kind`` with an analytic SDF grid and deterministic surface points."""
    if kind not in _SDF:
        raise ValueError(f"unknown primitive {kind!r}; expected one of {PRIMITIVES}")
    g = grid_coordinates(resolution)
    q = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    mesh = {
        "box": lambda: trimesh.creation.box(extents=(2.0, 2.0, 2.0)),
        "cylinder": lambda: trimesh.creation.cylinder(radius=1.0, height=2.0, sections=64),
        "sphere": lambda: trimesh.creation.icosphere(subdivisions=4, radius=1.0),
    }[kind]()
    points = _exactly(_POINTS[kind](n_points), n_points, mesh)
    return Asset(asset_id=f"primitive:{kind}", category=kind, source="primitive",
                 sdf=_SDF[kind](q).astype(np.float32), points=points.astype(np.float32), mesh=mesh,
                 description=f"exact {kind} primitive")
