"""SceneEval's scene state (``"format": "sceneState"``, ``scene@1.0.2``): the input its metrics read.

SceneEval (3dlg-hcvc/SceneEval) loads a scene state with ``scenes/scene_state.py``: ``scene`` holds
``version``, ``id``, ``up``, ``front``, ``unit`` (metres per unit), ``assetSource``, ``arch``
(``version``, ``elements``: walls and floors as point lists) and ``object``, a list of ``{"id",
"index", "modelId", "parentId", "parentIndex", "transform": {"rows", "cols", "data", "rotation",
"translation", "scale"}}``. ``transform.data`` is the 4 x 4 placement in column-major order (its
loaders read ``np.asarray(data).reshape(4, 4).T``), ``rotation`` a quaternion x, y, z, w.
``modelId`` is ``<prefix>.<asset id>``; SceneEval's asset retriever splits it at the dot and asks
the dataset registered under that prefix (``configs/assets.yaml``) for the mesh file.

The physcene objects are written as meshes of their own, already scaled to the object's size, in
``assets/<name>.glb`` (metres, body frame), with ``modelId = "physcene.<name>"``; ``assets.json``
lists each asset's file and description for a SceneEval dataset class registered under the prefix
``physcene`` (docs/export.md shows one). The table top is the floor (one ``Floor`` element, the
table box's outline at z = 0); a tabletop has no walls.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from physcene.export.models import ExportConfig, table_box, visual_meshes
from physcene.files import write_atomic
from physcene.graph import ensure_hierarchy
from physcene.scene import Scene

__all__ = ["ASSET_PREFIX", "SCENE_VERSION", "export_sceneeval", "sceneeval_state"]

SCENE_VERSION = "scene@1.0.2"
ARCH_VERSION = "arch@1.0.2"
ASSET_PREFIX = "physcene"


def _transform(position_m: np.ndarray, yaw: float) -> dict:
    c, s = float(np.cos(yaw)), float(np.sin(yaw))
    matrix = np.array([[c, -s, 0.0, position_m[0]], [s, c, 0.0, position_m[1]],
                       [0.0, 0.0, 1.0, position_m[2]], [0.0, 0.0, 0.0, 1.0]])
    half = 0.5 * yaw
    return {"rows": 4, "cols": 4, "data": [float(v) for v in matrix.T.ravel()],
            "rotation": [0.0, 0.0, float(np.sin(half)), float(np.cos(half))],
            "translation": [float(v) for v in position_m], "scale": [1.0, 1.0, 1.0]}


def sceneeval_state(scene: Scene, *, library=None, config: ExportConfig | None = None,
                    names: list[str] | None = None) -> dict:
    """The scene-state document; ``names`` are the asset names (default: the export's safe names)."""
    config = config or ExportConfig.load()
    scene = ensure_hierarchy(scene)  # parentId: what each object rests on or in (physcene.graph)
    entries = visual_meshes(scene, library=library)
    names = names or [name for _, name, _, _ in entries]
    index = {obj.instance_id: k for k, (obj, _, _, _) in enumerate(entries)}
    centre, half = table_box(scene, config)
    lo, hi = centre[:2] - half[:2], centre[:2] + half[:2]
    floor = {"id": "table|floor", "roomId": "table", "type": "Floor",
             "points": [[float(lo[0]), float(lo[1]), 0.0], [float(hi[0]), float(lo[1]), 0.0],
                        [float(hi[0]), float(hi[1]), 0.0], [float(lo[0]), float(hi[1]), 0.0]]}
    objects = []
    for k, ((obj, _, _, _), name) in enumerate(zip(entries, names)):
        parent = obj.parent if obj.parent in index else None
        objects.append({
            "id": obj.instance_id, "index": k, "modelId": f"{ASSET_PREFIX}.{name}",
            # SceneEval's own converters write "" and the object's index for a root object.
            "parentId": parent or "", "parentIndex": index[parent] if parent else k,
            "transform": _transform(0.01 * np.asarray(obj.center, dtype=np.float64), obj.yaw)})
    return {"format": "sceneState",
            "scene": {"version": SCENE_VERSION, "id": str(scene.meta.get("id", "physcene_scene")),
                      "up": [0, 0, 1], "front": [0, 1, 0], "unit": 1.0, "assetSource": [ASSET_PREFIX],
                      "arch": {"version": ARCH_VERSION, "elements": [floor]},
                      "object": objects, "modifications": []},
            "selected": []}


def export_sceneeval(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write ``out_dir/scene_state.json``, ``assets/<name>.glb`` and ``assets.json``; returns the state."""
    out_dir = Path(out_dir)
    entries = visual_meshes(scene, library=library)
    assets = {}
    for obj, name, asset, mesh in entries:
        # Asset names are file-safe (physcene.export.models._safe_names) and hold no dot, which
        # SceneEval's retriever would split on.
        safe = name.replace(".", "_")
        while safe in assets:
            safe += "_"
        data = trimesh.Scene(geometry={safe: mesh}).export(file_type="glb")
        write_atomic(out_dir / "assets" / f"{safe}.glb", data)
        assets[safe] = {"file": f"assets/{safe}.glb", "category": obj.category, "source": asset.asset_id,
                        "description": obj.description or obj.category.replace("_", " ")}
    state = sceneeval_state(scene, library=library, config=config, names=list(assets))
    write_atomic(out_dir / "assets.json", (json.dumps({"prefix": ASSET_PREFIX, "units": "m",
                                                         "assets": assets}, indent=2) + "\n").encode())
    path = out_dir / "scene_state.json"
    write_atomic(path, (json.dumps(state, indent=2) + "\n").encode())
    return path
