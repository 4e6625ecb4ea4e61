"""``pada.object_credit`` (not in the paper): the physics reward charges each object the penetration of
the pairs it was written into, and PADA lowers the advantage of the tokens that place that object (its
plan step and its layout line)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from physcene.ctrc import completion_text, parse
from physcene.reward import ChargeConfig, PhysicsReward, RewardConfig
from physcene.scene import TABLE
from physcene.train.object_credit import ChargedReward, ObjectCredit, object_token_depths
from physcene.train.targets import numeric_spans, object_line_spans, object_text_spans
from physcene.train.tokenizer import build_tokenizer


@pytest.fixture(scope="module")
def texts(written_into):
    """A clean level-2 test scene as CTRC, and the same with its last table-level object moved onto
    its first one (a collision charged to the later-written object)."""
    clean, moved = written_into(0.0)
    return completion_text(clean, decimals=2), completion_text(moved, decimals=2)


@pytest.fixture(scope="module")
def reward():
    return PhysicsReward(RewardConfig(device="cpu"), charges=ChargeConfig())


def test_object_lines_are_the_parsed_objects_in_order(texts):
    for text in texts:
        lines = object_line_spans(text)
        scene = parse(text)
        assert len(lines) == len(scene.objects)
        for (a, b), obj in zip(lines, scene.objects):
            assert f'"instance_id": "{obj.instance_id}"' in text[a:b] and "\n" not in text[a:b]


def test_each_object_is_placed_by_its_plan_step_and_its_layout_line(texts):
    for text in texts:
        scene = parse(text)
        spans = object_text_spans(text)
        assert [s[-1] for s in spans] == object_line_spans(text)
        for (step, line), obj in zip(spans, scene.objects):
            assert text[step[0]:step[1]].split(". ", 1)[1].startswith(f"Place {obj.instance_id} ")
            assert step[1] < text.index("**Scene Layout:**") < line[0]
    # an object the plan does not name keeps its layout line only
    clean = texts[0]
    first = parse(clean).objects[0].instance_id
    renamed = clean.replace(f"Place {first} ", "Place something_else ", 1)
    assert object_text_spans(renamed)[0] == [object_line_spans(renamed)[0]]


def test_the_reward_charges_each_pair_to_the_object_written_later(texts, reward):
    clean, moved = texts
    scored = reward.score([clean, moved, "not a layout"])
    rewards, depths = scored.rewards.tolist(), scored.object_charges
    assert depths[2] is None and rewards[2] == -100.0
    assert not np.any(depths[0]) and rewards[0] == 50.0
    scene = parse(moved)
    score = reward.engine.score([scene])
    expected = np.zeros(len(scene.objects))
    for i, j, d in score.pairs[0]:
        expected[max(i, j)] += d
    assert expected.sum() > 0 and np.allclose(depths[1], expected, atol=1e-5)
    # the charges add up to the E_pen the reward was computed from (cm -> mm)
    assert rewards[1] == pytest.approx(-min(0.01 * 10.0 * depths[1].sum(), 50.0), abs=1e-4)
    ids = [o.instance_id for o in scene.objects]
    last_table = [o.instance_id for o in scene.objects if o.parent == TABLE][-1]
    assert depths[1][ids.index(last_table)] > 0


def test_the_tokens_of_a_charged_object_line_carry_its_depth(texts, reward):
    clean, moved = texts
    tokenizer = build_tokenizer([clean, moved], vocab_size=320)
    depths = reward.score([moved, clean]).object_charges
    rows = [tokenizer(t, add_special_tokens=False)["input_ids"] for t in (moved, clean)]
    width = max(map(len, rows)) + 3
    ids = torch.tensor([r + [tokenizer.pad_token_id] * (width - len(r)) for r in rows])
    mask = torch.tensor([[1] * len(r) + [0] * (width - len(r)) for r in rows])
    charged, skipped = object_token_depths(tokenizer, ids, mask, depths)
    assert skipped == 0 and not charged[1].any() and not charged[0, len(rows[0]):].any()
    offsets = tokenizer(moved, add_special_tokens=False, return_offsets_mapping=True)["offset_mapping"]
    placed = object_text_spans(moved)
    assert depths[0].max() > 0 and all(len(spans) == 2 for spans in placed)
    for spans, d in zip(placed, depths[0]):
        inside = [t for t, (s, e) in enumerate(offsets) if any(s < b and e > a for a, b in spans)]
        assert torch.allclose(charged[0, inside], torch.tensor(float(d)))
    outside = [t for t, (s, e) in enumerate(offsets)
               if not any(s < b and e > a for spans in placed for a, b in spans)]
    assert not charged[0, outside].any()
    # a row whose objects do not match its lines is left out, not charged at the wrong tokens
    charged, skipped = object_token_depths(tokenizer, ids, mask, [np.ones(len(depths[0]) + 1), None])
    assert skipped == 1 and not charged.any()


def test_pada_lowers_the_advantage_of_the_charged_tokens_only(texts, reward):
    _, moved = texts
    tokenizer = build_tokenizer([moved], vocab_size=320)
    scored = reward.score([moved, moved])
    row = tokenizer(moved, add_special_tokens=False)["input_ids"]
    output = {"completion_ids": torch.tensor([row, row]), "completion_mask": torch.ones(2, len(row)),
              "advantages": torch.tensor([0.5, -0.5])}
    logged = {}
    charged = ChargedReward(reward, reward.charges)
    charged.keep(scored)
    trainer = SimpleNamespace(_tokenizer=tokenizer, log_value=lambda k, v: logged.__setitem__(k, v))
    credit = ObjectCredit(charged, 2.0, "line")
    credit.after_scoring(trainer, [], output)
    charged, _ = object_token_depths(tokenizer, output["completion_ids"], output["completion_mask"],
                                     scored.object_charges)
    assert output["advantages"].shape == (2, len(row))
    assert torch.allclose(output["advantages"], torch.tensor([[0.5], [-0.5]]) - 2.0 * charged)
    assert 0 < logged["object_credit/charged_token_frac"] < 1 and logged["object_credit/rows_left_out"] == 0
    with pytest.raises(ValueError, match="object depths for 2 completions, 1 generated"):
        credit.after_scoring(trainer, [], {k: v[:1] for k, v in output.items()})



def test_the_numbers_scope_charges_only_the_charged_objects_geometry_numbers(texts, reward):
    """``pada.object_credit_scope: numbers``: of a charged object only the numbers of its box and
    rotation lose advantage, each by the object's depth; its id, category, relation, description and
    plan step keep the layout's advantage (with the whole line charged, 36-41 % of the
    rollout tokens, the greedy outputs began writing numbers into descriptions)."""
    _, moved = texts
    tokenizer = build_tokenizer([moved], vocab_size=320)
    depths = reward.score([moved]).object_charges
    ids = torch.tensor([tokenizer(moved, add_special_tokens=False)["input_ids"]])
    mask = torch.ones_like(ids)
    line, _ = object_token_depths(tokenizer, ids, mask, depths)
    numbers, skipped = object_token_depths(tokenizer, ids, mask, depths, scope="numbers")
    offsets = tokenizer(moved, add_special_tokens=False, return_offsets_mapping=True)["offset_mapping"]

    def over(spans):
        return [t for t, (s, e) in enumerate(offsets) if any(s < b and e > a for a, b in spans)]

    assert skipped == 0 and 0 < (numbers > 0).sum() < (line > 0).sum()
    charged = set(torch.nonzero(numbers[0]).flatten().tolist())
    assert charged <= set(over(numeric_spans(moved)))  # geometry numbers only
    for spans, d in zip(object_text_spans(moved, "numbers"), depths[0]):
        assert len(spans) == 7  # six box numbers and the rotation
        assert torch.allclose(numbers[0, over(spans)], torch.tensor(float(d)))
    with pytest.raises(ValueError, match="scope must be one of"):
        object_text_spans(moved, "words")


def _moved_last_table_object(scene, center):
    """``scene`` with its last table-level object moved to ``center(obj)``; (scene, its index)."""
    last = [o for o in scene.objects if o.parent == TABLE][-1]
    moved = scene.with_objects(o.moved(center=center(o)) if o is last else o for o in scene.objects)
    return moved, [o.instance_id for o in moved.objects].index(last.instance_id)


def test_floating_and_out_of_zone_objects_are_charged_when_asked(texts):
    """``object_terms``: a lifted object is charged its gap, one pushed past the zone edge how far
    its yawed footprint reaches past it: the objects the floating and out-of-zone metrics flag, read
    by the compiled scanner and by the parser alike."""
    from physcene.eval.metrics import out_of_zone
    from physcene.scene import ZONE_TOLERANCE_CM

    clean = parse(texts[0])
    lifted, k_lifted = _moved_last_table_object(clean, lambda o: (*o.center[:2], o.center[2] + 4.0))
    # wholly past the right edge (1 cm clear of it): out of the zone, touching nothing
    outside, k_out = _moved_last_table_object(
        clean, lambda o: (clean.zone.xmax + 1.0 + 0.5 * np.ptp(o.footprint()[:, 0]), *o.center[1:]))
    both = PhysicsReward(RewardConfig(device="cpu"),
                         charges=ChargeConfig(terms=("penetration", "floating", "out_of_zone")))
    written = [completion_text(s, decimals=2) for s in (clean, lifted, outside)]
    scored = both.score(written)
    assert scored.rewards.tolist() == [50.0, 50.0, 50.0]  # the paper's reward sees neither
    fast = [d.copy() for d in scored.object_charges]
    for a, b in zip(fast, both.score_parsed([parse(t) for t in written]).object_charges):
        assert np.allclose(a, b, atol=1e-4)
    none, on_lifted, on_outside = fast
    assert not none.any()
    assert np.flatnonzero(on_lifted).tolist() == [k_lifted]
    assert on_lifted[k_lifted] == pytest.approx(4.0, abs=0.05)
    assert np.flatnonzero(on_outside).tolist() == list(out_of_zone(outside)) == [k_out]
    fp = outside.objects[k_out].footprint()
    assert on_outside[k_out] == pytest.approx(fp[:, 0].max() - outside.zone.xmax, abs=1e-3)
    assert on_outside[k_out] > ZONE_TOLERANCE_CM
    # the default charges penetration only: neither moved object is charged
    only = PhysicsReward(RewardConfig(device="cpu"), charges=ChargeConfig())
    charged = only.score([completion_text(s, decimals=2) for s in (lifted, outside)]).object_charges
    assert not any(d.any() for d in charged)


def test_unknown_object_terms_are_named():
    from physcene.config import load_config
    from physcene.train.pada import pada_arguments

    with pytest.raises(ValueError, match=r"got \['penetration', 'flying'\]"):
        ChargeConfig(terms=("penetration", "flying"))
    repeated = load_config("train_tiny", ["pada.object_credit_terms=[out_of_zone,out_of_zone]"])
    with pytest.raises(ValueError, match="pada.object_credit_terms: object terms must be distinct"):
        pada_arguments(repeated, "pada")
    two = load_config("train_tiny", ["pada.object_credit_terms=[penetration,floating]"])
    args = pada_arguments(two, "pada")
    assert args.object_credit_terms == ["penetration", "floating"] and args.object_credit_scope == "line"
    numbers = pada_arguments(load_config("train_tiny", ["pada.object_credit_scope=numbers"]), "pada")
    assert numbers.object_credit_scope == "numbers"
    with pytest.raises(ValueError, match=r"scope must be one of \['line', 'numbers'\], got 'box'"):
        pada_arguments(load_config("train_tiny", ["pada.object_credit_scope=box"]), "pada")
