"""Size bands: a penetration-only reward pays for flattening objects; ``reward.size_per_cm`` takes it back."""

from __future__ import annotations

import numpy as np
import pytest

from physcene.assets import CATEGORY_PRIORS, SIZE_SIGMA_FLOOR, canonical_category
from physcene.ctrc import completion_text, parse
from physcene.reward import (
    ChargeConfig,
    PhysicsReward,
    RewardConfig,
    object_terms_checked,
    size_outside_band_cm,
)
from physcene.scene import TABLE


def test_band_is_the_judges_tolerance_around_the_prior_mean_in_any_orientation():
    book = CATEGORY_PRIORS["book"]
    low, high = book.band_cm(1.0)
    _, mean, sigma = book.aligned(book.mean_cm)
    assert np.all(sigma >= SIZE_SIGMA_FLOOR)
    assert np.allclose(low, mean * np.exp(-sigma)) and np.allclose(high, mean * np.exp(sigma))
    assert book.outside_band_cm(book.mean_cm, 1.0) == 0.0
    w, d, h = book.mean_cm
    assert book.outside_band_cm((h, w, d), 1.0) == 0.0  # a book on its side is still a book
    thin = (w, d, 0.25 * h)
    assert book.outside_band_cm(thin, 1.0) == pytest.approx(float(low.min()) - 0.25 * h)
    assert book.outside_band_cm(thin, 2.0) < book.outside_band_cm(thin, 1.0)
    assert canonical_category("Coffee Mug") == "mug"


@pytest.fixture(scope="module")
def scenes(written_into):
    """A clean level-2 test scene; the same with its last table-level object written into its first;
    and that colliding scene with every table-level object flattened to 1/2 and 1/4 of its height."""
    clean, colliding = written_into(3.0)

    def flattened(f):
        return colliding.with_objects(
            o.moved(size=(*o.size[:2], f * o.size[2]), center=(*o.center[:2], f * o.center[2]))
            if o.parent == TABLE else o for o in colliding.objects)

    return [clean, colliding, flattened(0.5), flattened(0.25)]


def test_penetration_only_reward_pays_for_flattening_and_the_size_term_takes_it_back(scenes):
    texts = [completion_text(s, decimals=2) for s in scenes]
    plain = PhysicsReward(RewardConfig())
    scored = plain.score(texts)
    paper = scored.rewards
    assert "mean_size_outside_cm" not in scored.metrics  # per-object host work, only when asked
    assert paper[0] == 50.0
    assert paper[1] < paper[2] < paper[3] < 0  # the hack: the flatter, the shallower, the better
    sized = PhysicsReward(RewardConfig(size_per_cm=2.0))
    scored = sized.score(texts)
    guarded = scored.rewards
    assert guarded[0] == 50.0 and guarded[1] == paper[1]  # the test data's sizes lie in their bands
    assert guarded[1] > guarded[2] > guarded[3] >= -RewardConfig().max_penalty
    # the charge is the penalty per cm times the summed distance outside the bands, read from the text
    outside = [sum(CATEGORY_PRIORS[canonical_category(o.category)].outside_band_cm(o.size, 2.0)
                   for o in parse(t).objects if canonical_category(o.category) in CATEGORY_PRIORS)
               for t in texts]
    assert outside[0] == outside[1] == 0.0 and outside[3] > outside[2] > 0
    assert guarded[2] == pytest.approx(paper[2] - 2.0 * outside[2], abs=1e-3)
    assert scored.metrics["mean_size_outside_cm"] == pytest.approx(np.mean(outside), abs=1e-3)
    # the same from parsed scenes (the Python packer) as from the compiled scanner
    assert sized.score_parsed([parse(t) for t in texts]).rewards.tolist() == pytest.approx(guarded.tolist(),
                                                                                            abs=1e-3)


def test_size_is_an_object_credit_term_and_denoising_sees_placement_only(scenes):
    texts = [completion_text(s, decimals=2) for s in scenes]
    reward = PhysicsReward(RewardConfig(), charges=ChargeConfig(terms=("penetration", "size")))
    scored = reward.score(texts)
    pen = PhysicsReward(RewardConfig(), charges=ChargeConfig()).score(texts)
    batch = reward.engine.pack([parse(t) for t in texts])
    size_cm = size_outside_band_cm(batch, RewardConfig().size_tolerance)
    charges = zip(scored.object_charges, scored.placement_charges, pen.object_charges)
    for k, (both, placement, only_pen) in enumerate(charges):
        n = len(scenes[k].objects)
        assert np.allclose(placement, only_pen, atol=1e-4)
        assert np.allclose(both, only_pen + size_cm[k, :n], atol=1e-4)
    assert not size_cm[:2].any() and size_cm[3].sum() > size_cm[2].sum() > 0
    # the paper's penetration charge on the written-in object shrinks with its height: the hack, per object
    moved = len(scenes[1].objects) - 1 - [o.parent for o in reversed(scenes[1].objects)].index(TABLE)
    depth = [float(d[moved]) for d in pen.object_charges[1:]]
    assert depth[0] > depth[1] > depth[2] > 0
    assert object_terms_checked(["size"]) == ("size",)


def test_reward_overrides_reach_the_pada_reward_and_bad_keys_are_named():
    from physcene.reward.trl import PhysicsRewardFunction

    fn = PhysicsRewardFunction("cpu", overrides=["size_per_cm=2.0", "size_tolerance=1.5"])
    assert fn.reward.config.size_per_cm == 2.0 and fn.reward.config.size_tolerance == 1.5
    with pytest.raises(Exception, match="size_per_centimetre"):
        PhysicsRewardFunction("cpu", overrides=["size_per_centimetre=2.0"])


def test_pada_denoising_targets_are_built_from_the_placement_charges(scenes, monkeypatch, generated):
    """With ``size`` among the credit terms, a denoising target must not move an object for its size."""
    from types import SimpleNamespace

    import physcene.train.denoise as denoise
    from physcene.train.object_credit import ChargedReward
    from physcene.train.tokenizer import build_tokenizer

    texts = [completion_text(s, decimals=2) for s in scenes[1:3]]  # colliding; colliding and flattened
    reward = PhysicsReward(RewardConfig(), charges=ChargeConfig(terms=("penetration", "size")))
    scored = reward.score(texts)
    assert not np.allclose(scored.object_charges[1], scored.placement_charges[1])
    seen = []
    monkeypatch.setattr(denoise, "denoise_targets",
                        lambda t, charges, **kw: seen.append(charges) or [None] * len(t))
    tokenizer = build_tokenizer(texts, vocab_size=320)
    output = generated(tokenizer, texts)
    charged = ChargedReward(reward, reward.charges)
    charged.keep(scored)
    trainer = SimpleNamespace(_tokenizer=tokenizer, max_completion_length=10_000, log_value=lambda k, v: None)
    denoise.Denoise(charged, 1.0, tto=None, margin_cm=1.0, decimals=2).after_scoring(trainer, [], output)
    assert seen and seen[0] is scored.placement_charges


def test_a_pair_count_charge_does_not_fall_when_the_objects_are_written_thinner(scenes):
    texts = [completion_text(s, decimals=2) for s in scenes[1:]]
    moved = len(scenes[1].objects) - 1 - [o.parent for o in reversed(scenes[1].objects)].index(TABLE)
    by_depth = PhysicsReward(RewardConfig(), charges=ChargeConfig()).score(texts)
    by_pairs = PhysicsReward(RewardConfig(), charges=ChargeConfig(penetration="pairs")).score(texts)
    # the charge is PADA's credit; the reward is the paper's
    assert by_pairs.rewards.tolist() == by_depth.rewards.tolist()
    depth = [float(d[moved]) for d in by_depth.object_charges]
    pairs = [d[moved] for d in by_pairs.object_charges]
    assert depth[0] > depth[1] > depth[2] > 0
    assert pairs == [1.0, 1.0, 1.0]
    assert all(set(np.flatnonzero(a)) == set(np.flatnonzero(b))  # the same objects blamed
               for a, b in zip(by_depth.object_charges, by_pairs.object_charges))
    with pytest.raises(ValueError, match=r"must be one of \['depth', 'pairs'\], got 'area'"):
        ChargeConfig(penetration="area")


def test_pada_takes_the_penetration_charge_from_its_config():
    from physcene.config import load_config
    from physcene.train.pada import pada_arguments

    assert pada_arguments(load_config("train_tiny"), "pada").object_credit_penetration == "depth"
    pairs = pada_arguments(load_config("train_tiny", ["pada.object_credit_penetration=pairs"]), "pada")
    assert pairs.object_credit_penetration == "pairs"
    with pytest.raises(ValueError, match="pada.object_credit_penetration: penetration charge must be one of"):
        pada_arguments(load_config("train_tiny", ["pada.object_credit_penetration=volume"]), "pada")
