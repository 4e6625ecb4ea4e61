"""Simulator export (issue 9): MJCF compiles in MuJoCo, URDF parses with yourdfpy, the GLB reloads;
metres everywhere; masses from density; cavities stay hollow in the collision geometry."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

mujoco = pytest.importorskip("mujoco")
yourdfpy = pytest.importorskip("yourdfpy")
pytest.importorskip("coacd")

from physcene.assets import default_library  # noqa: E402
from physcene.cli import main  # noqa: E402
from physcene.export import (  # noqa: E402
    ExportConfig,
    ExportError,
    build_models,
    convex_parts,
    export,
    export_glb,
    export_mjcf,
    export_urdf,
    table_box,
)
from physcene.scene import Scene, SceneObject, Zone  # noqa: E402

ZONE = Zone(0.0, 80.0, 0.0, 50.0)
OBJECTS = (
    SceneObject("box_0", "box", (10.0, 10.0, 5.0), (20.0, 10.0, 10.0), yaw=0.5),
    SceneObject("cylinder_0", "cylinder", (40.0, 10.0, 6.0), (8.0, 8.0, 12.0)),
    SceneObject("cylinder_1", "cylinder", (55.0, 10.0, 3.0), (10.0, 6.0, 6.0)),
    SceneObject("sphere_0", "sphere", (70.0, 10.0, 3.0), (6.0, 6.0, 6.0)),
    SceneObject("sphere_1", "sphere", (70.0, 30.0, 2.0), (8.0, 6.0, 4.0)),
    SceneObject("bowl 0/odd", "bowl", (20.0, 35.0, 4.0), (18.0, 18.0, 8.0), yaw=1.0),
    SceneObject("cup_0", "cup", (45.0, 35.0, 3.5), (6.0, 6.0, 7.0)),
)
SCENE = Scene(ZONE, OBJECTS)


@pytest.fixture(scope="session")
def export_config(tmp_path_factory) -> ExportConfig:
    cache = tmp_path_factory.getbasetemp() / "physcene-coacd"
    return ExportConfig.load([f"decomposition.cache_dir={cache}"])


@pytest.fixture(scope="session")
def models(export_config):
    return build_models(SCENE, library=default_library(), config=export_config)


def test_models_are_in_metres_with_density_masses(models, export_config):
    by_id = {m.instance_id: m for m in models}
    box = by_id["box_0"]
    np.testing.assert_allclose(box.position, [0.10, 0.10, 0.05])
    np.testing.assert_allclose(box.visual.extents, [0.20, 0.10, 0.10], atol=1e-9)
    assert box.collision[0].kind == "box" and np.allclose(box.collision[0].size, [0.10, 0.05, 0.05])
    assert box.mass == pytest.approx(export_config.density("box") * 0.2 * 0.1 * 0.1, rel=1e-6)
    np.testing.assert_allclose(box.quaternion, [math.cos(0.25), 0, 0, math.sin(0.25)])
    assert [s.kind for s in by_id["cylinder_0"].collision] == ["cylinder"]
    assert [s.kind for s in by_id["cylinder_1"].collision] == ["mesh"]  # elliptic: a convex mesh
    assert [s.kind for s in by_id["sphere_0"].collision] == ["sphere"]
    assert [s.kind for s in by_id["sphere_1"].collision] == ["ellipsoid"]
    # The cup's mass is its wall material's, from the mesh volume, far below the full box's.
    cup = by_id["cup_0"]
    assert cup.mass == pytest.approx(export_config.density("cup") * cup.visual.volume, rel=1e-6)
    assert cup.mass < 0.5 * export_config.density("cup") * 0.06 * 0.06 * 0.07
    for m in models:
        assert np.all(np.linalg.eigvalsh(m.inertia) > 0), m.instance_id


def test_collision_parts_keep_the_cavity_hollow(models):
    """A point in the middle of the bowl's and cup's cavities lies in no collision part, while the
    convex hull of either object would contain it (a cup inside would be pushed out)."""
    by_id = {m.instance_id: m for m in models}
    for oid, height in (("bowl 0/odd", 0.08), ("cup_0", 0.07)):
        model = by_id[oid]
        assert len(model.collision) > 1
        cavity = np.array([[0.0, 0.0, 0.15 * height]])  # above the floor, below the rim
        assert model.visual.convex_hull.contains(cavity)[0]
        assert not any(s.mesh.contains(cavity)[0] for s in model.collision), oid
        # ... yet the parts cover the walls: every visual vertex is within 2 mm of a part.
        union = trimesh.util.concatenate([s.mesh for s in model.collision])
        _, dist, _ = trimesh.proximity.closest_point(union, model.visual.vertices[::7])
        inside = np.zeros(len(dist), bool)
        for s in model.collision:
            inside |= s.mesh.contains(model.visual.vertices[::7])
        assert np.all(inside | (dist < 0.002)), oid


def test_decomposition_is_cached_on_disk(export_config, monkeypatch):
    import coacd

    import physcene.export.decompose as export_module

    mesh = default_library().resolve("cup").asset.mesh
    first = convex_parts(mesh, export_config.decomposition)
    cache = list(Path(export_config.decomposition["cache_dir"]).glob("*"))
    assert cache and not any(p.name.endswith(".tmp") for p in cache)

    def forbidden(*args, **kwargs):
        raise AssertionError("CoACD ran although the parts were cached")

    monkeypatch.setattr(coacd, "run_coacd", forbidden)
    monkeypatch.setattr(export_module, "_run_coacd_isolated", forbidden)  # CoACD runs in a child
    again = convex_parts(mesh, export_config.decomposition)
    assert len(again) == len(first)
    for a, b in zip(first, again):
        np.testing.assert_allclose(a.vertices, b.vertices)
    # A convex mesh needs no decomposition at all.
    box = trimesh.creation.box(extents=(2, 2, 2))
    assert len(convex_parts(box, export_config.decomposition)) == 1


def test_mjcf_compiles_in_mujoco(tmp_path, export_config):
    path = export_mjcf(SCENE, tmp_path, library=default_library(), config=export_config)
    model = mujoco.MjModel.from_xml_path(str(path))
    assert model.nbody == 1 + len(OBJECTS)
    assert model.njnt == len(OBJECTS)
    assert {int(t) for t in model.jnt_type} == {int(mujoco.mjtJoint.mjJNT_FREE)}
    assert model.opt.timestep == pytest.approx(export_config.mujoco["timestep"])
    built = build_models(SCENE, library=default_library(), config=export_config)
    for k, m in enumerate(built, start=1):
        assert model.body_mass[k] == pytest.approx(m.mass, rel=1e-6)
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    assert model.geom_pos[table][2] + model.geom_size[table][2] == pytest.approx(0.0, abs=1e-12)
    # Visual geoms never collide; collision geoms do.
    visual = [g for g in range(model.ngeom) if model.geom_group[g] == 2]
    assert visual and all(model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0 for g in visual)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    np.testing.assert_allclose(data.xpos[1], [0.10, 0.10, 0.05], atol=1e-9)


def test_urdf_scene_loads_with_yourdfpy(tmp_path, export_config):
    path = export_urdf(SCENE, tmp_path, library=default_library(), config=export_config)
    doc = json.loads(path.read_text())
    assert doc["format"] == "physcene-urdf-scene" and doc["units"] == "m" and doc["quaternion"] == "wxyz"
    assert [o["id"] for o in doc["objects"]] == [o.instance_id for o in OBJECTS]
    table = yourdfpy.URDF.load(str(tmp_path / doc["table"]["urdf"]))
    assert doc["table"]["fixed"] and table.link_map["table"].collisions[0].geometry.box is not None
    for entry, obj in zip(doc["objects"], OBJECTS):
        urdf = yourdfpy.URDF.load(str(tmp_path / entry["urdf"]), load_meshes=True, load_collision_meshes=True)
        (link,) = urdf.robot.links
        assert link.inertial.mass == pytest.approx(entry["mass_kg"])
        assert link.collisions and link.visuals
        np.testing.assert_allclose(entry["pose"]["position"], 0.01 * np.asarray(obj.center))
        # The visual mesh loads, in metres, the size of the object.
        visual = urdf.scene.to_geometry()
        np.testing.assert_allclose(visual.extents, 0.01 * np.asarray(obj.size), rtol=0.02)
        meshes = [c.geometry.mesh for c in link.collisions if c.geometry.mesh is not None]
        for mesh in meshes:
            assert (tmp_path / entry["urdf"]).parent.joinpath(mesh.filename).is_file()


def test_glb_reloads_with_trimesh(tmp_path, export_config):
    path = export_glb(SCENE, tmp_path, library=default_library(), config=export_config)
    loaded = trimesh.load(path)
    assert isinstance(loaded, trimesh.Scene)
    nodes = set(loaded.graph.nodes_geometry)
    assert {"table", *(o.instance_id for o in OBJECTS)} <= nodes
    centre, half = table_box(SCENE, export_config)
    bounds = loaded.bounds
    assert bounds[1][2] == pytest.approx(max(o.zmax for o in OBJECTS) * 0.01, abs=1e-4)
    assert bounds[0][2] == pytest.approx(-2 * half[2], abs=1e-6)
    transform, geom = loaded.graph["box_0"]
    np.testing.assert_allclose(transform[:3, 3], [0.10, 0.10, 0.05], atol=1e-6)


def test_export_command_writes_every_format(tmp_path, capsys, export_config):
    layout = {"item_placement_zone": [0, 60, 0, 40],
              "objects": {"box_0": {"position": [20, 20, 5], "size": [20, 20, 10], "z_rotation": 0},
                          "cup_0": {"position": [45, 20, 3.5], "size": [6, 6, 7], "z_rotation": 1.0}}}
    src = tmp_path / "layout.json"
    src.write_text(json.dumps(layout))
    cache = f"decomposition.cache_dir={export_config.decomposition['cache_dir']}"
    assert main(["export", str(src), "--format", "all", "-o", str(tmp_path / "out"), cache]) == 0
    assert (tmp_path / "out/glb/scene.glb").is_file()
    assert (tmp_path / "out/mjcf/scene.xml").is_file() and (tmp_path / "out/urdf/scene.json").is_file()
    mujoco.MjModel.from_xml_path(str(tmp_path / "out/mjcf/scene.xml"))
    with pytest.raises(SystemExit):  # argparse rejects an unknown format
        main(["export", str(src), "--format", "stl", "-o", str(tmp_path / "x")])
    assert main(["export", str(tmp_path / "missing.json"), "--format", "glb", "-o", str(tmp_path / "x")]) == 2
    assert "missing.json" in capsys.readouterr().err


def test_bad_input_is_named():
    with pytest.raises(ExportError, match="format"):
        export(SCENE, "/nonexistent", "stl")
    with pytest.raises(ValueError, match="densit"):
        ExportConfig.load(["density_kg_m3.book=-1"])


def test_a_crashing_decomposition_does_not_kill_the_export(tmp_path, monkeypatch):
    """CoACD aborts the process on some meshes; the export survives and falls back to the hull."""
    import physcene.export.decompose as export_module

    # the child aborts, as CoACD's C++ std::logic_error does to its process
    monkeypatch.setattr(export_module, "_COACD_CHILD", "import os; os.abort()")
    mesh = default_library().resolve("bowl").asset.mesh
    settings = {**ExportConfig.load().decomposition, "cache_dir": str(tmp_path)}
    with pytest.warns(RuntimeWarning, match="CoACD failed"):
        parts = convex_parts(mesh, settings)
    assert len(parts) == 1 and parts[0].volume == pytest.approx(mesh.convex_hull.volume)
    assert not list(tmp_path.iterdir())  # a fallback is not cached


def test_export_command_takes_one_jsonl_record(tmp_path, capsys, export_config):
    records = [{"id": f"s{k}", "layout": {"item_placement_zone": [0, 50, 0, 50], "objects": {
        f"box_{k}": {"position": [10 + k, 10, 5], "size": [10, 10, 10], "z_rotation": 0}}}} for k in range(2)]
    jsonl = tmp_path / "data.jsonl"
    jsonl.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "out"
    assert main(["export", f"{jsonl}:2", "--format", "glb", "-o", str(out)]) == 0
    loaded = trimesh.load(out / "scene.glb")
    assert "box_1" in loaded.graph.nodes_geometry and "box_0" not in loaded.graph.nodes_geometry
    capsys.readouterr()
    assert main(["export", str(jsonl), "--format", "glb", "-o", str(out)]) == 2
    assert "holds 2 layouts" in capsys.readouterr().err
    assert main(["export", f"{jsonl}:9", "--format", "glb", "-o", str(out)]) == 2
