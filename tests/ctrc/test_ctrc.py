"""CTRC: relative boxes, encode/decode, completion text, prompts, parser; round-trip property."""

import json
import math
import random

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from physcene.ctrc import (
    ON_CONTACT_GAP_CM,
    ParseError,
    build_prompt,
    coarse_location,
    completion_text,
    decimals_of,
    decode,
    encode,
    parse,
    sub_instructions,
    zero_shot_prompt,
)
from physcene.graph import build_hierarchy
from physcene.layout import layout_to_dict, load_layout, read_layout, yaw_to_quaternion
from physcene.scene import TABLE, Scene, SceneError, SceneObject, Zone

EXAMPLE = "examples/office_table.layout.json"


def assert_scenes_close(a: Scene, b: Scene, tol: float = 1e-4):
    """Same ids, categories, descriptions; poses and sizes within tol (cm, rad)."""
    np.testing.assert_allclose(a.zone.to_list(), b.zone.to_list(), atol=tol)
    assert sorted(a.ids()) == sorted(b.ids())
    bb = b.by_id()
    for o in a.objects:
        p = bb[o.instance_id]
        assert (o.category, o.description) == (p.category, p.description), o.instance_id
        np.testing.assert_allclose(o.center, p.center, atol=tol, err_msg=o.instance_id)
        np.testing.assert_allclose(o.size, p.size, atol=tol, err_msg=o.instance_id)
        dyaw = math.remainder(o.yaw - p.yaw, 2 * math.pi)
        assert abs(dyaw) <= tol, (o.instance_id, o.yaw, p.yaw)


def obj(iid, center, size, yaw=0.0, **kw):
    return SceneObject(instance_id=iid, category=iid.rsplit("_", 1)[0], center=center, size=size, yaw=yaw,
                       **kw)


# Relative placement --------------------------------------------------------------------------
def test_relative_bbox_of_child_in_rotated_parent():
    zone = Zone(0, 100, 0, 60)
    parent = obj("tray_0", (50.0, 30.0, 1.0), (20.0, 10.0, 2.0), yaw=math.pi / 2)
    child = obj("cup_0", (50.0, 30.0, 6.0), (4.0, 6.0, 8.0), yaw=math.pi / 2 + 0.25)
    entries = {e["instance_id"]: e for e in encode(Scene(zone, (parent, child)))}
    assert entries["tray_0"]["relative_bbox"] == pytest.approx([40, 60, 25, 35, 0, 2])
    e = entries["cup_0"]
    assert (e["parent_id"], e["relation_type"], e["layer"]) == ("tray_0", "on", 2)
    # Centred in the parent's frame (10, 5) from its (xmin, ymin) corner, own extents 4 x 6 x 8,
    # z from the parent's top.
    assert e["relative_bbox"] == pytest.approx([8, 12, 2, 8, 0, 8])
    assert e["relative_rotation_deg"] == pytest.approx(math.degrees(0.25))


def test_in_relation_z_from_parent_bottom_and_zone_corner_offset():
    zone = Zone(-10, 90, 5, 65)
    holder = obj("pen_holder_0", (10.0, 20.0, 5.0), (8.0, 8.0, 10.0))
    pen = obj("pen_0", (10.0, 20.0, 7.5), (1.0, 1.0, 14.0))
    entries = {e["instance_id"]: e for e in encode(Scene(zone, (holder, pen)))}
    assert entries["pen_holder_0"]["relative_bbox"] == pytest.approx([16, 24, 11, 19, 0, 10])
    assert entries["pen_0"]["relation_type"] == "in"
    assert entries["pen_0"]["relative_bbox"] == pytest.approx([3.5, 4.5, 3.5, 4.5, 0.5, 14.5])


def test_encode_decode_exact_and_subtree_moves_rigidly():
    scene = build_hierarchy(read_layout(EXAMPLE))
    entries = encode(scene)
    decoded = decode(entries, scene.zone)
    # exact, but an `on` child resting on its support comes back ON_CONTACT_GAP_CM above it
    assert_scenes_close(decoded, scene, tol=1.01 * ON_CONTACT_GAP_CM)
    mug, saucer = decoded.get("7_mug_0"), decoded.get("6_saucer_0")
    assert scene.get("7_mug_0").zmin == scene.get("6_saucer_0").zmax  # the example's exact contact
    assert mug.zmin - saucer.zmax == pytest.approx(ON_CONTACT_GAP_CM, abs=1e-9)
    assert encode(decoded, decimals=5) == encode(scene, decimals=5)  # the text round trip is exact
    # Moving / turning the parent in the text moves its child with it (rigid subtree).
    book = next(e for e in entries if e["instance_id"] == "2_book_0")
    book["relative_rotation_deg"] += 90.0
    moved = decode(entries, scene.zone)
    b0, b1 = moved.get("2_book_0"), moved.get("3_book_1")
    orig0, orig1 = scene.get("2_book_0"), scene.get("3_book_1")
    assert math.dist(b0.center, b1.center) == pytest.approx(math.dist(orig0.center, orig1.center)
                                                            + ON_CONTACT_GAP_CM)  # the book rests on the book
    assert b1.yaw - b0.yaw == pytest.approx(orig1.yaw - orig0.yaw)


def test_decode_errors_name_object_and_field():
    zone = Zone(0, 100, 0, 60)
    good = {"instance_id": "cup_0", "parent_id": TABLE, "relation_type": "near",
            "relative_bbox": [1, 5, 1, 5, 0, 8], "relative_rotation_deg": 0}
    cases = [
        ({"relative_bbox": [5, 1, 1, 5, 0, 8]}, "relative_bbox"),
        ({"relative_bbox": [1, 5, 1, 5, 0, float("nan")]}, "relative_bbox"),
        ({"relative_bbox": [1, 5, 1, 5, 0, 1e9]}, "relative_bbox"),
        ({"relative_rotation_deg": "90"}, "relative_rotation_deg"),
        ({"parent_id": "ghost_0", "relation_type": "on"}, "parent_id"),
        ({"parent_id": TABLE, "relation_type": "under"}, "relation_type"),
        ({"description": 3}, "description"),
        ({"layer": "one"}, "layer"),
    ]
    for change, field in cases:
        with pytest.raises(SceneError) as info:
            decode([{**good, **change}], zone)
        assert info.value.obj == "cup_0" and info.value.field == field, change
    with pytest.raises(SceneError, match="duplicate"):
        decode([good, good], zone)
    a = {**good, "instance_id": "a_0", "parent_id": "b_0", "relation_type": "on"}
    b = {**good, "instance_id": "b_0", "parent_id": "a_0", "relation_type": "on"}
    with pytest.raises(SceneError, match="cycle"):
        decode([a, b], zone)


# Text ----------------------------------------------------------------------------------------
def test_completion_text_format():
    scene = read_layout(EXAMPLE)
    text = completion_text(scene)
    plan, layout = text.split("**Scene Layout:**")
    lines = [ln for ln in plan.splitlines() if ln[:1].isdigit()]
    assert len(lines) == len(scene)
    assert lines[0] == "1. Place 1_laptop_0 at the center of the table."
    assert "Place 5_pen_0 in 4_pen_holder_0." in plan and "Place 7_mug_0 on 6_saucer_0." in plan
    assert "Place 4_pen_holder_0 to the left of 1_laptop_0, about 44 cm away, at the left back" in plan
    data = json.loads(layout)
    assert data["item_placement_zone"] == [0, 120, 0, 60]
    assert data["objects"][0] == {"layer": 0, "instance_id": TABLE, "type": "zone",
                                  "bbox": [0, 120, 0, 60, 0, 0], "z_rotation": 0}
    keys = {"layer", "instance_id", "category", "parent_id", "relation_type", "description",
            "relative_bbox", "relative_rotation_deg"}
    assert all(set(e) == keys for e in data["objects"][1:])
    ids = [e["instance_id"] for e in data["objects"][1:]]
    assert ids.index("4_pen_holder_0") + 1 == ids.index("5_pen_0")  # children right after the parent
    assert isinstance(parse(text), Scene)
    assert [i for i, _ in sub_instructions(scene)] == ids


def test_coarse_location():
    zone = Zone(0, 90, 0, 60)
    at = lambda x, y: coarse_location(obj("a_0", (x, y, 1.0), (1.0, 1.0, 2.0)), zone)  # noqa: E731
    assert [at(45, 30), at(5, 55), at(85, 5), at(45, 55), at(5, 30)] == [
        "center", "left back", "right front", "back", "left"]


def test_prompts():
    objects = read_layout(EXAMPLE).objects
    p = build_prompt("Set up a desk.", "office table", Zone(0, 120, 0, 60), objects)
    assert "Set up a desk." in p and "office table" in p and "[0.0, 120.0, 0.0, 60.0]" in p
    assert "book (2)" in p and "pen holder (1)" in p
    assert "Object List" not in build_prompt("x", "office table", [0, 120, 0, 60])
    assert "restricted_zone" not in p
    sink = build_prompt("x", "kitchen counter", [0, 120, 0, 60], restricted_zones=[Zone(10, 40, 20, 50)])
    assert "**restricted_zone**: [[10.0, 40.0, 20.0, 50.0]]" in sink
    z = zero_shot_prompt("Tidy up.", [0, 80.5, 0, 41.9], ["woven_basket_0", "1_lotion_bottle_1"])
    assert "**item_placement_zone**: [0.0, 80.5, 0.0, 41.9]" in z
    assert "woven basket (1), lotion bottle (1)" in z
    assert '"instance": "unique_object_name"' in z


# Parser --------------------------------------------------------------------------------------
PROMPT3_OUTPUT = """<json>
{
    "item_placement_zone": [0.0, 80.5, 0.0, 41.9],
    "objects": [
        {"instance": "woven_basket_0", "z_rotation": 0.0, "size": [20.0, 15.0, 12.0],
         "position": [65.0, 28.0, 6.0], "description": "basket"},
        {"instance": "lotion_bottle_1", "z_rotation": 1.5708, "size": [5.0, 5.0, 15.0],
         "position": [10.0, 30.0, 7.5], "description": "bottle"},
    ]
}
<json>"""


def test_parse_prompt3_flat_output():
    scene = parse(PROMPT3_OUTPUT)
    assert isinstance(scene, Scene), scene
    assert scene.get("lotion_bottle_1").yaw == pytest.approx(1.5708)
    assert scene.get("woven_basket_0").category == "woven_basket"
    assert scene.zone.to_list() == [0.0, 80.5, 0.0, 41.9]
    # An explicit zone (the task's table) wins over the completion's.
    assert parse(PROMPT3_OUTPUT, zone=[0, 100, 0, 50]).zone.to_list() == [0, 100, 0, 50]


@pytest.mark.parametrize("wrap", [
    lambda t: t,
    lambda t: "Sure! Here is the layout.\n```json\n" + t.split("**Scene Layout:**")[1] + "```\nDone.",
    lambda t: "<json>" + t.split("**Scene Layout:**")[1] + "<json>",
    lambda t: t.replace("\n  ],", ",\n  ],"),  # a trailing comma
])
def test_parse_wrappings(wrap):
    scene = read_layout(EXAMPLE)
    assert_scenes_close(parse(wrap(completion_text(scene))), scene)


def test_parse_paper_appendix_example():
    text = """**Scene Layout:**
{"objects": [{"layer": 0, "instance_id": "root_zone", "type": "zone",
 "bbox": [0.0, 80.5, 0.0, 41.9, 0.0, 0.0], "z_rotation": 0.0},
 {"layer": 1, "instance_id": "2_woven_basket_0", "parent_id": "root_zone",
 "relation_type": "on_surface", "description": "basket",
 "relative_bbox": [57.05, 78.75, 20.7, 35.5, 0.0, 15.0],
 "relative_rotation_deg": 0.0}], "item_placement_zone": [0.0, 80.5, 0.0, 41.9]}"""
    scene = parse(text)
    o = scene.get("2_woven_basket_0")
    assert o.category == "woven_basket" and o.relation == "near" and o.parent == TABLE
    np.testing.assert_allclose(o.center, [67.9, 28.1, 7.5])
    np.testing.assert_allclose(o.size, [21.7, 14.8, 15.0])


# The paper's appendix example from "**Sub-instruction:**" on (trailing spaces trimmed), with its
# typeset line wraps inside strings (raw newlines) and "on_surface" relations.
PAPER_EXAMPLE = """**Sub-instruction:**
[
    {
        "step": 1,
        "instance_id": "10_lotion_bottle_1",
        "instruction": "Place 10_lotion_bottle_1 at the left back of center of t
                        he table, approximately 28cm from center.",
        "reference_objects": []
    },
    {
        "step": 2,
        "instance_id": "1_soapenser_lotion_bottle_0",
        "instruction": "Place 1_soapenser_lotion_bottle_0 to the left of 10_loti
                        on_bottle_1.",
        "reference_objects": ["10_lotion_bottle_1"]
    },
    {
        "step": 3,
        "instance_id": "2_woven_basket_0",
        "instruction": "Place 2_woven_basket_0 near 10_lotion_bottle_1, about 53
                        cm away.",
        "reference_objects": ["10_lotion_bottle_1"]
    }
]

**Scene Layout:**
{
    "objects": [
                   {
                       "layer": 0,
                       "instance_id": "root_zone",
                       "type": "zone",
                       "bbox": [0.0, 80.5, 0.0, 41.9, 0.0, 0.0],
                       "z_rotation": 0.0
                    },
                    {
                       "layer": 1,
                       "instance_id": "2_woven_basket_0",
                       "parent_id": "root_zone",
                       "relation_type": "on_surface",
                       "description": "Rectangular woven basket of natural fiber
                                       s, light brown color with darker accents
                                       and distinctive texture.",
                       "relative_bbox": [57.05, 78.75, 20.7, 35.5, 0.0, 15.0],
                       "relative_rotation_deg": 0.0
                    },

                    {
                       "layer": 1,
                       "instance_id": "1_soapenser_lotion_bottle_0",
                       "parent_id": "root_zone",
                       "relation_type": "on_surface",
                       "description": "Tall, cylindrical, smooth surface, pastel
                                       colors, slightly tapered base, labeled wi
                                       th brand information.",
                       "relative_bbox": [2.75, 12.85, 30.9, 36.1, 0.0, 22.0],
                       "relative_rotation_deg": 0.0
                    },
                    {
                       "layer": 1,
                       "instance_id": "10_lotion_bottle_1",
                       "parent_id": "root_zone",
                       "relation_type": "on_surface",
                       "description": "Tall, cylindrical, smooth surface, pastel
                                       colors, slightly tapered base, labeled wi
                                       th brand information.",
                       "relative_bbox": [13.8, 21.6, 31.75, 35.65, 0.0, 16.2],
                       "relative_rotation_deg": 0.0}],
                       "item_placement_zone": [0.0, 80.5, 0.0, 41.9]
                    }
"""


def test_parse_paper_appendix_verbatim():
    scene = parse(PAPER_EXAMPLE)
    assert isinstance(scene, Scene), scene
    assert scene.ids() == ["2_woven_basket_0", "1_soapenser_lotion_bottle_0", "10_lotion_bottle_1"]
    bottle = scene.get("10_lotion_bottle_1")
    assert bottle.category == "lotion_bottle" and bottle.relation == "near"
    np.testing.assert_allclose(bottle.center, [17.7, 33.7, 8.1])
    np.testing.assert_allclose(bottle.size, [7.8, 3.9, 16.2], atol=1e-9)


def test_parse_rejects_too_many_objects():
    entry = '{"instance": "cup_%d", "position": [1, 1, 1], "size": [1, 1, 1]}'
    text = ('{"item_placement_zone": [0, 10, 0, 10], "objects": ['
            + ", ".join(entry % k for k in range(1001)) + "]}")
    result = parse(text)
    assert isinstance(result, ParseError) and "1001 objects" in result.reason


@pytest.mark.parametrize("text, reason", [
    ("", "empty"), ("   \n", "empty"), ("no json here", "no JSON"), ('{"objects": []', "truncated"),
    ('{"objects": [], "item_placement_zone": [0, 1, 0, 1]}', "no objects"),
    ('{"objects": [{"instance_id": "a_0", "relative_bbox": [0, 1, 0, 1, 0, 1]}]}', "item_placement_zone"),
    ('{"objects": [{"instance_id": "a_0", "relative_bbox": [0, NaN, 0, 1, 0, 1]}], '
     '"item_placement_zone": [0, 1, 0, 1]}', "NaN"),
    ("[" * 100000, "JSON"), ('{"a":' * 30000, "deep"), ("{" * 300000, "exceeds"), (None, "string"),
], ids=["empty", "blank", "no-json", "truncated", "no-objects", "no-zone", "nan", "brackets", "deep", "long",
        "none"])
def test_parse_rejects_with_reason(text, reason):
    result = parse(text)
    assert isinstance(result, ParseError) and reason.lower() in result.reason.lower(), result


# Round-trip property ------------------------------------------------------------------------
_WORDS = ["mug", "book", "pen", "plate", "bowl", "lamp", "box", "cylinder", "sphere", "tray"]
# What a pen may go "in" (graph.in_requires_container): container categories, and a category the
# priors do not know ("box"), which keeps the geometric rule.
_CONTAINERS = ["mug", "plate", "bowl", "tray", "pen_holder", "basket", "box"]
_DESCRIPTIONS = ["", "A plain mug.", 'He said "hi" {ok}', "Scene Layout: <json> ]", "Über 10°",
                 "line\nbreak", "tab\there"]


@st.composite
def layouts(draw):
    """A MesaTask layout dict whose intended hierarchy is unambiguous, and that hierarchy.

    Roots sit in separate grid cells (some flush with the zone edges, some rotated); on each root
    there may be a stack up to three deep (each level small and centred enough to be fully
    supported) or, for containers, one object inside. Hypothesis draws the structure; the
    continuous values come from a generator it seeds (one draw instead of dozens keeps 500
    examples fast).
    """
    rng = random.Random(draw(st.integers(0, 2**32 - 1)))

    def u(lo, hi):
        return lo + (hi - lo) * rng.random()

    x0, y0 = u(-50, 50), u(-50, 50)
    nx, ny = draw(st.integers(1, 3)), draw(st.integers(1, 2))
    cell_w, cell_d = u(25, 60), u(25, 60)
    zone = [x0, x0 + nx * cell_w, y0, y0 + ny * cell_d]
    objects, intended = [], {}
    counter = iter(range(10_000))

    def add(category, center, size, yaw, parent, relation):
        iid = f"{next(counter)}_{category}_{rng.randrange(4)}"
        entry = {"instance": iid, "position": list(center), "size": list(size),
                 "description": rng.choice(_DESCRIPTIONS)}
        style = draw(st.sampled_from(["quat", "both", "z"]))
        if style in ("quat", "both"):
            entry["rotation"] = yaw_to_quaternion(yaw)
        if style in ("both", "z"):
            entry["z_rotation"] = yaw if style == "z" else yaw + 1.0  # the quaternion must win
        if rng.random() < 0.5:
            entry["retrieved_uid"] = f"uid{rng.randrange(100)}"
        objects.append(entry)
        intended[iid] = (parent, relation)
        return iid

    for i in range(nx):
        for j in range(ny):
            if not draw(st.booleans()):
                continue
            m = min(cell_w, cell_d)
            w, d = u(0.3 * m, 0.65 * m), u(0.3 * m, 0.65 * m)
            h = u(5.0, 30.0)
            yaw = draw(st.sampled_from([0.0, math.pi / 2, -math.pi, u(-math.pi, math.pi)]))
            # Centre inside the cell, or flush with a zone edge when the cell is on the border.
            # Half extents of the yawed footprint's axis-aligned box.
            ex = 0.5 * (abs(w * math.cos(yaw)) + abs(d * math.sin(yaw)))
            ey = 0.5 * (abs(w * math.sin(yaw)) + abs(d * math.cos(yaw)))
            cx = x0 + (i + 0.5) * cell_w + u(-0.05, 0.05) * cell_w
            cy = y0 + (j + 0.5) * cell_d + u(-0.05, 0.05) * cell_d
            if i in (0, nx - 1) and draw(st.booleans()):
                cx = x0 + ex if i == 0 else zone[1] - ex
            if j in (0, ny - 1) and draw(st.booleans()):
                cy = y0 + ey if j == 0 else zone[3] - ey
            kind = draw(st.sampled_from(["single", "stack", "container"]))
            cat = rng.choice(_CONTAINERS if kind == "container" else _WORDS)
            root = add(cat, (cx, cy, 0.5 * h), (w, d, h), yaw, TABLE, "near")
            if kind == "container":
                cw, cd = u(0.1, 0.5) * min(w, d), u(0.1, 0.5) * min(w, d)
                t = u(0.0, 0.8)
                ch = u(0.5, 1.8) * (h - t)
                off = u(-0.1, 0.1) * min(w, d)
                add("pen", (cx + off, cy - off, t + 0.5 * ch), (cw, cd, ch), u(-3.2, 3.2),
                    root, "in")
            elif kind == "stack":
                parent, pw, pd, ptop, px, py = root, w, d, h, cx, cy
                for _ in range(draw(st.sampled_from([1, 2, 3, 3]))):
                    m = min(pw, pd)
                    sw, sd = u(0.2, 0.5) * m, u(0.2, 0.5) * m
                    sh = u(1.5, 8.0)
                    offx, offy = u(-0.1, 0.1) * m, u(-0.1, 0.1) * m
                    gap = u(-0.3, 0.3)  # resting within the 1 cm "on" tolerance
                    px, py = px + offx, py + offy
                    parent = add(rng.choice(_WORDS), (px, py, ptop + gap + 0.5 * sh), (sw, sd, sh),
                                 u(-math.pi, math.pi), parent, "on")
                    pw, pd, ptop = sw, sd, ptop + gap + sh
    if not objects:
        add("mug", (x0 + 10, y0 + 10, 5.0), (8.0, 8.0, 10.0), 0.0, TABLE, "near")
    as_dict = draw(st.booleans())
    data = {"item_placement_zone": zone, "restricted_zone": [], "scene_type": "office table",
            "objects": {o.pop("instance"): o for o in objects} if as_dict else objects}
    return data, intended


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(layouts())
def test_round_trip_layout_ctrc_text_parse(case):
    data, intended = case
    scene = load_layout(json.loads(json.dumps(data)))
    hierarchy = build_hierarchy(scene)
    assert {o.instance_id: (o.parent, o.relation) for o in hierarchy.objects} == intended
    text = completion_text(hierarchy)  # the same text completion_text(scene) builds, one graph pass saved
    parsed = parse(text)
    assert isinstance(parsed, Scene), (parsed, text)
    assert_scenes_close(parsed, scene, tol=1e-4)
    assert {o.instance_id: (o.parent, o.relation) for o in parsed.objects} == intended
    assert {o.instance_id: o.asset_id for o in scene.objects} == {
        o["instance"]: o["retrieved_uid"] for o in layout_to_dict(scene)["objects"]}
    # The layout JSON is stable: encoding the parsed scene again writes the same entries. (Their
    # order and the plan's whole-cm distances may flip where the original had an exact tie.)
    def entries(t):
        rows = json.loads(t.split("**Scene Layout:**")[1])["objects"]
        return {r["instance_id"]: r for r in rows}
    assert entries(completion_text(parsed)) == entries(text)


def test_completion_text_of_a_box_thinner_than_the_last_decimal_still_parses():
    """A model may write an extent of 1e-7 cm (max just above min); its anchor text rounds to 5
    decimals and must keep a positive extent instead of failing on a zero size."""
    from physcene.ctrc import completion_text, parse

    text = ('{"objects": [{"layer": 1, "instance_id": "1_pencil_0", "category": "pencil", "parent_id": '
            '"root_zone", "relation_type": "near", "description": "A pencil.", "relative_bbox": '
            '[10.0, 10.0000001, 5.0, 6.0, 0.0, 12.0], "relative_rotation_deg": 0.0}], '
            '"item_placement_zone": [0.0, 100.0, 0.0, 80.0]}')
    scene = parse(text)
    assert not isinstance(scene, ParseError), scene
    again = parse(completion_text(scene))
    assert not isinstance(again, ParseError), again
    assert 0 < again.objects[0].size[0] <= 2e-5


@pytest.mark.parametrize("decimals", [0, 1, 2, 5])
def test_decimals_of_reads_back_the_precision_completion_text_wrote(decimals):
    from physcene.data.noisy import noisy_scenes

    [scene] = noisy_scenes(1, 8, seed=3, push_cm=3.0)  # poses off the whole centimetre
    assert decimals_of(completion_text(scene, decimals=decimals)) == decimals
    # the plan's numbers (whole cm) and the prompt's never count: only the layout's
    assert decimals_of("1. Place mug_0 about 31.5 cm from the center.\n\n**Scene Layout:**\n{}") == 0


def test_text_and_tto_rest_on_children_the_same_distance_up():
    """TTO's output written as text and read back must not move its `on` children (tto.yaml)."""
    from physcene.tto import TTOConfig

    assert TTOConfig.load().contact_gap_cm == ON_CONTACT_GAP_CM
