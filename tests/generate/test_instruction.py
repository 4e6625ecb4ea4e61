"""Reading an instruction: scene type, named categories, counts, stated in/on relations, unknown words."""

from __future__ import annotations

import pytest

from physcene.generation import read_instruction


def _named(reading) -> dict:
    return {m.word: (m.categories, m.count) for m in reading.mentions}


def test_the_dining_example_is_read_whole():
    reading = read_instruction("a dining table set for two, with plates, glasses, a vase and a bowl of fruit")
    assert reading.scene_type == "dining table" and reading.scene_type_stated
    named = _named(reading)
    assert named["plates"] == (("plate",), None)
    assert named["glasses"] == (("glass",), None)  # drinking glasses on a dining table
    assert named["vase"] == (("vase",), 1) and named["bowl"] == (("bowl",), 1)
    assert set(named["fruit"][0]) == {"apple", "orange", "lemon"}
    assert [(reading.mentions[r.child].word, r.relation, reading.mentions[r.parent].word)
            for r in reading.relations] == [("fruit", "in", "bowl")]
    assert reading.diners == 2 and reading.unknown == ()


@pytest.mark.parametrize("text, word, count", [
    ("two mugs on a desk", "mugs", 2), ("3 pens and a notebook", "pens", 3), ("two white mugs", "mugs", 2),
    ("a lamp", "lamp", 1), ("some books", "books", 2), ("mugs", "mugs", None),
])
def test_counts(text, word, count):
    assert _named(read_instruction(text))[word][1] == count


@pytest.mark.parametrize("text, child, relation, parent", [
    ("a pen in the pen holder on my desk", "pen", "in", "pen holder"),
    ("a mug on the saucer", "mug", "on", "saucer"),
    ("fruit in the bowl", "fruit", "in", "bowl"),
    ("an apple on the plate", "apple", "in", "plate"),      # a plate's cavity holds it
    ("a candle on top of a book", "candle", "on", "book"),
    ("a cup of pens", "pens", "in", "cup"),
])
def test_stated_relations(text, child, relation, parent):
    reading = read_instruction(text)
    got = [(reading.mentions[r.child].word, r.relation, reading.mentions[r.parent].word)
           for r in reading.relations]
    assert got == [(child, relation, parent)]


def test_nothing_goes_on_an_ordinary_object():
    assert read_instruction("a phone on the lamp").relations == ()


def test_scene_type_from_a_word_or_from_the_objects():
    assert read_instruction("my bedside with a clock").scene_type == "nightstand"
    assert read_instruction("a keyboard, a mouse and a monitor").scene_type == "office table"
    assert not read_instruction("a keyboard, a mouse and a monitor").scene_type_stated
    assert read_instruction("a lamp", scene_type="side_table").scene_type == "side table"
    # eyeglasses where the type knows no drinking glass
    assert read_instruction("glasses on a dressing table").mentions[0].categories == ("glasses",)


def test_words_it_did_not_understand_are_listed():
    reading = read_instruction("a desk with a laptop and a frobnicator, please, sparkly")
    assert reading.unknown == ("frobnicator", "sparkly")
    assert [m.categories for m in reading.mentions] == [("laptop",)]


@pytest.mark.parametrize("bad", ["", "   "])
def test_an_empty_instruction_is_an_error(bad):
    with pytest.raises(ValueError, match="empty"):
        read_instruction(bad)
    with pytest.raises(ValueError, match="unknown scene type"):
        read_instruction("a lamp", scene_type="bar counter")
