"""Scene model validation: every error names the object and the field."""

import math

import numpy as np
import pytest

from physcene.scene import TABLE, Scene, SceneError, SceneObject, Zone, wrap_angle, zone_overshoot

ZONE = Zone(0.0, 100.0, 0.0, 60.0)


def _obj(iid="cup_0", **kw):
    args = dict(instance_id=iid, category="cup", center=(10.0, 10.0, 5.0), size=(8.0, 8.0, 10.0))
    args.update(kw)
    return SceneObject(**args)


@pytest.mark.parametrize("kw, field", [
    (dict(center=(1.0, float("nan"), 2.0)), "center"),
    (dict(center=(1.0, float("inf"), 2.0)), "center"),
    (dict(size=(1.0, 0.0, 2.0)), "size"),
    (dict(size=(1.0, -3.0, 2.0)), "size"),
    (dict(size=(1.0, 2.0)), "size"),
    (dict(yaw=float("nan")), "yaw"),
    (dict(category=""), "category"),
    (dict(relation="under"), "relation"),
    (dict(parent="cup_0"), "parent"),
    (dict(parent="plate_0", relation="near"), "relation"),
    (dict(parent="root_zone", relation="in"), "relation"),
])
def test_object_validation_names_object_and_field(kw, field):
    with pytest.raises(SceneError) as info:
        _obj(**kw)
    assert info.value.obj == "cup_0" and info.value.field == field
    assert "cup_0" in str(info.value) and field in str(info.value)


def test_scene_validation():
    with pytest.raises(SceneError, match="duplicate") as info:
        Scene(ZONE, (_obj(), _obj()))
    assert info.value.obj == "cup_0"
    with pytest.raises(SceneError, match="unknown parent") as info:
        Scene(ZONE, (_obj(parent="ghost"),))
    assert info.value.field == "parent"
    with pytest.raises(SceneError, match="cycle"):
        Scene(ZONE, (_obj("a", parent="b", relation="on"), _obj("b", parent="c", relation="on"),
                     _obj("c", parent="a", relation="on")))
    with pytest.raises(SceneError, match="zone"):
        Zone.from_list([5, 1, 0, 1])
    ok = Scene(ZONE, (_obj("a", parent=TABLE, relation="near"), _obj("b", parent="a", relation="on")))
    assert ok.has_hierarchy and [o.instance_id for o in ok.children("a")] == ["b"]


def test_geometry_and_poses():
    o = _obj(size=(4.0, 2.0, 10.0), yaw=math.pi / 2)
    box = o.aabb()
    np.testing.assert_allclose(box, [9, 11, 8, 12, 0, 10], atol=1e-12)
    scene = Scene(ZONE, (o, _obj("b")))
    poses = scene.poses()
    assert poses.shape == (2, 4) and scene.sizes().shape == (2, 3)
    moved = scene.with_poses(poses + np.array([1.0, 0, 0, 0]))
    assert moved.get("b").center[0] == 11.0
    with pytest.raises(SceneError, match="poses"):
        scene.with_poses(poses[:1])


def test_wrap_angle():
    for a in (-7.0, -math.pi, 0.0, 3.0, math.pi, 10.0):
        w = wrap_angle(a)
        assert -math.pi <= w < math.pi and math.isclose(math.cos(w), math.cos(a), abs_tol=1e-12)
        assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-12)


def test_source_in_error():
    err = SceneError("bad", obj="x", field="size").with_source("a.json")
    assert str(err) == "a.json, object 'x', field 'size': bad"


def test_zone_overshoot_is_how_far_the_yawed_footprint_corners_reach_past_the_zone():
    rng = np.random.default_rng(0)
    zone = Zone(0.0, 120.0, 0.0, 60.0)
    boxes = [SceneObject(f"{k}_box_0", "box", (*rng.uniform(-10, 130, 1), *rng.uniform(-10, 70, 1), 5.0),
                         tuple(rng.uniform(1, 40, 3)), yaw=float(rng.uniform(-math.pi, math.pi)))
             for k in range(200)]
    past = zone_overshoot(np.array([o.center[:2] for o in boxes]), np.array([o.size[:2] for o in boxes]),
                          np.array([o.yaw for o in boxes]), np.array([0.0, 120.0, 0.0, 60.0]))
    for o, p in zip(boxes, past):
        fp = o.footprint()
        expected = max(zone.xmin - fp[:, 0].min(), fp[:, 0].max() - zone.xmax,
                       zone.ymin - fp[:, 1].min(), fp[:, 1].max() - zone.ymax, 0.0)
        assert p == pytest.approx(expected, abs=1e-9)
    assert (past > 0).sum() > 20 and (past == 0).sum() > 20  # both kinds among the boxes
