"""Turn a mesh into an :class:`Asset`: normalise it, bake its SDF grid (Warp), sample its points.

Normalisation (the Asset contract): the mesh is moved so its bounding-box centre is the origin and
each axis is scaled by 2 / extent, so the mesh fills [-1, 1]^3 exactly; z stays up. The real
extents (cm) are kept on the asset. The sign method is picked per mesh: ray parity when the mesh is
watertight, the generalised winding number for open meshes (an open bowl, a mesh with a seam), an
unsigned thin shell for single-layer sheets (see :func:`sign_method_for`).
"""

from __future__ import annotations

import numpy as np
import trimesh

from physcene.assets.asset import Asset
from physcene.assets.cache import BakeCache
from physcene.assets.surface import surface_points

__all__ = ["BakeUnavailableError", "bake_mesh_asset", "normalise_mesh", "sign_method_for"]

_FLAT = 1e-6  # relative extent below which an axis cannot be stretched to fill [-1, 1]


class BakeUnavailableError(ModuleNotFoundError):
    """An asset that must be baked (it is not in the bake cache, or its open mesh must be classified)
    on a machine without Warp, which bakes. Synthesising a split, building the benchmark's scenes and
    scoring all read the assets' SDFs, so such a machine needs a cache baked where Warp runs."""


def _sdf_bake(asset_id: str, what: str):
    """:mod:`physcene.kernels.sdf_bake`, or a :class:`BakeUnavailableError` naming the asset and the fix."""
    try:
        from physcene.kernels import sdf_bake  # Warp loads only when something must be baked
    except ImportError as exc:
        raise BakeUnavailableError(
            f"asset {asset_id!r}: {what} needs Warp (pip install warp-lang), which this Python lacks "
            f"({exc}); bake the assets where Warp runs (physcene assets bake) and point PHYSCENE_CACHE "
            f"at a copy of that cache (it is keyed by content, so any machine's bake serves)", name="warp"
        ) from exc
    return sdf_bake


def normalise_mesh(mesh: trimesh.Trimesh, *, name: str = "mesh") -> tuple[trimesh.Trimesh, np.ndarray]:
    """(the mesh in the normalised frame, its real extents (3,) in the mesh's units)."""
    if len(mesh.faces) == 0:
        raise ValueError(f"{name}: mesh has no faces")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError(f"{name}: mesh has non-finite vertices")
    lo, hi = mesh.bounds
    extents = hi - lo
    if extents.min() <= _FLAT * max(extents.max(), 1e-12):
        raise ValueError(f"{name}: mesh is flat (extents {extents.tolist()}); it cannot fill [-1, 1]^3")
    out = mesh.copy()
    out.apply_translation(-(lo + hi) / 2)
    out.apply_scale(2.0 / extents)
    return out, extents


SHEET_AMBIGUITY = 0.05
"""Share of probe nodes with a fractional winding number above which an open mesh is a sheet."""


def sign_method_for(mesh: trimesh.Trimesh, *, device: str = "cpu", name: str = "mesh") -> str:
    """``"parity"`` for a watertight, consistently wound mesh; for an open one ``"winding"``,
    or ``"shell"`` when its winding number is fractional over whole regions (a single-layer sheet:
    the winding number would fill a one-layer bowl's cavity).
    """
    if mesh.is_watertight and mesh.is_winding_consistent:
        return "parity"
    ambiguity = _sdf_bake(name, "classifying its open mesh").winding_ambiguity(mesh.vertices, mesh.faces,
                                                                              device=device)
    return "shell" if ambiguity > SHEET_AMBIGUITY else "winding"


def bake_mesh_asset(
    mesh: trimesh.Trimesh,
    *,
    asset_id: str,
    category: str,
    source: str,
    description: str = "",
    unit_cm: float = 1.0,
    resolution: int = 64,
    n_points: int = 1024,
    seed: int = 0,
    device: str = "cpu",
    cache: BakeCache | None = None,
    edge_angle_deg: float = 30.0,
    points_scale=None,
) -> Asset:
    """Bake ``mesh`` (any placement, z up, units of ``unit_cm`` cm) into an asset.

    ``points_scale`` (3,): the half-extents that weigh the surface points' areas and edge lengths
    (default: this mesh's own); the library passes one shared by every procedural category of the
    same normalised shape (:func:`physcene.assets.library.procedural_points_scale`).

    A cache hit skips the Warp bake and the point sampling; the result is identical either way.
    """
    normalised, extents = normalise_mesh(mesh, name=asset_id)
    extents_cm = tuple(float(e) for e in extents * unit_cm)
    method = sign_method_for(normalised, device=device, name=asset_id)
    scale = np.asarray(extents / 2 if points_scale is None else points_scale, dtype=np.float64)
    key = BakeCache.key(
        normalised.vertices,
        normalised.faces,
        resolution=resolution,
        n_points=n_points,
        seed=seed,
        sign_method=method,
        points_scale=scale,
        edge_angle_deg=edge_angle_deg,
    )
    entry = cache.load(key, resolution, n_points) if cache is not None else None
    if entry is None:
        where = cache.root if cache is not None else "no bake cache"
        sdf = _sdf_bake(asset_id, f"baking its SDF (not in {where})").bake_sdf(
            normalised.vertices, normalised.faces, resolution, sign_method=method, device=device)
        points = surface_points(normalised, n_points, seed, scale=scale, edge_angle_deg=edge_angle_deg)
        if cache is not None:
            cache.store(key, sdf, points)
        entry = {"sdf": sdf, "points": points}
    return Asset(
        asset_id=asset_id,
        category=category,
        source=source,
        sdf=entry["sdf"],
        points=entry["points"],
        mesh=normalised,
        description=description,
        extents=extents_cm,
    )
