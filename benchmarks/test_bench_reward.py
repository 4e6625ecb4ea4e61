"""Engine and reward throughput (issue 4), CPU always and CUDA when present.

    python -m pytest benchmarks/test_bench_reward.py --benchmark-enable -q
    physcene bench reward --device cuda          # the same figures as one report (Gq/s, ratios)

Sizes: 512 scenes x 16 objects x 1024 points on CUDA (the issue's), 64 x 12 x 1024 on CPU. With
``--benchmark-enable`` the CPU reward case asserts the issue's >= 500 scenes/s on 12-object scenes.
"""

from __future__ import annotations

import pytest
import torch
from conftest import synchronized

from physcene.assets import AssetLibrary
from physcene.commands.bench import bench_scenes
from physcene.ctrc import completion_text
from physcene.physics import PhysicsEngine
from physcene.physics.reference import reference_penetration
from physcene.reward import PhysicsReward, RewardConfig, TextPacker


def _sizes(device: torch.device) -> tuple[int, int]:
    return (512, 16) if device.type == "cuda" else (64, 12)


def _engine(device: torch.device) -> PhysicsEngine:
    library = AssetLibrary(resolution=64, n_points=1024)
    library.add_primitives()
    return PhysicsEngine(library, device)


@pytest.fixture()
def setup(bench_device):
    engine = _engine(bench_device)
    scenes = bench_scenes(*_sizes(bench_device))
    batch = engine.pack(scenes)
    engine.evaluate(batch, with_grad=True)  # JIT, asset upload
    return bench_device, engine, scenes, batch


@pytest.mark.parametrize("with_grad", [False, True], ids=["forward", "forward+grad"])
def test_bench_engine(benchmark, setup, with_grad):
    device, engine, scenes, batch = setup
    out = benchmark.pedantic(synchronized(lambda: engine.evaluate(batch, with_grad=with_grad), device),
                             rounds=20 if device.type == "cuda" else 3, iterations=1, warmup_rounds=1)
    assert out["energy"].shape == (len(scenes),)
    benchmark.extra_info.update(scenes=len(scenes), objects=len(scenes[0].objects), device=str(device))


@pytest.mark.parametrize("with_grad", [False, True], ids=["forward", "forward+grad"])
def test_bench_reference(benchmark, setup, with_grad):
    device, engine, scenes, batch = setup
    kw = dict(poses=batch.poses, sizes=batch.sizes, count=batch.count, obj_asset=batch.asset_index,
              assets=engine.packed_assets(), margin=engine.config.margin_cm, with_grad=with_grad,
              depth_cap_ratio=engine.config.depth_cap_ratio)
    out = benchmark.pedantic(synchronized(lambda: reference_penetration(**kw), device), rounds=2,
                             iterations=1, warmup_rounds=0)
    assert out["energy"].shape == (len(scenes),)


@pytest.mark.parametrize("fast_parse", [True, False], ids=["fast-parse", "python-parse"])
def test_bench_whole_reward(benchmark, setup, fast_parse):
    """Prepared completion texts -> rewards: parse, pack, one engine call, the reward formula.

    fast-parse: the compiled CTRC scanner (reward.text_batch); python-parse: ctrc.parse.
    """
    device, engine, scenes, batch = setup
    reward = PhysicsReward(RewardConfig(device=str(device), fast_parse=fast_parse), engine=engine)
    texts = [completion_text(s) for s in scenes]
    scored = benchmark.pedantic(synchronized(lambda: reward.score(texts), device), rounds=3,
                                iterations=1, warmup_rounds=1)
    assert len(scored.rewards) == len(scenes) and scored.metrics["parse_failure_rate"] == 0.0
    if benchmark.enabled and device.type == "cpu":
        rate = len(scenes) / benchmark.stats.stats.median
        assert rate >= 500, f"reward on 12-object scenes: {rate:.0f} scenes/s < 500"
    if benchmark.enabled and device.type == "cuda" and fast_parse:
        ms = benchmark.stats.stats.median * 1e3
        assert ms <= 3.0, f"whole reward of 512 x 16-object completions: {ms:.2f} ms > 3 ms"


def test_bench_pack_texts(benchmark, setup):
    """Completion texts -> SceneBatch by the compiled scanner alone (no engine call)."""
    device, engine, scenes, batch = setup
    texts = [completion_text(s) for s in scenes]
    packer = TextPacker(engine)
    pack = benchmark.pedantic(synchronized(lambda: packer.pack(texts), device),
                              rounds=20 if device.type == "cuda" else 3, iterations=1, warmup_rounds=1)
    assert pack.fast.all() and pack.batch.n_scene == len(scenes)
