"""MJCF (MuJoCo): one free body per object with its visual mesh, collision geoms and inertial."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

from physcene.export.models import (
    ExportConfig,
    ObjectModel,
    _fmt,
    _obj_bytes,
    build_models,
    category_color,
    table_box,
)
from physcene.files import write_atomic
from physcene.scene import Scene

__all__ = ["export_mjcf", "mjcf_document"]


def mjcf_document(scene: Scene, *, library=None, config: ExportConfig | None = None,
                  models: Sequence[ObjectModel] | None = None) -> tuple[str, dict[str, bytes]]:
    """The MJCF text and its mesh files ({relative path: bytes}), ready for
    ``mujoco.MjModel.from_xml_string(xml, files)`` or for writing beside ``scene.xml``.

    One body with a free joint per object; visual meshes in geom group 2 (no contact), collision
    geoms in group 3; explicit inertials (mass from density × volume); the table a static box.
    """
    config = config or ExportConfig.load()
    if models is None:
        models = build_models(scene, library=library, config=config)
    mj = config.mujoco
    root = ET.Element("mujoco", model=str(scene.meta.get("id", "physcene_scene")))
    # Explicit inertials only: the convex parts overlap and cover a hollow shell, so their summed
    # volume is not the object's; mesh inertia "shell" keeps thin visual meshes from failing.
    ET.SubElement(root, "compiler", angle="radian", autolimits="true", inertiafromgeom="false")
    ET.SubElement(root, "option", timestep=_fmt([mj["timestep"]]), integrator=str(mj["integrator"]),
                  cone=str(mj["cone"]), impratio=_fmt([mj["impratio"]]), gravity="0 0 -9.81")
    default = ET.SubElement(root, "default")
    ET.SubElement(default, "geom", friction=_fmt(mj["friction"]), condim=str(int(mj["condim"])),
                  solref=_fmt(mj["solref"]), solimp=_fmt(mj["solimp"]), margin=_fmt([mj["margin"]]),
                  gap=_fmt([mj["gap"]]))
    visual_class = ET.SubElement(default, "default", {"class": "visual"})
    ET.SubElement(visual_class, "geom", contype="0", conaffinity="0", group="2")
    collision_class = ET.SubElement(default, "default", {"class": "collision"})
    ET.SubElement(collision_class, "geom", group="3", rgba="0.5 0.5 0.9 0.4")
    asset = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", pos="0 0 3", dir="0 0 -1", directional="true")
    centre, half = table_box(scene, config)
    ET.SubElement(world, "geom", name="table", type="box", pos=_fmt(centre), size=_fmt(half),
                  rgba="0.6 0.45 0.3 1")
    files: dict[str, bytes] = {}
    for model in models:
        vis = f"meshes/{model.name}_visual.obj"
        files[vis] = _obj_bytes(model.visual)
        ET.SubElement(asset, "mesh", name=f"{model.name}_visual", file=vis, inertia="shell")
        body = ET.SubElement(world, "body", name=model.name, pos=_fmt(model.position),
                             quat=_fmt(model.quaternion))
        ET.SubElement(body, "freejoint", name=model.name)
        i = model.inertia
        ET.SubElement(body, "inertial", pos=_fmt(model.center_of_mass), mass=_fmt([model.mass]),
                      fullinertia=_fmt([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]))
        r, g, b, _ = category_color(model.category)
        ET.SubElement(body, "geom", {"class": "visual", "type": "mesh", "mesh": f"{model.name}_visual",
                                     "rgba": _fmt([r / 255, g / 255, b / 255, 1.0])})
        for k, shape in enumerate(model.collision):
            attrs = {"class": "collision", "name": f"{model.name}_c{k}"}
            if shape.kind == "mesh":
                part = f"meshes/{model.name}_c{k}.obj"
                files[part] = _obj_bytes(shape.mesh)
                ET.SubElement(asset, "mesh", name=f"{model.name}_c{k}", file=part, inertia="shell")
                attrs.update(type="mesh", mesh=f"{model.name}_c{k}")
            else:
                attrs.update(type=shape.kind, size=_fmt(shape.size))
            ET.SubElement(body, "geom", attrs)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode"), files


def export_mjcf(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write ``out_dir/scene.xml`` and its ``meshes/*.obj``; returns the XML's path."""
    xml, files = mjcf_document(scene, library=library, config=config)
    out_dir = Path(out_dir)
    for rel, data in files.items():
        write_atomic(out_dir / rel, data)
    path = out_dir / "scene.xml"
    write_atomic(path, xml.encode())
    return path
