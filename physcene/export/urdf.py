"""URDF (SAPIEN / ManiSkill): one URDF per object and the table, with a ``scene.json`` of poses."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from physcene.export.models import (
    CollisionShape,
    ExportConfig,
    ExportError,
    _fmt,
    _obj_bytes,
    build_models,
    category_color,
    table_box,
)
from physcene.files import write_atomic
from physcene.scene import Scene

__all__ = ["export_urdf"]


def _urdf_geometry(parent: ET.Element, shape: CollisionShape | None, mesh_file: str | None) -> None:
    geometry = ET.SubElement(parent, "geometry")
    if mesh_file is not None:
        ET.SubElement(geometry, "mesh", filename=mesh_file)
    elif shape.kind == "box":
        ET.SubElement(geometry, "box", size=_fmt(2 * np.asarray(shape.size)))
    elif shape.kind == "cylinder":
        ET.SubElement(geometry, "cylinder", radius=_fmt([shape.size[0]]), length=_fmt([2 * shape.size[1]]))
    elif shape.kind == "sphere":
        ET.SubElement(geometry, "sphere", radius=_fmt([shape.size[0]]))
    else:
        raise ExportError(f"URDF has no {shape.kind!r} shape; it must be written as a mesh")


def _urdf_robot(name: str, link: str, mass: float, com, inertia, visual_file: str | None,
                shapes: Sequence[tuple[CollisionShape | None, str | None]], rgba) -> str:
    robot = ET.Element("robot", name=name)
    body = ET.SubElement(robot, "link", name=link)
    inertial = ET.SubElement(body, "inertial")
    ET.SubElement(inertial, "origin", xyz=_fmt(com), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=_fmt([mass]))
    ET.SubElement(inertial, "inertia", ixx=_fmt([inertia[0, 0]]), ixy=_fmt([inertia[0, 1]]),
                  ixz=_fmt([inertia[0, 2]]), iyy=_fmt([inertia[1, 1]]), iyz=_fmt([inertia[1, 2]]),
                  izz=_fmt([inertia[2, 2]]))
    if visual_file is not None:
        visual = ET.SubElement(body, "visual")
        ET.SubElement(visual, "origin", xyz="0 0 0", rpy="0 0 0")
        _urdf_geometry(visual, None, visual_file)
        material = ET.SubElement(visual, "material", name=f"{name}_material")
        ET.SubElement(material, "color", rgba=_fmt(rgba))
    for k, (shape, mesh_file) in enumerate(shapes):
        collision = ET.SubElement(body, "collision", name=f"{link}_c{k}")
        ET.SubElement(collision, "origin", xyz="0 0 0", rpy="0 0 0")
        _urdf_geometry(collision, shape, mesh_file)
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def export_urdf(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write one URDF per object plus the table and ``out_dir/scene.json`` listing them with poses.

    Layout: ``objects/<name>/<name>.urdf`` with ``visual.obj`` and ``collision_<k>.obj`` beside it
    (mesh paths relative to the URDF), ``table/table.urdf``. ``scene.json`` (docs/export.md):
    ``{"format": "physcene-urdf-scene", "version": 1, "units": "m", "quaternion": "wxyz",
    "gravity": [0, 0, -9.81], "table": {"urdf", "pose", "fixed": true},
    "objects": [{"id", "category", "urdf", "pose": {"position": [x, y, z], "quaternion": [w, x, y, z]},
    "fixed": false, "mass_kg"}]}``. Each object's link origin is its box centre.
    """
    config = config or ExportConfig.load()
    out_dir = Path(out_dir)
    models = build_models(scene, library=library, config=config)
    centre, half = table_box(scene, config)
    table = CollisionShape("box", tuple(half), trimesh.creation.box(extents=2 * half))
    big = 1e3 * float(np.prod(2 * half))  # a fixed base; its mass only matters to loaders that check it
    table_inertia = np.diag(big / 3.0 * np.array([half[1] ** 2 + half[2] ** 2, half[0] ** 2 + half[2] ** 2,
                                                  half[0] ** 2 + half[1] ** 2]))
    write_atomic(out_dir / "table" / "table.urdf",
                  _urdf_robot("table", "table", big, np.zeros(3), table_inertia, None, [(table, None)],
                              [0.6, 0.45, 0.3, 1.0]).encode())
    entries = []
    for model in models:
        folder = out_dir / "objects" / model.name
        write_atomic(folder / "visual.obj", _obj_bytes(model.visual))
        shapes = []
        for k, shape in enumerate(model.collision):
            if shape.kind in ("box", "cylinder", "sphere"):
                shapes.append((shape, None))
            else:
                write_atomic(folder / f"collision_{k}.obj", _obj_bytes(shape.mesh))
                shapes.append((shape, f"collision_{k}.obj"))
        rgba = [c / 255 for c in category_color(model.category)]
        urdf = _urdf_robot(model.name, model.name, model.mass, model.center_of_mass, model.inertia,
                           "visual.obj", shapes, rgba)
        write_atomic(folder / f"{model.name}.urdf", urdf.encode())
        entries.append({"id": model.instance_id, "category": model.category,
                        "urdf": f"objects/{model.name}/{model.name}.urdf",
                        "pose": {"position": model.position.tolist(),
                                 "quaternion": model.quaternion.tolist()},
                        "fixed": False, "mass_kg": model.mass})
    doc = {"format": "physcene-urdf-scene", "version": 1, "units": "m", "quaternion": "wxyz",
           "gravity": [0.0, 0.0, -9.81],
           "table": {"urdf": "table/table.urdf",
                     "pose": {"position": centre.tolist(), "quaternion": [1.0, 0.0, 0.0, 0.0]},
                     "fixed": True},
           "objects": entries}
    path = out_dir / "scene.json"
    write_atomic(path, (json.dumps(doc, indent=2) + "\n").encode())
    return path
