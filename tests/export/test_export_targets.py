"""SceneEval and USD export (issue 35): the scene-state JSON reads back with SceneEval's loader structure;
the USD stage opens in pxr with one rigid-body prim per object."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from physcene.cli import main
from physcene.export import sceneeval_state
from physcene.layout import read_layout

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "office_table.layout.json"


def _scene_eval_load(doc: dict) -> list[dict]:
    """The fields SceneEval's ``scenes/scene_state.py`` and ``scenes/obj.py`` read, with their checks
    (format, scene, version, arch, object) and its placement ``np.asarray(data).reshape(4, 4).T``."""
    assert doc.get("format") == "sceneState"
    spec = doc["scene"]
    assert spec["version"] == "scene@1.0.2"
    assert spec.get("up", [0, 0, 1]) == [0, 0, 1] and spec.get("unit", 1.0) == 1.0
    assert spec["arch"]["version"] == "arch@1.0.2"
    for element in spec["arch"]["elements"]:
        assert {"id", "roomId", "type", "points"} <= set(element)
    objs = []
    for k, o in enumerate(spec["object"]):
        t = o["transform"]
        assert (t.get("rows", 4), t.get("cols", 4)) == (4, 4)
        prefix, asset_id = o["modelId"].split(".")  # SceneEval's retriever: exactly one dot
        objs.append({"id": o["id"], "index": o["index"], "prefix": prefix, "asset": asset_id,
                     "parentId": o["parentId"], "parentIndex": o["parentIndex"],
                     "matrix": np.asarray(t["data"]).reshape(4, 4).T, "rotation": t["rotation"],
                     "translation": t["translation"], "scale": t["scale"]})
        assert objs[-1]["index"] == k
    return objs


def test_sceneeval_export_reads_back_with_scene_evals_structure(tmp_path, capsys):
    assert main(["export", str(EXAMPLE), "--format", "sceneeval", "-o", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "scene_state.json").read_text())
    scene = read_layout(EXAMPLE)
    objs = _scene_eval_load(doc)
    assert [o["id"] for o in objs] == scene.ids()
    assets = json.loads((tmp_path / "assets.json").read_text())
    assert assets["prefix"] == "physcene"
    by_id = scene.by_id()
    for o in objs:
        obj = by_id[o["id"]]
        assert o["prefix"] == "physcene" and o["asset"] in assets["assets"]
        np.testing.assert_allclose(o["matrix"][:3, 3], 0.01 * np.asarray(obj.center), atol=1e-9)
        np.testing.assert_allclose(o["translation"], 0.01 * np.asarray(obj.center), atol=1e-9)
        # the matrix's rotation is the yaw, and the quaternion (x, y, z, w) says the same
        c, s = np.cos(obj.yaw), np.sin(obj.yaw)
        np.testing.assert_allclose(o["matrix"][:2, :2], [[c, -s], [s, c]], atol=1e-9)
        q = o["rotation"]
        assert q[0] == q[1] == 0.0 and np.isclose(2 * np.arctan2(q[2], q[3]), obj.yaw)
        # SceneEval places the asset's mesh with that matrix: the mesh is the object at its size (m)
        mesh = trimesh.load(tmp_path / assets["assets"][o["asset"]]["file"], force="mesh")
        mesh.apply_transform(o["matrix"])
        lo, hi = mesh.bounds
        np.testing.assert_allclose(0.5 * (lo[2] + hi[2]), 0.01 * obj.center[2], atol=0.01)
        assert hi[2] - lo[2] == pytest.approx(0.01 * obj.size[2], rel=0.05)
    # the scene graph's supports become parents: the pen stands in its holder
    pen = next(o for o in objs if o["id"] == "5_pen_0")
    assert pen["parentId"] == "4_pen_holder_0" and objs[pen["parentIndex"]]["id"] == "4_pen_holder_0"
    laptop = next(o for o in objs if o["id"] == "1_laptop_0")
    assert laptop["parentId"] == "" and laptop["parentIndex"] == laptop["index"]


def test_sceneeval_state_is_json_of_plain_values():
    doc = sceneeval_state(read_layout(EXAMPLE))
    assert json.loads(json.dumps(doc)) == doc


def test_usd_export_opens_in_pxr_with_one_prim_per_object(tmp_path, capsys):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom, UsdPhysics

    pytest.importorskip("coacd")
    assert main(["export", str(EXAMPLE), "--format", "usd", "-o", str(tmp_path / "out")]) == 0
    stage = Usd.Stage.Open(str(tmp_path / "out" / "scene.usda"))
    assert stage is not None and UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    scene = read_layout(EXAMPLE)
    bodies = stage.GetPrimAtPath("/World/Objects").GetChildren()
    assert len(bodies) == len(scene.objects)
    ids = [b.GetCustomDataByKey("physcene:instance_id") for b in bodies]
    assert ids == scene.ids()
    cache = UsdGeom.XformCache()
    for prim, obj in zip(bodies, scene.objects):
        assert prim.HasAPI(UsdPhysics.RigidBodyAPI) and prim.HasAPI(UsdPhysics.MassAPI)
        assert UsdPhysics.MassAPI(prim).GetMassAttr().Get() > 0
        world = np.array(cache.GetLocalToWorldTransform(prim)).T  # pxr matrices are row-vector
        np.testing.assert_allclose(world[:3, 3], 0.01 * np.asarray(obj.center), atol=1e-6)
        colliders = [p for p in Usd.PrimRange(prim) if p.HasAPI(UsdPhysics.CollisionAPI)]
        assert colliders, obj.instance_id
        visual = UsdGeom.Mesh(stage.GetPrimAtPath(prim.GetPath().AppendChild("visual")))
        points = np.array(visual.GetPointsAttr().Get())
        np.testing.assert_allclose(points.max(0) - points.min(0), 0.01 * np.asarray(obj.size), rtol=0.05)
    table = stage.GetPrimAtPath("/World/table")
    assert table.HasAPI(UsdPhysics.CollisionAPI) and not table.HasAPI(UsdPhysics.RigidBodyAPI)
