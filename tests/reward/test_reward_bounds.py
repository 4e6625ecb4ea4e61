"""The reward's bounds: over-limit and pathological completions score −100 or a bounded reward, in
bounded time, on both parse paths (the compiled scanner and the Python parser)."""

from __future__ import annotations

import json
import random
import time

import numpy as np
import pytest

from physcene.ctrc import LAYOUT_HEADER, MAX_CHARS
from physcene.data import synthesize
from physcene.reward import PhysicsReward, RewardConfig
from physcene.scene import TABLE


@pytest.fixture(scope="module")
def rewards():
    fast = PhysicsReward(RewardConfig(device="cpu"))
    return fast, PhysicsReward(RewardConfig(device="cpu", fast_parse=False), engine=fast.engine)


@pytest.fixture(scope="module")
def completions():
    return [r["completion"] for r in synthesize("test", n=6, seed=0)]


def stacked(n: int) -> str:
    """A valid completion of ``n`` boxes written at one spot (each a table-level object), the layout
    alone (no plan): about 85 bytes an object."""
    entries = [{"layer": 1, "instance_id": f"b{k}", "category": "box", "parent_id": TABLE,
                "relation_type": "near", "relative_bbox": [55.0, 65.0, 25.0, 35.0, 0.0, 10.0]}
               for k in range(n)]
    layout = {"objects": [{"layer": 0, "instance_id": TABLE, "type": "zone", "bbox": [0, 120, 0, 60, 0, 0]},
                          *entries], "item_placement_zone": [0.0, 120.0, 0.0, 60.0]}
    return LAYOUT_HEADER + "\n" + json.dumps(layout, separators=(",", ":"))


def both(rewards, texts):
    fast, python = rewards
    a, b = fast.score(texts), python.score(texts)
    assert np.array_equal(a.rewards, b.rewards)
    return a


def test_a_text_over_the_length_limit_is_unparsable_on_both_paths(rewards, completions):
    text = completions[0]
    long = text.replace('"description": "', '"description": "' + "x" * 299, 1)
    padded = text + " " * (MAX_CHARS + 1 - len(text))
    assert len(padded) > MAX_CHARS
    batch = both(rewards, [padded, text])
    assert batch.rewards[0] == -100.0 and "exceeds" in batch.parse_errors[0]
    assert batch.rewards[1] > -100.0
    assert len(long) < MAX_CHARS


def test_a_thousand_stacked_objects_are_refused_in_bounded_time(rewards):
    text = stacked(999)
    assert 60_000 < len(text) < MAX_CHARS, len(text)
    for reward in rewards:
        start = time.perf_counter()
        batch = reward.score([text])
        assert time.perf_counter() - start < 5.0
        assert batch.rewards[0] == -100.0 and "pairs of objects overlap" in batch.parse_errors[0]
    few = both(rewards, [stacked(40)])  # under the bound: scored, and colliding
    assert -100.0 < few.rewards[0] < 0.0


def test_mutated_completions_get_a_bounded_reward_on_both_paths(rewards, completions):
    rng = random.Random(30)
    texts = []
    for _ in range(300):
        text = rng.choice(completions)
        cut = rng.randrange(len(text))
        op = rng.randrange(4)
        if op == 0:
            text = text[:cut] + text[cut + rng.randrange(1, 40):]
        elif op == 1:
            text = text[:cut] + text[cut:cut + rng.randrange(1, 200)] * 2 + text[cut:]
        elif op == 2:
            text = text[:cut] + rng.choice(['"', "]", "}", ",", "1e309", "-", "NaN", "\\u0000"]) + text[cut:]
        else:
            text = text.replace("relative_bbox", rng.choice(["bbox", "relative_box", "relative_bbox"]), 1)
        texts.append(text)
    start = time.perf_counter()
    batch = both(rewards, texts)
    assert time.perf_counter() - start < 60.0
    assert np.isfinite(batch.rewards).all()
    assert (batch.rewards >= -100.0).all() and (batch.rewards <= 50.0).all()
    assert all((r == -100.0) == (e is not None) for r, e in zip(batch.rewards, batch.parse_errors))
