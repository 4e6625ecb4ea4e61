"""Simulator-ready export of a scene: GLB (whole scene), MJCF (MuJoCo), URDF (SAPIEN/ManiSkill),
SceneEval's scene state and USD (Isaac Sim / IsaacLab).

Every export is in **metres** (the scene is in cm) with the scene's own frame: origin at the
placement zone's near-left corner, +z up, the table top at z = 0. The table is a static box
under it (SceneEval's floor). Each object is one rigid body posed at its box centre with its
yaw; its geometry is the asset's mesh scaled from the normalised cube [-1, 1]^3 to ``size`` / 2.

Collision geometry keeps cavities hollow: exact primitives become native shapes (box, cylinder,
sphere/ellipsoid); any other mesh is split into convex parts by CoACD (approximate convex
decomposition) once per asset, in the normalised frame. A scaling is linear, so the scaled parts
of a convex decomposition are a convex decomposition of the scaled mesh: one cache entry serves
every size. Entries live on disk keyed by a hash of the mesh and the CoACD settings.

Masses are density × volume: the mesh's own volume when it is a closed volume, else the box's.
Inertia comes from the same solid. Densities per category are in ``configs/export.yaml``.

One module per target: :mod:`~physcene.export.models` (config, one rigid body per object, the
table), :mod:`~physcene.export.decompose` (CoACD), :mod:`~physcene.export.glb`,
:mod:`~physcene.export.mjcf`, :mod:`~physcene.export.urdf`, :mod:`~physcene.export.sceneeval`,
:mod:`~physcene.export.usd` (needs ``pxr``: the ``[usd]`` extra).
"""

from __future__ import annotations

from pathlib import Path

from physcene.export.decompose import convex_parts
from physcene.export.glb import export_glb, glb_scene
from physcene.export.mjcf import export_mjcf, mjcf_document
from physcene.export.models import (
    CM,
    CollisionShape,
    ExportConfig,
    ExportError,
    ObjectModel,
    build_models,
    table_box,
    visual_meshes,
)
from physcene.export.sceneeval import export_sceneeval, sceneeval_state
from physcene.export.urdf import export_urdf
from physcene.export.usd import export_usd
from physcene.scene import Scene

__all__ = [
    "CM", "FORMATS", "SIMULATOR_FORMATS", "CollisionShape", "ExportConfig", "ExportError", "ObjectModel",
    "build_models", "convex_parts", "export", "export_glb", "export_mjcf", "export_sceneeval", "export_urdf",
    "export_usd", "glb_scene", "mjcf_document", "sceneeval_state", "table_box", "visual_meshes",
]

# ``--format all`` writes the first three: the simulator formats every install can write (usd needs
# the [usd] extra, sceneeval is a benchmark's input rather than a simulator's).
FORMATS = ("glb", "mjcf", "urdf", "sceneeval", "usd")
SIMULATOR_FORMATS = FORMATS[:3]


def export(scene: Scene, out_dir, fmt: str, *, library=None, config: ExportConfig | None = None) -> Path:
    """Export in one of :data:`FORMATS`; returns the main file written."""
    writers = {"glb": export_glb, "mjcf": export_mjcf, "urdf": export_urdf, "sceneeval": export_sceneeval,
               "usd": export_usd}
    if fmt not in writers:
        raise ExportError(f"unknown export format {fmt!r}; expected one of {FORMATS}")
    return writers[fmt](scene, out_dir, library=library, config=config)
