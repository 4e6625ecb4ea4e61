"""Fuzz the CTRC parser: >= 10,000 random and mutated completions, none raises.

Every mutation below breaks the layout on purpose (truncation, NaN, non-positive extents,
duplicate ids, unknown parents, cycles, absurd magnitudes, wrong types, deep nesting, junk), so
each must come back as a ParseError with a non-empty reason. Junk inserted at random positions
may land inside a string and leave a valid layout: for those only "no exception" is required.
"""

import copy
import json
import math
import random
import time

import pytest

from physcene.ctrc import ParseError, completion_text, parse
from physcene.layout import read_layout
from physcene.scene import Scene, SceneObject, Zone

MARK = "**Scene Layout:**"


def _base_completions() -> list[str]:
    example = read_layout("examples/office_table.layout.json")
    stack = Scene(Zone(0, 60, 0, 40), (
        SceneObject("box_0", "box", (30.0, 20.0, 5.0), (20.0, 16.0, 10.0), yaw=0.4),
        SceneObject("book_0", "book", (30.5, 20.0, 11.0), (12.0, 9.0, 2.0), yaw=1.0),
        SceneObject("cup_0", "cup", (30.5, 20.2, 15.0), (5.0, 5.0, 6.0), yaw=-2.0),
        SceneObject("bowl_0", "bowl", (8.0, 8.0, 3.0), (12.0, 12.0, 6.0)),
        SceneObject("spoon_0", "spoon", (8.0, 8.0, 3.5), (2.0, 6.0, 5.0), yaw=0.2),
    ))
    return [completion_text(example), completion_text(stack)]


def _split(text: str) -> tuple[str, dict]:
    head, body = text.split(MARK)
    return head + MARK + "\n", json.loads(body)


def _join(head: str, data: dict) -> str:
    return head + json.dumps(data)  # allow_nan: NaN / Infinity tokens are what we want to test


WRONG = {
    "relative_bbox": ["1,2,3,4,5,6", [1, 2, 3], [0, 1, 0, 1, 0, "1"], {"x": 1}, 5, True, [[0, 1]] * 6, None],
    "relative_rotation_deg": ["90", [90], True, {}],
    "parent_id": [5, [], {}, True, ""],
    "instance_id": [5, None, [], "", "   ", {"a": 1}],
    "relation_type": [3, "under", [], True, "beside_the_point"],
    "description": [5, [], {}, True],
    "category": [5, [], True],
    "layer": ["1", 1.5, [], -1, {}],
}


def _objects(data):
    return [e for e in data["objects"] if e.get("instance_id") != "root_zone"]


def _mutate(rng: random.Random, head: str, data: dict) -> str:
    """One deliberately invalid completion."""
    data = copy.deepcopy(data)
    objs = _objects(data)
    e = rng.choice(objs)
    kind = rng.randrange(11)
    if kind == 0:  # non-finite number
        e["relative_bbox"][rng.randrange(6)] = rng.choice([math.nan, math.inf, -math.inf])
    elif kind == 1:  # non-positive extent
        axis = rng.randrange(3)
        lo = e["relative_bbox"][2 * axis]
        e["relative_bbox"][2 * axis + 1] = lo - rng.choice([0.0, 1e-3, 5.0])
    elif kind == 2:  # duplicate id
        other = rng.choice([o for o in objs if o is not e] or [e])
        if other is e:
            data["objects"].append(copy.deepcopy(e))
        else:
            other["instance_id"] = e["instance_id"]
    elif kind == 3:  # unknown parent
        e["parent_id"] = rng.choice(["ghost_0", "root", "ROOT_ZONE", e["instance_id"] + "x"])
        e["relation_type"] = "on"
    elif kind == 4:  # parent cycle (or self-parent)
        ring = rng.sample(objs, rng.randint(1, len(objs)))
        for a, b in zip(ring, ring[1:] + ring[:1]):
            a["parent_id"], a["relation_type"] = b["instance_id"], "on"
    elif kind == 5:  # absurd magnitude
        e["relative_bbox"][rng.randrange(6)] = rng.choice([1e9, -1e9, 1e300, 2e5])
        if rng.random() < 0.3:
            e["relative_bbox"] = [v * 1e6 for v in e["relative_bbox"]]
    elif kind == 6:  # wrong type in an entry
        field = rng.choice(list(WRONG))
        e[field] = rng.choice(WRONG[field])
        if field == "parent_id" and e[field] == "":
            e["relation_type"] = "on"
    elif kind == 7:  # wrong type at the top
        key = rng.choice(["objects", "item_placement_zone"])
        data[key] = rng.choice(["x", 5, None, [1, 2, 3], [5, 1, 0, 1], [0, math.nan, 0, 1], []])
        if key == "item_placement_zone":
            data["objects"] = [o for o in data["objects"] if o.get("instance_id") != "root_zone"]
    elif kind == 8:  # deep nesting
        depth = rng.choice([2_000, 20_000])
        return head + json.dumps(data).replace('"relative_bbox": [', '"relative_bbox": ' + "[" * depth, 1)
    elif kind == 9:  # near relation under an object / in the table
        if rng.random() < 0.5:
            e["relation_type"], e["parent_id"] = "near", rng.choice(objs)["instance_id"]
            if e["parent_id"] == e["instance_id"]:
                e["parent_id"] = "ghost_1"
        else:
            e["relation_type"], e["parent_id"] = "in", "root_zone"
    else:  # every object removed
        data["objects"] = [o for o in data["objects"] if o.get("instance_id") == "root_zone"]
    return _join(head, data)


def _random_json(rng: random.Random, depth: int = 0):
    r = rng.random()
    if depth > 3 or r < 0.3:
        return rng.choice([0, -1, 1.5, 1e9, "x", "objects", True, None, "", [], {}])
    if r < 0.6:
        return [_random_json(rng, depth + 1) for _ in range(rng.randrange(4))]
    keys = ["objects", "relative_bbox", "instance_id", "parent_id", "item_placement_zone", "layer", "k"]
    return {rng.choice(keys): _random_json(rng, depth + 1) for _ in range(rng.randrange(4))}


ALPHABET = '{}[]":,.-0123456789eE ntrufalsNaIiy\n\t<>/json`objects relative_bbox'


def test_fuzz_parser_never_raises():
    rng = random.Random(20260601)
    bases = [(text, *_split(text)) for text in _base_completions()]
    counts = {"truncated": 0, "mutated": 0, "junk": 0, "random": 0, "special": 0}
    t0 = time.perf_counter()

    def must_fail(text: str, label: str):
        result = parse(text)
        assert isinstance(result, ParseError), (label, text[:300])
        assert isinstance(result.reason, str) and result.reason.strip(), label
        counts[label] += 1

    for _ in range(2_500):  # truncation at any point before the layout closes
        text, head, _ = rng.choice(bases)
        must_fail(text[: rng.randrange(text.rindex("}"))], "truncated")
    for _ in range(4_500):
        _, head, data = rng.choice(bases)
        must_fail(_mutate(rng, head, data), "mutated")
    for _ in range(1_500):  # junk tokens anywhere: no exception, a reason if it fails
        text, *_ = rng.choice(bases)
        for _ in range(rng.randint(1, 4)):
            k = rng.randrange(len(text) + 1)
            junk = rng.choice(["}", "{", "]", ",", '"', "NaN", "<json>", "```", "\\", "\x00", "null",
                               "1e999"])
            text = text[:k] + junk + text[k:]
        result = parse(text)
        assert isinstance(result, (Scene, ParseError))
        if isinstance(result, ParseError):
            assert result.reason.strip()
        counts["junk"] += 1
    for _ in range(1_000):
        must_fail("".join(rng.choice(ALPHABET) for _ in range(rng.randrange(200))) or " ", "random")
    for _ in range(500):
        must_fail(json.dumps(_random_json(rng)), "random")
    specials = ["", " ", "\n\n", "{}", "[]", "null", '{"objects": null}', '{"objects": {}}',
                '{"objects": [null]}', "<json><json>", "```json\n```", "[" * 50_000, '{"a":' * 30_000,
                '{"objects": [' + "1" * 5000 + "]}", "\ud800", "\x00" * 1000, "{" * 300_000]
    for text in specials:
        must_fail(text, "special")
    total = sum(counts.values())
    elapsed = time.perf_counter() - t0
    print(f"fuzz: {total} completions in {elapsed:.1f} s {counts}")
    assert total >= 10_000


@pytest.mark.parametrize("value", [None, 5, b"{}", ["x"], object()])
def test_non_string_input(value):
    result = parse(value)
    assert isinstance(result, ParseError) and "string" in result.reason
