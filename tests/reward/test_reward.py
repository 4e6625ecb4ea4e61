"""The paper's physics reward as a TRL reward function."""

from __future__ import annotations

import numpy as np
import pytest

from physcene.assets import AssetLibrary
from physcene.ctrc import completion_text
from physcene.physics import PhysicsEngine
from physcene.reward import (
    PhysicsReward,
    RewardConfig,
    completion_text_of,
    physics_reward,
    reward_for_device,
    reward_from_energy,
)
from physcene.scene import Scene, SceneObject, Zone

ZONE = Zone(0.0, 120.0, 0.0, 60.0)


class CountingEngine:
    """The real engine, counting calls (the reward must make one per batch). It packs Scenes only:
    the rewards given it read texts with ``fast_parse=False``."""

    def __init__(self):
        library = AssetLibrary(resolution=32, n_points=512)
        library.add_primitives()
        self.inner = PhysicsEngine(library)
        self.packs = 0
        self.evaluations = 0

    def pack(self, scenes):
        self.packs += 1
        return self.inner.pack(scenes)

    def evaluate(self, batch, poses=None, **kw):
        self.evaluations += 1
        return self.inner.evaluate(batch, poses, **kw)


@pytest.fixture()
def engine():
    return CountingEngine()


def text(*objects) -> str:
    return completion_text(Scene(ZONE, objects))


def box(name, center, size, yaw=0.0):
    return SceneObject(name, "box", center, size, yaw)


CLEAN = text(box("1_box_0", (30, 30, 5), (10, 10, 10)), box("2_box_1", (60, 30, 5), (10, 10, 10)))
# the second box overlaps the first by 2 cm along x: E_pen = 20 mm
OVERLAP = text(box("1_box_0", (30, 30, 5), (10, 10, 10)), box("2_box_1", (38, 30, 5), (10, 10, 10)))
SUNK = text(box("1_box_0", (30, 30, 4), (10, 10, 10)))  # 1 cm below the table top


def test_reward_values_and_one_engine_call(engine):
    reward = PhysicsReward(RewardConfig(fast_parse=False), engine=engine)
    chat = [{"role": "assistant", "content": OVERLAP}]
    rewards = reward(["p"] * 4, [CLEAN, OVERLAP, "I cannot do that.", chat])
    assert rewards[0] == 50.0 and rewards[2] == -100.0
    assert rewards[1] == pytest.approx(-0.2, abs=2e-3) and rewards[3] == rewards[1]
    assert engine.packs == 1 and engine.evaluations == 1
    batch = reward.score([CLEAN, OVERLAP, "I cannot do that.", OVERLAP])
    assert batch.rewards.tolist() == rewards and engine.packs == 2 and engine.evaluations == 2
    m = batch.metrics
    assert m["parse_failure_rate"] == 0.25
    assert m["mean_energy_mm"] == pytest.approx(40 / 3, abs=0.1)
    assert m["collision_free_rate"] == pytest.approx(1 / 3)
    assert batch.parse_errors[2] is not None and batch.parse_errors[0] is None


def test_unparsable_batch_never_touches_the_engine(engine):
    reward = PhysicsReward(RewardConfig(fast_parse=False), engine=engine)
    batch = reward.score(["", "{not json", '{"objects": []}'])
    assert batch.rewards.tolist() == [-100.0] * 3
    assert engine.packs == 0 and engine.evaluations == 0
    assert batch.metrics["parse_failure_rate"] == 1.0


def test_tolerance_and_table_term(engine):
    slow = {"fast_parse": False}
    assert PhysicsReward(RewardConfig(tolerance_mm=25.0, **slow), engine=engine)(None, [OVERLAP]) == [50.0]
    assert PhysicsReward(RewardConfig(tolerance_mm=15.0, **slow), engine=engine)(None, [OVERLAP])[0] < 0
    assert PhysicsReward(RewardConfig(fast_parse=False), engine=engine)(None, [SUNK]) == [50.0]
    sunk = PhysicsReward(RewardConfig(table_term=True, **slow), engine=engine)(None, [SUNK])[0]
    assert sunk == pytest.approx(-0.1, abs=1e-3)


def test_penalty_is_capped():
    cfg = RewardConfig()
    got = reward_from_energy(np.array([0.0, 1e-3, 100.0, 4999.0, 5000.0, 1e9]), cfg)
    assert got.tolist() == pytest.approx([50.0, -1e-5, -1.0, -49.99, -50.0, -50.0])


def test_completion_formats():
    assert completion_text_of("abc") == "abc"
    assert completion_text_of([{"role": "assistant", "content": "abc"}]) == "abc"
    assert completion_text_of([{"role": "assistant", "content": [{"type": "text", "text": "a"}]}]) == "a"
    turns = [{"role": "user", "content": "x"}, {"role": "assistant", "content": "y"}]
    assert completion_text_of(turns) == "y"


def test_module_level_function_uses_the_config_and_device():
    rewards = physics_reward(["p", "p"], [CLEAN, "nope"], device="cpu", extra_column=[1, 2])
    assert rewards == [50.0, -100.0]
    assert reward_for_device("cpu").score([CLEAN, "nope"]).metrics["parse_failure_rate"] == 0.5
    assert RewardConfig.load(["tolerance_mm=2"]).tolerance_mm == 2.0
    with pytest.raises(ValueError, match="unknown keys"):
        RewardConfig.load(["bogus=1"])


@pytest.mark.parametrize("fast_parse", [True, False])
def test_resting_contacts_written_as_text_are_not_penetration(fast_parse):
    """An `on` child written at relative zmin 0 rests on its support: exact contact read as float32
    noise (1e-7-1e-6 cm) and, at the paper's 0 cm threshold, took a repaired stack's +50 away — 14
    of these 20 stacked scenes before ctrc.ON_CONTACT_GAP_CM. Both parse paths decode alike."""
    from physcene.data.noisy import noisy_scenes
    from physcene.graph import ensure_hierarchy
    from physcene.tto import TTOConfig, repair

    engine = PhysicsEngine()
    results = repair(noisy_scenes(24, 8, seed=5, push_cm=3.0), TTOConfig.load(["steps=60"]), engine)
    assert all(r.report.collision_free for r in results)
    stacked = [ensure_hierarchy(r.scene) for r in results]
    stacked = [s for s in stacked if any(o.relation == "on" for o in s.objects)]
    assert len(stacked) >= 16
    reward = PhysicsReward(RewardConfig(fast_parse=fast_parse), engine=engine)
    texts = [completion_text(s, decimals=2) for s in stacked]
    assert reward.score(texts).rewards.tolist() == [50.0] * len(stacked)
