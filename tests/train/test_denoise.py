"""``pada.denoise`` (not in the paper): each rollout the reward blamed objects in is repaired by TTO with
only those objects free, their numbers are rewritten in the rollout's own text, and PADA adds the
cross-entropy of the rewritten numbers given the rollout's prefix."""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from shapely.geometry import Polygon

from physcene.ctrc import completion_text, decimals_of, parse, usual_decimals
from physcene.reward import ChargeConfig, PhysicsReward, RewardConfig
from physcene.scene import TABLE, ZONE_TOLERANCE_CM, zone_overshoot
from physcene.train.denoise import Denoise, _place_table_level, denoise_targets, free_spot, rewrite_boxes
from physcene.train.object_credit import ChargedReward
from physcene.train.targets import object_line_spans, tokenize_target
from physcene.train.tokenizer import build_tokenizer
from physcene.tto import TTOConfig

TTO = TTOConfig.load(["lambda_zone=100.0", "report_relations=false"])


@pytest.fixture(scope="module")
def texts(written_into):
    """A clean level-2 test scene as CTRC, and the same with its last table-level object written 1 cm
    beside its first one (a collision the reward charges to the later-written object)."""
    clean, moved = written_into(1.0)
    return completion_text(clean, decimals=2), completion_text(moved, decimals=2)


@pytest.fixture(scope="module")
def reward():
    return PhysicsReward(RewardConfig(device="cpu"), charges=ChargeConfig())


@pytest.fixture(scope="module")
def targets(texts, reward):
    clean, moved = texts
    charges = reward.score([clean, moved, "not a layout"]).object_charges
    return charges, denoise_targets([clean, moved, "not a layout"], charges, config=TTO, engine=reward.engine)


def test_only_the_blamed_object_moves_and_the_repair_is_collision_free(texts, reward, targets):
    charges, out = targets
    assert out[0] is None and out[2] is None  # nothing blamed / not parsed
    target = out[1]
    before, after = parse(texts[1]), parse(target.text)
    blamed = [o.instance_id for o, c in zip(before.objects, charges[1]) if c > 0]
    assert target.moved == blamed and len(blamed) == 1
    for a, b in zip(before.objects, after.objects):  # every other object exactly as the rollout wrote it
        if a.instance_id not in blamed:
            assert np.allclose([*a.center, a.yaw], [*b.center, b.yaw], atol=1e-4)
            assert a.size == pytest.approx(b.size, abs=1e-4)
    assert reward.score([target.text]).rewards.tolist() == [50.0]  # the rewritten text scores collision-free
    assert target.depth_before > 0 and target.depth_after == 0.0
    moved = after.get(blamed[0])
    assert moved.size == pytest.approx(before.get(blamed[0]).size, abs=0.02)  # the margin is shrunk back
    past = zone_overshoot(np.array(moved.center[:2]), np.array(moved.size[:2]), np.array(moved.yaw),
                          np.array(after.zone.to_list()))
    assert past <= ZONE_TOLERANCE_CM


def test_the_repair_keeps_the_margin_to_its_neighbours(texts, reward):
    """With a 1.5 cm margin the moved object's footprint, grown by 1 cm, still touches nothing."""
    clean, moved = texts
    charges = reward.score([moved]).object_charges
    target = denoise_targets([moved], charges, config=TTO, engine=reward.engine, margin_cm=1.5)[0]
    after = parse(target.text)
    blamed = after.get(target.moved[0])
    grown = after.with_objects(o.moved(size=(o.size[0] + 2.0, o.size[1] + 2.0, o.size[2]))
                               if o is blamed else o for o in after.objects)
    assert reward.score_parsed([grown]).rewards.tolist() == [50.0]


def _footprint(x, y, hw, hd, yaw) -> Polygon:
    c, s = np.cos(yaw), np.sin(yaw)
    corners = ((-hw, -hd), (hw, -hd), (hw, hd), (-hw, hd))
    return Polygon([(x + c * u - s * v, y + s * u + c * v) for u, v in corners])


def test_free_spot_is_the_nearest_clear_place_inside_the_zone():
    rng = np.random.default_rng(0)
    zone = np.array([0.0, 100.0, 0.0, 60.0])
    for _ in range(40):
        obstacles = np.column_stack([rng.uniform(10, 90, 6), rng.uniform(10, 50, 6), rng.uniform(3, 10, 6),
                                     rng.uniform(3, 10, 6), rng.uniform(-np.pi, np.pi, 6)])
        center, half, yaw = np.array([50.0, 30.0]), rng.uniform(2, 8, 2), float(rng.uniform(-np.pi, np.pi))
        spot = free_spot(center, half, yaw, obstacles, zone, step_cm=0.5)
        assert spot is not None
        box = _footprint(*spot, *half, yaw)
        assert all(box.intersection(_footprint(*o)).area < 1e-6 for o in obstacles)
        assert box.bounds[0] >= -1e-9 and box.bounds[2] <= 100 + 1e-9 and box.bounds[1] >= -1e-9
        # no grid point nearer the start is free (the grid is nearest first)
        d = np.hypot(*(spot - center))
        for dx, dy in ((0.0, 0.0), (0.5, 0.0), (0.0, -0.5)):
            p = center + (dx, dy)
            if np.hypot(dx, dy) < d - 1e-9:
                near = _footprint(*p, *half, yaw)
                assert any(near.intersection(_footprint(*o)).area > 1e-9 for o in obstacles) or not \
                    Polygon([(0, 0), (100, 0), (100, 60), (0, 60)]).contains(near)
    # a table with no room left: None
    table_sized = np.array([[50.0, 30.0, 50.0, 30.0, 0.0]])
    assert free_spot(center, np.array([30.0, 20.0]), 0.0, table_sized, zone) is None


def test_a_blamed_table_level_object_moves_with_its_subtree(texts):
    scene = parse(texts[1])
    table = [o for o in scene.objects if o.parent == TABLE]
    with_child = next((o for o in table if scene.children(o.instance_id)), None)
    assert with_child is not None, "the fixture scene has a support or container on the table"
    # put the support onto another table-level object and blame it
    other = next(o for o in table if o is not with_child)
    shift = np.subtract(other.center[:2], with_child.center[:2])
    subtree = {with_child.instance_id} | {c.instance_id for c in scene.children(with_child.instance_id)}
    moved = scene.with_objects(o.moved(center=(o.center[0] + shift[0], o.center[1] + shift[1], o.center[2]))
                               if o.instance_id in subtree else o for o in scene.objects)
    placed_scene, placed = _place_table_level(moved, {with_child.instance_id}, 1.0)
    assert placed == {with_child.instance_id}
    new = placed_scene.get(with_child.instance_id)
    step = np.subtract(new.center, moved.get(with_child.instance_id).center)
    assert np.linalg.norm(step[:2]) > 0 and step[2] == 0
    for c in scene.children(with_child.instance_id):  # the children keep their place on it
        child_step = np.subtract(placed_scene.get(c.instance_id).center, moved.get(c.instance_id).center)
        assert np.allclose(child_step, step)
    for o in placed_scene.objects:
        if o.instance_id not in subtree:
            assert o == moved.get(o.instance_id)


def test_only_the_rewritten_numbers_are_supervised(texts, targets):
    _, moved = texts
    target = targets[1][1]
    assert target.spans and all(b > a for a, b in target.spans)
    # outside the spans the text is the rollout's, character for character
    kept, pos, old = [], 0, moved
    for a, b in target.spans:
        kept.append(target.text[pos:a])
        pos = b
    kept.append(target.text[pos:])
    assert all(piece in old for piece in kept)
    # the spans are numbers of the moved object's line and parse as numbers
    line = next((a, b) for a, b in object_line_spans(target.text)
                if f'"instance_id": "{target.moved[0]}"' in target.text[a:b])
    for a, b in target.spans:
        assert line[0] <= a < b <= line[1]
        float(target.text[a:b])
    tokenizer = build_tokenizer([target.text, moved], vocab_size=320)
    ids, mask = tokenize_target(tokenizer, target.text, target.spans, max_length=10_000)
    assert ids[-1] == tokenizer.eos_token_id and len(ids) == len(mask)
    offsets = tokenizer(target.text, add_special_tokens=False, return_offsets_mapping=True)["offset_mapping"]
    for t, (s, e) in enumerate(offsets):
        over = any(s < b and a < e for a, b in target.spans)
        assert mask[t] == int(over)
    assert mask[-1] == 0  # the EOS is the rollout's, not a rewritten number
    assert 0 < sum(mask) < len(mask)


def test_rewrite_boxes_keeps_numbers_within_their_last_decimal(texts):
    _, moved = texts
    scene = parse(moved)
    same, spans = rewrite_boxes(moved, scene, set(scene.ids()), 2)
    assert spans == [] and same == moved
    with pytest.raises(ValueError, match="object lines"):
        rewrite_boxes(moved, scene.with_objects(scene.objects[:-1]), set(), 2)


def test_targets_keep_the_rollouts_usual_precision_not_its_longest_number(texts, reward):
    """One stray long number in a rollout (here in an object the reward does not blame) must not set
    the precision of the rewritten ones: targets made that way taught eight-decimal numbers."""
    _, moved = texts
    first = re.search(r'"relative_bbox": \[(-?\d+\.\d+)', moved)
    stray = moved[:first.end(1)] + "3141" + moved[first.end(1):]
    assert decimals_of(stray) >= 5 and usual_decimals(stray) == 2 == usual_decimals(moved)
    charges = reward.score([stray]).object_charges
    for decimals, most in ((None, 2), (1, 1)):
        target = denoise_targets([stray], charges, config=TTO, engine=reward.engine, decimals=decimals)[0]
        assert target is not None and target.spans
        for a, b in target.spans:
            number = target.text[a:b]
            assert len(number.partition(".")[2].rstrip("0")) <= most, number
    assert usual_decimals("no layout") == 0


def test_denoise_targets_checks_its_inputs(texts):
    with pytest.raises(ValueError, match="2 completions but 1 charges"):
        denoise_targets(list(texts), [None])


def test_pada_builds_denoise_rows_aligned_with_the_rollouts(texts, reward, generated):
    clean, moved = texts
    tokenizer = build_tokenizer([clean, moved], vocab_size=320)
    output = generated(tokenizer, [moved, clean])
    scored = reward.score([moved, clean])
    logged = {}
    charged = ChargedReward(reward, reward.charges)
    charged.keep(scored)
    trainer = SimpleNamespace(_tokenizer=tokenizer, max_completion_length=10_000,
                              log_value=lambda k, v: logged.__setitem__(k, v))
    Denoise(charged, 1.0, tto=TTO, margin_cm=1.0, decimals=2).after_scoring(trainer, [], output)
    assert output["denoise_ids"].shape[0] == 2
    assert output["denoise_loss_mask"][0].sum() > 0 and output["denoise_loss_mask"][1].sum() == 0
    assert output["denoise_attention_mask"][1].sum() == 0  # no target: an empty row
    assert logged["denoise/rows_frac"] == 0.5 and 0 < logged["denoise/token_frac"] < 0.1
    assert logged["denoise/depth_after_cm"] < logged["denoise/depth_before_cm"]
    assert logged["denoise/collision_free_frac"] == 1.0
    text = tokenizer.decode(output["denoise_ids"][0][output["denoise_attention_mask"][0].bool()],
                            skip_special_tokens=True)
    assert reward.score([text]).rewards.tolist() == [50.0]


def test_pada_with_denoise_trains_and_logs_it(tmp_path, monkeypatch):
    """``pada.denoise`` through TRL on the tiny model: the targets travel with the rollouts through TRL's
    shuffle and split, the loss gets the denoising term, and a negative weight is refused.

    The tiny model's 16-token completions never parse, so the targets are stood in for: each rollout's
    own text with its first characters supervised (the real targets are tested above)."""
    from test_train_pipeline import _sft_for_pada

    import physcene.train.denoise as denoise
    from physcene.config import load_config
    from physcene.train.pada import run_pada

    torch.set_num_threads(1)
    cfg = _sft_for_pada(tmp_path, 4, 4, "pada.max_steps=2", "pada.denoise=1.0")

    def stand_in(texts, charges, **kwargs):
        assert len(texts) == len(charges) and kwargs["margin_cm"] == 1.0
        return [denoise.DenoiseTarget(t, [(0, min(4, len(t)))], [], 1.0, 0.0) if t else None for t in texts]

    monkeypatch.setattr(denoise, "denoise_targets", stand_in)
    losses = []
    original = Denoise.loss

    def spy(self, trainer, model, inputs):
        loss = original(self, trainer, model, inputs)
        assert loss.requires_grad
        losses.append(float(loss.detach()))
        return loss

    monkeypatch.setattr(Denoise, "loss", spy)
    out = run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")))
    assert losses and all(np.isfinite(x) and x > 0 for x in losses)
    log = json.loads((out / "train_log.json").read_text())
    assert any(e.get("denoise/rows_frac", 0) > 0 and "denoise/nll" in e for e in log)
    assert json.loads((out / "physcene_run.json").read_text())["steps"] == 2
    with pytest.raises(ValueError, match="pada.denoise"):
        run_pada(load_config("train_tiny", [f"output_dir={tmp_path / 'neg'}", "pada.denoise=-1"]),
                 variant="pada")


def test_offline_check_supervises_the_rewritten_numbers_and_reads_the_originals(texts, targets):
    """physcene.train.analysis.denoise_offline: the rows it trains on supervise the rewritten numbers, and the
    held-out comparison reads the numbers they replaced in the original text."""
    from physcene.train.analysis import denoise_offline as offline

    _, moved = texts
    target = targets[1][1]
    old_spans = offline._original_spans(moved, target)
    assert len(old_spans) == len(target.spans)
    rebuilt, pos = [], 0  # putting the target's numbers back into the original gives the target
    for (a, b), (c, d) in zip(old_spans, target.spans):
        float(moved[a:b])
        rebuilt += [moved[pos:a], target.text[c:d]]
        pos = b
    assert "".join(rebuilt + [moved[pos:]]) == target.text
    tokenizer = build_tokenizer([target.text, moved], vocab_size=320)
    record = {"prompt": "Arrange the table.", "sft_completion": moved}
    (row,) = offline.supervised_rows(tokenizer, [record, dict(record)], [target, None])
    assert row["mask"][-1] == 1 and row["old_mask"][-1] == 1  # cut after the last supervised token
    assert sum(row["mask"]) > 0 and sum(row["old_mask"]) > 0
    assert tokenizer.decode(row["ids"]) == target.text[:len(tokenizer.decode(row["ids"]))]


def test_denoise_settings_are_checked():
    from physcene.config import load_config
    from physcene.train.pada import pada_arguments

    args = pada_arguments(load_config("train_tiny", ["pada.denoise=1.0", "pada.denoise_decimals=2"]), "pada")
    assert args.denoise == 1.0 and args.denoise_decimals == 2
    assert pada_arguments(load_config("train_tiny", []), "pada").denoise_decimals is None
    for bad in ("9", "-1", "1.5", "true"):
        with pytest.raises(ValueError, match="pada.denoise_decimals must be null or an integer from 0 to 8"):
            pada_arguments(load_config("train_tiny", [f"pada.denoise_decimals={bad}"]), "pada")
    with pytest.raises(ValueError, match="pada.denoise and pada.denoise_margin_cm must be >= 0"):
        pada_arguments(load_config("train_tiny", ["pada.denoise_margin_cm=-1"]), "pada")
