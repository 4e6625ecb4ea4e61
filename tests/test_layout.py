"""MesaTask layout.json reader/writer."""

import json
import math

import pytest

from physcene.layout import (
    category_from_instance,
    iter_layout_tree,
    layout_to_dict,
    load_layout,
    quaternion_to_yaw,
    read_layout,
    write_layout,
    yaw_to_quaternion,
)
from physcene.scene import SceneError


def _layout(**over):
    data = {
        "item_placement_zone": [0.0, 100.0, 0.0, 50.0],
        "restricted_zone": [],
        "objects": [
            {"instance": "1_teapot_0", "position": [20.0, 20.0, 8.0], "size": [15.0, 12.0, 16.0],
             "rotation": [0.0, 0.0, 0.0, 1.0], "z_rotation": 0.0, "retrieved_uid": "abc123",
             "description": "A teapot."},
        ],
    }
    data.update(over)
    return data


@pytest.mark.parametrize("name, category", [
    ("1_teapot_0", "teapot"), ("teapot_0", "teapot"), ("teapot", "teapot"),
    ("10_lotion_bottle_1", "lotion_bottle"), ("box_0", "box"), ("box_small_lid_3", "box"),
    ("2_cylinder_tall_1", "cylinder"), ("sphere_7", "sphere"), ("cardboard_box_0", "cardboard_box"),
    ("boxing_glove_0", "boxing_glove"), ("12", "12"),
])
def test_category_from_instance(name, category):
    assert category_from_instance(name) == category


def test_reads_fields_and_asset_id():
    scene = load_layout(_layout(scene_type="kitchen counter", instruction="Make tea."))
    (o,) = scene.objects
    assert (o.instance_id, o.category, o.asset_id) == ("1_teapot_0", "teapot", "abc123")
    assert o.description == "A teapot."
    assert o.center == (20.0, 20.0, 8.0) and o.size == (15.0, 12.0, 16.0)
    assert scene.scene_type == "kitchen counter" and scene.instruction == "Make tea."
    assert scene.zone.to_list() == [0.0, 100.0, 0.0, 50.0]


def test_selected_uid_is_an_asset_id_fallback():
    data = _layout()
    data["objects"][0].pop("retrieved_uid")
    data["objects"][0]["selected_uid"] = "glb42"
    assert load_layout(data).objects[0].asset_id == "glb42"


def test_unknown_object_keys_survive_a_round_trip():
    data = _layout()
    data["objects"][0]["material"] = "ceramic"
    back = layout_to_dict(load_layout(data))
    assert back["objects"][0]["material"] == "ceramic"


def test_quaternion_is_authoritative_over_z_rotation():
    q = yaw_to_quaternion(0.7)
    data = _layout()
    data["objects"][0].update(rotation=q, z_rotation=-2.0)
    assert load_layout(data).objects[0].yaw == pytest.approx(0.7, abs=1e-12)
    # Without a quaternion z_rotation is used.
    del data["objects"][0]["rotation"]
    assert load_layout(data).objects[0].yaw == pytest.approx(-2.0)


def test_quaternion_yaw_with_tilt_and_scale():
    # A non-unit quaternion of a pure yaw: scale does not change the yaw.
    q = [3.0 * v for v in yaw_to_quaternion(-2.5)]
    assert quaternion_to_yaw(q) == pytest.approx(-2.5)
    assert quaternion_to_yaw([0, 0, 1, 0]) == pytest.approx(math.pi)


def test_tilt_is_reported_not_kept():
    data = _layout()
    half = math.sqrt(0.5)
    data["objects"][0]["rotation"] = [half, 0.0, 0.0, half]  # lying on its side (90 deg about x)
    scene = load_layout(data)
    assert scene.meta["tilted_objects"] == ["1_teapot_0"]
    assert scene.objects[0].yaw == pytest.approx(0.0)
    assert "tilted_objects" not in load_layout(_layout()).meta


def test_objects_as_dict_keyed_by_instance():
    data = _layout(objects={"3_cup_1": {"position": [5, 5, 5], "size": [8, 8, 10], "z_rotation": 0.3}})
    (o,) = load_layout(data).objects
    assert o.instance_id == "3_cup_1" and o.category == "cup" and o.yaw == pytest.approx(0.3)


@pytest.mark.parametrize("restricted, sink, n", [
    ([], None, 0), ([10, 20, 10, 20], None, 1), ([[10, 20, 10, 20], [30, 40, 0, 5]], [1, 2, 3, 4], 3),
    (None, [[0, 5, 0, 5]], 1), ({}, [], 0),
])
def test_restricted_and_sink_zones(restricted, sink, n):
    data = _layout(restricted_zone=restricted)
    if sink is not None:
        data["sink_zone"] = sink
    assert len(load_layout(data).restricted_zones) == n


@pytest.mark.parametrize("mutate, obj, field", [
    (lambda d: d["objects"][0].update(size=[1, 0, 2]), "1_teapot_0", "size"),
    (lambda d: d["objects"][0].update(size=[1, 2]), "1_teapot_0", "size"),
    (lambda d: d["objects"][0].update(position=[1, "x", 2]), "1_teapot_0", "position"),
    (lambda d: d["objects"][0].update(position=[1, float("nan"), 2]), "1_teapot_0", "position"),
    (lambda d: d["objects"][0].update(rotation=[0, 0, 0]), "1_teapot_0", "rotation"),
    (lambda d: d["objects"][0].update(description=["x"]), "1_teapot_0", "description"),
    (lambda d: d["objects"].append(dict(d["objects"][0])), "1_teapot_0", "instance_id"),
    (lambda d: d["objects"][0].update(parent="ghost_0"), "1_teapot_0", "parent"),
    (lambda d: d.update(item_placement_zone=[10, 0, 0, 5]), None, "item_placement_zone"),
    (lambda d: d.pop("item_placement_zone"), None, "item_placement_zone"),
    (lambda d: d.update(sink_zone=[[1, 2, 3]]), None, "sink_zone[0]"),
    (lambda d: d.update(objects="nope"), None, "objects"),
    (lambda d: d["objects"][0].pop("instance"), None, "objects[0].instance"),
])
def test_errors_name_file_object_field(mutate, obj, field):
    data = _layout()
    mutate(data)
    with pytest.raises(SceneError) as info:
        load_layout(data, source="scene_7/layout.json")
    err = info.value
    assert err.field == field and err.obj == obj and err.source == "scene_7/layout.json"
    assert "scene_7/layout.json" in str(err) and repr(field) in str(err)


def test_write_read_round_trip(tmp_path):
    data = _layout(scene_type="office table", sink_zone=[60, 70, 10, 20])
    data["objects"].append({"instance": "box_lid_0", "position": [60.5, 30.25, 1.0], "size": [3, 4, 2],
                            "rotation": yaw_to_quaternion(-1.2), "description": "lid"})
    scene = load_layout(data)
    path = write_layout(scene, tmp_path / "a" / "layout.json")
    back = read_layout(path)
    for a, b in zip(back.objects, scene.objects):
        assert a.moved(yaw=0.0) == b.moved(yaw=0.0)
        assert a.yaw == pytest.approx(b.yaw, abs=1e-12)
    assert back.zone == scene.zone and back.restricted_zones == scene.restricted_zones
    written = json.loads(path.read_text())
    entry = written["objects"][1]
    keys = {"instance", "position", "size", "rotation", "z_rotation", "retrieved_uid", "description"}
    assert set(entry) >= keys
    assert "category" not in entry  # implied by the instance name
    assert entry["z_rotation"] == pytest.approx(-1.2)
    again = layout_to_dict(back)
    assert [o["position"] for o in again["objects"]] == [o["position"] for o in written["objects"]]
    assert again["restricted_zone"] == written["restricted_zone"] == [[60.0, 70.0, 10.0, 20.0]]


def test_read_layout_bad_json_names_file(tmp_path):
    path = tmp_path / "layout.json"
    path.write_text('{"item_placement_zone": [0, 1, 0, 1], "objects": [')
    with pytest.raises(SceneError, match=r"layout\.json.*line 1"):
        read_layout(path)
    path.write_text('{"item_placement_zone": [0, 1, 0, NaN]}')
    with pytest.raises(SceneError, match="NaN"):
        read_layout(path)


def test_iter_layout_tree(tmp_path):
    for table, scene in [("office_table", "s1"), ("office_table", "s0"), ("dining_table", "x")]:
        d = tmp_path / "Layout_info" / table / scene
        d.mkdir(parents=True)
        (d / "layout.json").write_text(json.dumps(_layout()))
    found = list(iter_layout_tree(tmp_path))
    assert [p.parent.name for p, _ in found] == ["x", "s0", "s1"]
    assert [s.scene_type for _, s in found] == ["dining table", "office table", "office table"]
    (tmp_path / "Layout_info" / "dining_table" / "x" / "layout.json").write_text("{")
    with pytest.raises(SceneError):
        list(iter_layout_tree(tmp_path / "Layout_info"))
    assert len(list(iter_layout_tree(tmp_path, skip_errors=True))) == 2


def test_bundled_example():
    scene = read_layout("examples/office_table.layout.json")
    assert len(scene) == 9 and scene.get("2_book_0").yaw == pytest.approx(math.radians(15), abs=1e-6)
