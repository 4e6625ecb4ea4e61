"""``reward.valid_terms``: the paper's reward pays a collision dodged by lifting an object off its support
or by flattening it; with the terms on, such a layout is paid ``invalid`` (docs/results.md)."""

from __future__ import annotations

import numpy as np
import pytest

from physcene.assets import CATEGORY_PRIORS, canonical_category
from physcene.config import ConfigError
from physcene.ctrc import completion_text, parse
from physcene.reward import PhysicsReward, RewardConfig, band_low_ratio
from physcene.scene import TABLE


def _subtree(scene, root_id):
    """Ids of ``root_id`` and every object resting in or on it, at any depth."""
    ids = {root_id}
    grew = True
    while grew:
        more = {o.instance_id for o in scene.objects if o.parent in ids} - ids
        ids |= more
        grew = bool(more)
    return ids


@pytest.fixture(scope="module")
def scenes(written_into):
    """clean; colliding (the last table-level object written into the first); the colliding object
    lifted with what it carries to 10 cm above every other object's top (out of the collision,
    floating); and instead flattened to 1/100 of its height on the table (a collision 1/100 as deep)."""
    clean, colliding = written_into(3.0)
    last = [o for o in colliding.objects if o.parent == TABLE][-1]
    carried = _subtree(colliding, last.instance_id)
    dz = max(o.zmax for o in colliding.objects if o.instance_id not in carried) + 10.0 - last.zmin
    lifted = colliding.with_objects(
        o.moved(center=(*o.center[:2], o.center[2] + dz)) if o.instance_id in carried else o
        for o in colliding.objects)
    h = last.size[2] / 100.0
    flat = colliding.with_objects(
        o.moved(size=(*o.size[:2], h), center=(*o.center[:2], h / 2.0)) if o is last else o
        for o in colliding.objects if o is last or o.instance_id not in carried)
    return [clean, colliding, lifted, flat]


def test_the_papers_reward_pays_for_lifting_and_flattening_and_valid_terms_take_it_back(scenes):
    texts = [completion_text(s, decimals=2) for s in scenes]
    paper = PhysicsReward(RewardConfig()).score(texts).rewards
    assert paper[0] == 50.0 and paper[1] < 0
    assert paper[2] == 50.0  # lifted out of the collision: paid as collision-free
    assert paper[1] < paper[3] <= 50.0  # flattened: a shallower collision, paid better

    floating = PhysicsReward(RewardConfig(valid_terms=("floating",)))
    scored = floating.score(texts)
    got = scored.rewards
    assert got[0] == 50.0 and got[1] == paper[1] and got[3] == paper[3]
    assert got[2] == RewardConfig().invalid == -50.0
    assert scored.metrics["invalid_rate"] == pytest.approx(0.25)
    assert scored.metrics["mean_floating_objects"] == pytest.approx(1 / 4)  # only its base floats

    both = PhysicsReward(RewardConfig(valid_terms=("floating", "shrunk"), invalid=-60.0))
    scored = both.score(texts)
    got = scored.rewards
    assert got[0] == 50.0 and got[1] == paper[1]
    assert got[2] == got[3] == -60.0
    assert scored.metrics["mean_shrunk_objects"] == pytest.approx(1 / 4)
    # the same from parsed scenes (the Python packer) as from the compiled scanner
    assert both.score_parsed([parse(t) for t in texts]).rewards.tolist() == pytest.approx(got.tolist())
    # the test data's objects are neither lifted nor shrunk: the terms never touch its clean scenes
    assert both.broken_objects(both.engine.pack([scenes[0]]))["shrunk"].sum() == 0


def test_low_ratio_reads_the_band_in_any_orientation(scenes):
    book = CATEGORY_PRIORS["book"]
    low, _ = book.band_cm(2.0)
    w, d, h = book.mean_cm
    assert book.low_ratio((w, d, h), 2.0) > 1.0 and book.low_ratio((h, w, d), 2.0) > 1.0
    assert book.low_ratio((w, d, 0.01), 2.0) == pytest.approx(0.01 / low.min())
    # the reward's batched form gives each object's own figure (inf without a prior, on padded slots)
    batch = PhysicsReward(RewardConfig()).engine.pack(scenes)
    ratio = band_low_ratio(batch, 2.0)
    for s, scene in enumerate(scenes):
        for k, o in enumerate(scene.objects):
            prior = CATEGORY_PRIORS.get(canonical_category(o.category))
            expected = np.inf if prior is None else prior.low_ratio(batch.sizes[s, k].numpy(), 2.0)
            assert ratio[s, k] == pytest.approx(expected)
        assert np.isinf(ratio[s, len(scene.objects):]).all()
    assert ratio[3].min() < 0.5 <= ratio[0].min()  # the flattened object, and none in the clean scene


def test_valid_terms_from_the_config_and_bad_ones_are_named():
    from physcene.reward.trl import PhysicsRewardFunction

    assert RewardConfig.load().valid_terms == ()  # the paper's reward by default
    assert RewardConfig.load(["valid_terms=floating"]).valid_terms == ("floating",)  # one name, not letters
    fn = PhysicsRewardFunction("cpu", overrides=["valid_terms=[floating,shrunk]", "shrink_ratio=0.4"])
    assert fn.reward.config.valid_terms == ("floating", "shrunk") and fn.reward.config.shrink_ratio == 0.4
    with pytest.raises(ConfigError, match=r"reward.yaml: valid terms .*got \['float'\]"):
        RewardConfig.load(["valid_terms=[float]"])
    with pytest.raises(ValueError, match="distinct"):
        RewardConfig(valid_terms=("floating", "floating"))


def test_pada_logs_what_the_valid_terms_charged(scenes):
    from physcene.reward.trl import PhysicsRewardFunction

    logged = {}
    fn = PhysicsRewardFunction("cpu", overrides=["valid_terms=[floating,shrunk]"])
    rewards = fn(None, [completion_text(s, decimals=2) for s in scenes],
                 log_metric=lambda k, v: logged.__setitem__(k, v))
    assert rewards[2] == rewards[3] == -50.0
    assert logged["invalid_rate"] == pytest.approx(0.5)
    assert logged["floating_objects"] == pytest.approx(0.25)
    assert logged["shrunk_objects"] == pytest.approx(0.25)
    plain = {}
    PhysicsRewardFunction("cpu")(None, [completion_text(scenes[0], decimals=2)],
                                 log_metric=lambda k, v: plain.__setitem__(k, v))
    assert "invalid_rate" not in plain and "floating_objects" not in plain
