"""The procedural generator on ten instructions of other scene types than the dining table: every named
category present, every stated in/on relation built as stated, no pair interpenetrating."""

from __future__ import annotations

import numpy as np
import pytest

from physcene.generation import procedural_scene, read_instruction
from physcene.generation.procedural import GenerationError

FRUIT = ("apple", "orange", "lemon")
# (instruction, scene type, categories that must be present, (child categories, relation, parent))
CASES = [
    ("an office desk with a monitor, a keyboard, a mouse and two pens in the pen holder", "office table",
     ["monitor", "keyboard", "mouse", "pen", "pen_holder"], [(("pen",), "in", "pen_holder")]),
    ("a coffee table with a mug on the saucer, three books and a remote", "coffee table",
     ["mug", "saucer", "book", "remote"], [(("mug",), "on", "saucer")]),
    ("a dressing table with a mirror, perfume, a lipstick and a comb in the tray", "dressing table",
     ["mirror", "perfume", "lipstick", "comb", "tray"], [(("comb",), "in", "tray")]),
    ("a kitchen counter with a kettle, a knife on the cutting board and a banana", "kitchen counter",
     ["kettle", "knife", "cutting_board", "banana"], [(("knife",), "on", "cutting_board")]),
    ("a bathroom vanity with a toothbrush in the toothbrush cup, soap in the soap dish and a towel",
     "bathroom vanity", ["toothbrush", "toothbrush_cup", "soap", "soap_dish", "towel"],
     [(("toothbrush",), "in", "toothbrush_cup"), (("soap",), "in", "soap_dish")]),
    ("a cashier counter with a cash register, a card reader and a pen in a pen holder", "cashier counter",
     ["cash_register", "card_reader", "pen", "pen_holder"], [(("pen",), "in", "pen_holder")]),
    ("a nightstand with a lamp, a clock and a phone on a book", "nightstand",
     ["lamp", "clock", "phone", "book"], [(("phone",), "on", "book")]),
    ("a side table with a plant, a candle on a book and a remote", "side table",
     ["plant", "candle", "book", "remote"], [(("candle",), "on", "book")]),
    ("a tv stand with a television, two speakers and a controller on the console", "tv stand",
     ["television", "speaker", "game_controller", "game_console"],
     [(("game_controller",), "on", "game_console")]),
    ("a kitchen counter with fruit in the basket, a toaster and a jar", "kitchen counter",
     ["basket", "toaster", "jar"], [(FRUIT, "in", "basket")]),
]


@pytest.fixture(scope="module")
def generated():
    return [procedural_scene(read_instruction(text), np.random.default_rng([7, k]))
            for k, (text, *_) in enumerate(CASES)]


@pytest.mark.parametrize("k", range(len(CASES)))
def test_named_objects_and_relations_are_in_the_layout(generated, k):
    text, scene_type, categories, relations = CASES[k]
    scene = generated[k]
    assert scene.scene_type == scene_type and scene.instruction == text
    present = {o.category for o in scene.objects}
    assert set(categories) <= present, sorted(set(categories) - present)
    by_id = scene.by_id()
    for children, relation, parent in relations:
        assert any(o.category in children and o.relation == relation and by_id[o.parent].category == parent
                   for o in scene.objects if o.parent in by_id), (children, relation, parent)
    assert all(o.description for o in scene.objects)


def test_counts_are_kept(generated):
    counts = [sum(o.category == c for o in generated[k].objects)
              for k, c in ((0, "pen"), (1, "book"), (8, "speaker"))]
    assert counts[0] >= 2 and counts[1] >= 3 and counts[2] >= 2


def test_no_pair_interpenetrates(generated):
    from physcene import check

    reports = check(generated)
    assert [r["pairs"] for r in reports] == [[] for _ in generated]
    assert [r["floating"] for r in reports] == [[] for _ in generated]


def test_only_fills_in_nothing_and_an_impossible_request_is_one_error():
    rng = np.random.default_rng(0)
    scene = procedural_scene(read_instruction("only a lamp and a clock on a nightstand"), rng)
    assert sorted(o.category for o in scene.objects) == ["clock", "lamp"]
    with pytest.raises(GenerationError, match="could not fit"):
        procedural_scene(read_instruction("two televisions on a nightstand"), rng, tries=2)
