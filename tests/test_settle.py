"""The MuJoCo settle test (issue 9): resting stacks are stable; sunk or hovering objects are not."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mujoco")
pytest.importorskip("coacd")

from physcene.assets import default_library  # noqa: E402
from physcene.cli import main  # noqa: E402
from physcene.export import ExportConfig, build_models  # noqa: E402
from physcene.scene import Scene, SceneObject, Zone  # noqa: E402
from physcene.settle import (  # noqa: E402
    SettleConfig,
    object_stability_rate,
    settle,
    stability_rate,
)

ZONE = Zone(0.0, 60.0, 0.0, 60.0)
BOWL = SceneObject("bowl_0", "bowl", (30.0, 30.0, 4.0), (18.0, 18.0, 8.0), yaw=0.4)
CUP_SIZE = (6.0, 6.0, 7.0)


@pytest.fixture(scope="session")
def export_config(tmp_path_factory) -> ExportConfig:
    """The shipped settings, with CoACD parts cached once per test run (shared with test_export)."""
    cache = tmp_path_factory.getbasetemp() / "physcene-coacd"
    return ExportConfig.load([f"decomposition.cache_dir={cache}"])


def box_stack(dz_cm: float) -> Scene:
    """A box resting on a box (dz = 0); dz < 0 sinks the top box into the lower, dz > 0 lifts it."""
    lower = SceneObject("box_0", "box", (30.0, 30.0, 5.0), (20.0, 20.0, 10.0))
    upper = SceneObject("box_1", "box", (32.0, 29.0, 10.0 + 4.0 + dz_cm), (10.0, 10.0, 8.0), yaw=0.3)
    return Scene(ZONE, (lower, upper))


def bowl_floor_cm(config: ExportConfig, radius_cm: float) -> float:
    """Height (cm) of the bowl's inner floor under a disc of ``radius_cm``: the highest surface point
    hit by rays cast down inside the disc, from the real (visual) mesh."""
    model = build_models(Scene(ZONE, (BOWL,)), library=default_library(), config=config)[0]
    angles = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    r = 0.01 * radius_cm
    xy = np.concatenate([[[0.0, 0.0]], np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)])
    origins = np.c_[xy, np.full(len(xy), 0.5)]
    hits, rays, _ = model.visual.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)),
                                                          multiple_hits=False)
    assert len(set(rays.tolist())) == len(xy), "every ray must hit the bowl's floor"
    return 100.0 * (hits[:, 2].max() + BOWL.center[2] * 0.01)


def cup_in_bowl(config: ExportConfig, dz_cm: float) -> Scene:
    """A cup standing on the bowl's inner floor (dz = 0), sunk (dz < 0) or hovering (dz > 0)."""
    bottom_radius = 0.5 * CUP_SIZE[0]  # the procedural cup tapers, so this bounds its foot
    floor = bowl_floor_cm(config, bottom_radius)
    cup = SceneObject("cup_0", "cup", (30.0, 30.0, floor + 0.5 * CUP_SIZE[2] + dz_cm), CUP_SIZE)
    return Scene(ZONE, (BOWL, cup))


def test_touching_box_stack_is_stable(export_config):
    result = settle(box_stack(0.0), library=default_library(), export_config=export_config)
    assert result.stable, result.to_dict()
    assert all(o.moved_cm < 0.1 and o.turned_rad < 0.01 for o in result.objects)


@pytest.mark.parametrize("dz_cm", [-2.0, 3.0], ids=["interpenetrating_2cm", "hovering_3cm"])
def test_sunk_or_hovering_box_is_unstable(export_config, dz_cm):
    result = settle(box_stack(dz_cm), library=default_library(), export_config=export_config)
    assert not result.stable
    top = result.objects[1]
    assert not top.stable and top.moved_cm > 1.0
    # The contact solver lifts the sunk box back onto its support; the hovering one falls onto it.
    assert abs(top.moved_cm - abs(dz_cm)) < 0.5, top
    assert result.objects[0].stable


def test_cup_in_bowl_is_stable(export_config):
    result = settle(cup_in_bowl(export_config, 0.0), library=default_library(), export_config=export_config)
    assert result.stable, result.to_dict()


@pytest.mark.parametrize("dz_cm", [-2.0, 3.0], ids=["interpenetrating_2cm", "hovering_3cm"])
def test_sunk_or_hovering_cup_in_bowl_is_unstable(export_config, dz_cm):
    result = settle(cup_in_bowl(export_config, dz_cm), library=default_library(), export_config=export_config)
    assert not result.stable
    cup = result.objects[1]
    assert not cup.stable and cup.moved_cm > 1.0


def test_rates_and_json_records(export_config):
    results = [settle(box_stack(dz), library=default_library(), export_config=export_config)
               for dz in (0.0, 3.0)]
    assert stability_rate(results) == 0.5
    assert object_stability_rate(results) == 0.75
    records = [r.to_dict() for r in results]
    assert stability_rate(records) == 0.5 and object_stability_rate(records) == 0.75
    assert set(records[0]) == {"path", "stable", "objects"}
    assert set(records[0]["objects"][0]) == {"id", "moved_cm", "turned_rad", "stable"}
    assert np.isnan(stability_rate([]))


def test_thresholds_come_from_config(export_config):
    loose = SettleConfig.load(["settle.max_moved_cm=5.0", "settle.max_turned_rad=1.0"])
    assert settle(box_stack(3.0), library=default_library(), config=loose, export_config=export_config).stable


def _mesatask(scene: Scene) -> dict:
    return {"item_placement_zone": scene.zone.to_list(),
            "objects": {o.instance_id: {"position": list(o.center), "size": list(o.size),
                                        "z_rotation": o.yaw} for o in scene.objects}}


def test_settle_command_json(tmp_path, capsys, export_config):
    folder = tmp_path / "tree" / "a"
    folder.mkdir(parents=True)
    (folder / "layout.json").write_text(json.dumps(_mesatask(box_stack(0.0))))
    records = [{"id": f"s{k}", "layout": _mesatask(box_stack(dz))} for k, dz in enumerate((0.0, -2.0))]
    jsonl = tmp_path / "data.jsonl"
    jsonl.write_text("".join(json.dumps(r) + "\n" for r in records))
    cache = f"decomposition.cache_dir={export_config.decomposition['cache_dir']}"
    assert main(["settle", str(tmp_path / "tree"), str(jsonl), "--json", cache]) == 0
    doc = json.loads(capsys.readouterr().out)
    paths = [s["path"] for s in doc["scenes"]]
    assert paths == [str(folder / "layout.json"), f"{jsonl}:1", f"{jsonl}:2"]
    assert [s["stable"] for s in doc["scenes"]] == [True, True, False]
    assert doc["stability_rate"] == pytest.approx(2 / 3)
    assert [o["id"] for o in doc["scenes"][2]["objects"]] == ["box_0", "box_1"]


def test_settle_command_names_unreadable_input(tmp_path, capsys):
    bad = tmp_path / "layout.json"
    bad.write_text('{"item_placement_zone": [0, 1, 0, 1], "objects": {"box_0": {"size": [1, -1, 1]}}}')
    assert main(["settle", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "box_0" in err
    assert main(["settle", str(tmp_path / "missing.json")]) == 2
