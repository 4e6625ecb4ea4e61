"""Hierarchical scene graph: relations, thresholds, forest guarantee, Algorithm-1 order."""

import math

import pytest

from physcene.config import ConfigError
from physcene.graph import (
    GraphConfig,
    anchor_order,
    build_hierarchy,
    can_contain,
    container_role,
    footprint_overlap,
    near_direction,
    near_references,
)
from physcene.scene import TABLE, Scene, SceneObject, Zone

ZONE = Zone(0.0, 100.0, 0.0, 60.0)


def box(iid, x, y, z0, w, d, h, yaw=0.0):
    """An object named iid standing with its bottom at z0 (cm)."""
    return SceneObject(instance_id=iid, category=iid.rsplit("_", 1)[0], center=(x, y, z0 + 0.5 * h),
                       size=(w, d, h), yaw=yaw)


def relations(*objects, config=None):
    scene = build_hierarchy(Scene(ZONE, objects), config)
    return {o.instance_id: (o.parent, o.relation) for o in scene.objects}


def test_pen_in_holder():
    rel = relations(box("pen_holder_0", 20, 20, 0, 8, 8, 10), box("pen_0", 20, 20, 0.5, 1, 1, 14))
    assert rel["pen_0"] == ("pen_holder_0", "in")
    assert rel["pen_holder_0"] == (TABLE, "near")


def test_book_on_book_on_table():
    rel = relations(box("book_0", 50, 30, 0, 22, 16, 4, yaw=0.3),
                    box("book_1", 50, 30, 4, 20, 14, 2, yaw=0.5),
                    box("book_2", 50.5, 30.5, 6.2, 18, 12, 3, yaw=-0.2))
    assert rel == {"book_0": (TABLE, "near"), "book_1": ("book_0", "on"), "book_2": ("book_1", "on")}


def test_cup_on_saucer():
    rel = relations(box("saucer_0", 70, 15, 0, 14, 14, 1), box("cup_0", 70, 15, 1, 11, 8, 9))
    assert rel["cup_0"] == ("saucer_0", "on")
    assert rel["saucer_0"] == (TABLE, "near")  # not "in" the cup: it is below the cup's z-range


def test_side_by_side_near_with_direction():
    a, b = box("mug_0", 30, 30, 0, 8, 8, 10), box("plate_0", 50, 32, 0, 20, 20, 2)
    rel = relations(a, b)
    assert rel == {"mug_0": (TABLE, "near"), "plate_0": (TABLE, "near")}
    assert near_direction(a, b) == "left of" and near_direction(b, a) == "right of"
    c, d = box("lamp_0", 50, 50, 0, 10, 10, 30), box("pen_0", 52, 10, 0, 1, 14, 1)
    assert near_direction(c, d) == "behind" and near_direction(d, c) == "in front of"


def test_resting_on_two_supports_highest_wins():
    low, high = box("box_0", 40, 30, 0, 20, 20, 10), box("book_0", 60, 30, 0, 20, 20, 10.6)
    tray = box("tray_0", 50, 30, 10.6, 30, 16, 2)
    assert relations(low, high, tray)["tray_0"] == ("book_0", "on")
    # Equal heights: the larger overlap wins.
    high2 = box("book_0", 62, 30, 0, 20, 20, 10)
    assert relations(low, high2, box("tray_0", 48, 30, 10, 30, 16, 2))["tray_0"] == ("box_0", "on")


def test_innermost_container_wins_and_in_beats_on():
    bin_ = box("basket_0", 50, 30, 0, 30, 30, 20)
    cup = box("cup_0", 50, 30, 0.5, 10, 10, 12)
    pen = box("pen_0", 50, 30, 1.0, 1, 1, 14)
    rel = relations(bin_, cup, pen)
    assert rel["cup_0"] == ("basket_0", "in") and rel["pen_0"] == ("cup_0", "in")


def test_yaw_aware_footprint():
    # A 45-degree container: the content's box lies inside its AABB but mostly outside its footprint.
    holder = box("tray_0", 50, 30, 0, 20, 4, 10, yaw=math.pi / 4)
    content = box("eraser_0", 54, 26, 1, 3, 3, 4)
    assert footprint_overlap(content, holder) < 0.5
    assert relations(holder, content)["eraser_0"] == (TABLE, "near")
    inside = box("eraser_0", 50, 30, 1, 2, 2, 4, yaw=0.3)
    assert relations(holder, inside)["eraser_0"] == ("tray_0", "in")


def test_thresholds_from_config():
    with pytest.raises(ConfigError, match="on_gap"):
        GraphConfig.load(["on_gap=0.1"])  # a typo is an error, not silently ignored
    with pytest.raises(ConfigError, match="on_gap_cm='wide': expected a number"):
        GraphConfig.load(["on_gap_cm=wide"])
    cfg = GraphConfig.load(["on_gap_cm=0.1"])
    assert cfg.on_gap_cm == 0.1 and cfg.in_volume_ratio == 1.5
    base, top = box("book_0", 50, 30, 0, 20, 20, 4), box("book_1", 50, 30, 4.5, 20, 20, 2)
    assert relations(base, top)["book_1"] == ("book_0", "on")
    assert relations(base, top, config=cfg)["book_1"] == (TABLE, "near")


def test_thin_stacked_cards_point_one_way():
    # Both thinner than on_gap_cm: only the upper one rests on the lower (a support starts below).
    rel = relations(box("card_0", 50, 30, 0, 9, 6, 0.2), box("card_1", 50, 30, 0.2, 9, 6, 0.2),
                    box("card_2", 50, 30, 0.4, 9, 6, 0.2))
    assert rel == {"card_0": (TABLE, "near"), "card_1": ("card_0", "on"), "card_2": ("card_1", "on")}


@pytest.mark.parametrize("h", [0.2, 0.5, 2.0])
def test_degenerate_equal_boxes_form_a_forest(h):
    objs = [box(f"card_{k}", 50, 30, 0, 10, 10, h) for k in range(4)]
    objs += [box(f"chip_{k}", 50, 30, 0.0, 2, 2, h) for k in range(3)]
    scene = build_hierarchy(Scene(ZONE, objs))  # Scene() re-validates: raises on a cycle
    assert scene.has_hierarchy
    assert any(o.parent == TABLE for o in scene.objects)


def test_anchor_order_algorithm_1():
    objs = [
        box("laptop_0", 52, 30, 0, 30, 20, 2),      # closest to the zone centre (50, 30): anchor
        box("pen_holder_0", 10, 50, 0, 8, 8, 10),
        box("pen_0", 10, 50, 0.5, 1, 1, 14),
        box("pencil_0", 11, 51, 0.2, 1, 1, 14),
        box("mouse_0", 80, 30, 0, 6, 10, 4),
        box("saucer_0", 90, 10, 0, 14, 14, 1),
        box("mug_0", 90, 10, 1, 10, 8, 9),
    ]
    scene = Scene(ZONE, objs)
    order = anchor_order(scene)
    assert order == ["laptop_0", "mouse_0", "saucer_0", "mug_0", "pen_holder_0", "pencil_0", "pen_0"]
    refs = near_references(scene)
    assert refs["laptop_0"] is None
    assert refs["mouse_0"] == ("laptop_0", "right of")
    assert refs["saucer_0"] == ("mouse_0", "in front of")  # dy = -20 dominates dx = 10
    assert refs["pen_holder_0"] == ("laptop_0", "left of")
    assert set(refs) == {"laptop_0", "mouse_0", "saucer_0", "pen_holder_0"}


def test_anchor_order_keeps_given_hierarchy_and_deep_stacks():
    objs = [box(f"book_{k}", 50, 30, 2.0 * k, 20, 14, 2) for k in range(120)]
    scene = build_hierarchy(Scene(ZONE, objs))
    assert [o.parent for o in scene.objects[1:4]] == ["book_0", "book_1", "book_2"]
    assert anchor_order(scene) == [f"book_{k}" for k in range(120)]


def test_in_requires_a_container_category():
    # A knife sunk 0.6 cm into a cutting board (60 % of its height inside the board's z-range)
    # passes the geometric in test; a cutting board is a support, so it is on, not in.
    board, knife = box("cutting_board_0", 50, 30, 0, 35, 25, 2), box("knife_0", 50, 30, 1.4, 22, 2, 1)
    assert relations(board, knife)["knife_0"] == ("cutting_board_0", "on")
    geometric = GraphConfig(in_requires_container=False)
    assert relations(board, knife, config=geometric)["knife_0"] == ("cutting_board_0", "in")
    # Sunk deeper than the on gap: neither in nor on, so near the table.
    deep = box("knife_0", 50, 30, 0.2, 22, 2, 1)
    assert relations(board, deep)["knife_0"] == (TABLE, "near")
    # A lemon nested in an orange in a bowl: the lemon goes in the bowl, the innermost container.
    bowl = box("bowl_0", 70, 30, 0, 15, 15, 7)
    orange = box("orange_0", 70, 30, 0.5, 9, 9, 8)
    lemon = box("lemon_0", 70, 30, 1.0, 5, 4, 4)
    rel = relations(bowl, orange, lemon)
    assert rel["orange_0"] == ("bowl_0", "in") and rel["lemon_0"] == ("bowl_0", "in")


def test_container_role_resolves_names_and_unknown_keeps_geometry():
    assert container_role("Coffee Mugs") == "container"  # normalised, alias coffee_mug -> mug
    assert container_role("pen_cup") == "container" and container_role("ceramic_bowl") == "container"
    assert container_role("kitchen_knife") == "object" and container_role("cutting_board") == "support"
    assert container_role("widget_holder") is None and can_contain("widget_holder")
    assert not can_contain("notebook") and can_contain("tray")
    # An unknown category (an arbitrary MesaTask mesh) is still a container by geometry alone.
    rel = relations(box("crate_0", 50, 30, 0, 20, 20, 10), box("pear_0", 50, 30, 0.5, 6, 6, 7))
    assert rel["pear_0"] == ("crate_0", "in")


def test_in_requires_container_from_config():
    assert GraphConfig.load().in_requires_container is True
    assert GraphConfig.load(["in_requires_container=false"]).in_requires_container is False
    with pytest.raises(ConfigError, match="in_requires_container"):
        GraphConfig.load(["in_requires_container=2"])
