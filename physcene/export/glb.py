"""GLB: the whole scene as one glTF binary (metres, +z up), one node per object plus the table."""

from __future__ import annotations

from pathlib import Path

import trimesh

from physcene.export.models import (
    ExportConfig,
    _pose_matrix,
    build_models,
    category_color,
    table_box,
)
from physcene.files import write_atomic
from physcene.scene import Scene

__all__ = ["export_glb", "glb_scene"]


def glb_scene(scene: Scene, *, library=None, config: ExportConfig | None = None) -> trimesh.Scene:
    """The whole scene as a ``trimesh.Scene`` in metres: one node per object plus ``table``."""
    config = config or ExportConfig.load()
    centre, half = table_box(scene, config)
    out = trimesh.Scene()
    table = trimesh.creation.box(extents=2 * half)
    table.visual.face_colors = [150, 110, 70, 255]
    out.add_geometry(table, node_name="table", geom_name="table",
                     transform=trimesh.transformations.translation_matrix(centre))
    for model in build_models(scene, library=library, config=config):
        mesh = model.visual.copy()
        mesh.visual.face_colors = category_color(model.category)
        mesh.metadata["category"] = model.category
        out.add_geometry(mesh, node_name=model.instance_id, geom_name=model.name,
                         transform=_pose_matrix(model))
    return out


def export_glb(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write ``out_dir/scene.glb`` (metres, +z up as in the scene; glTF viewers may show y up)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = glb_scene(scene, library=library, config=config).export(file_type="glb")
    path = out_dir / "scene.glb"
    write_atomic(path, data)
    return path

