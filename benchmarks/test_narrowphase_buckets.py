"""The engine's work-list narrowphase against the ``buckets`` variant that lost to it
(benchmarks/narrowphase_buckets.py): same results up to float summation order.

    python -m pytest benchmarks/test_narrowphase_buckets.py
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

# the engine tests' scenes and primitive library (tests/physics/test_physics.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "physics"))

from narrowphase_buckets import BucketsEngine  # noqa: E402
from test_physics import ZONE, PrimitiveLibrary, obj, random_scenes  # noqa: E402

from physcene.physics import PhysicsConfig, PhysicsEngine  # noqa: E402
from physcene.scene import Scene  # noqa: E402

KEYS = ("energy", "max_depth", "depth_sum", "pair_energy", "pair_depth", "table_depth", "table_energy",
        "table_below")


@pytest.fixture(scope="module")
def library() -> PrimitiveLibrary:
    return PrimitiveLibrary(n_points=256)


def engines(library, device="cpu", lanes=(1, 4, 16)):
    """(buckets engine at 16 lanes, [worklist engines at each lane count])."""
    base = BucketsEngine(library, device, PhysicsConfig(lanes_cpu=16, lanes_cuda=32))
    worklist = [PhysicsConfig(lanes_cpu=k, lanes_cuda=k) for k in lanes]
    return base, [PhysicsEngine(library, device, config) for config in worklist]


def assert_same(out, ref, with_grad=True):
    for key in KEYS:
        torch.testing.assert_close(out[key], ref[key], rtol=1e-5, atol=1e-5, msg=key)
    for key in ("pair_a", "pair_b", "pair_hit"):
        assert torch.equal(out[key], ref[key]), key
    if with_grad:
        scale = ref["grad"].abs().max().clamp_min(1e-6)
        assert float((out["grad"] - ref["grad"]).abs().max() / scale) < 1e-5


@pytest.mark.parametrize("n_scene,max_obj", [(1, 8), (40, 9)])
def test_worklist_equals_buckets_on_random_batches(library, n_scene, max_obj):
    scenes = random_scenes(np.random.default_rng(20 + n_scene), n_scene, max_obj=max_obj)
    if n_scene == 1:
        scenes = [Scene(ZONE, scenes[0].objects[:1] + tuple(
            obj(f"x{k}", (30 + 3 * k, 20 + 2 * k, 5), (8, 6, 10), 0.3 * k) for k in range(7)))]
    base, others = engines(library)
    batch = base.pack(scenes)
    ref = base.evaluate(batch, with_grad=True)
    assert ref["energy"].sum() > 0 and ref["grad"].abs().max() > 0  # collisions: not vacuous
    for eng in others:
        out = eng.evaluate(eng.pack(scenes), with_grad=True)
        assert_same(out, ref)
        fwd = eng.evaluate(eng.pack(scenes))
        assert_same(fwd, ref, with_grad=False)


def test_worklist_per_pair_verdicts_and_autograd(library):
    scenes = random_scenes(np.random.default_rng(31), 12, max_obj=7)
    base, (eng, *_) = engines(library, lanes=(3,))
    a, b = base.score(scenes), eng.score(scenes)
    assert [[p[:2] for p in row] for row in a.pairs] == [[p[:2] for p in row] for row in b.pairs]
    for row_a, row_b in zip(a.pairs, b.pairs):
        assert [p[2] for p in row_b] == pytest.approx([p[2] for p in row_a], rel=1e-5, abs=1e-5)
    assert a.floating == b.floating
    batch = eng.pack(scenes)
    poses = batch.poses.clone().requires_grad_(True)
    eng.penetration_energy(batch, poses).sum().backward()
    energy, grad = eng.energy_and_grad(batch)
    assert torch.equal(poses.grad, grad)
    assert torch.equal(eng.energy_and_grad(batch)[1], grad)  # fixed-order sums: repeatable


def test_worklist_edge_batches(library):
    base, (eng, *_) = engines(library, lanes=(4,))
    lone = Scene(ZONE, (obj("a", (10, 10, 5), (10, 10, 10)),))
    far = Scene(ZONE, (obj("a", (10, 10, 5), (10, 10, 10)), obj("b", (80, 40, 5), (10, 10, 10))))
    empty = Scene(ZONE, ())
    for scenes in ([lone], [empty], [lone, empty], [far], [far, lone, far]):  # no pair passes
        out = eng.evaluate(eng.pack(scenes), with_grad=True)
        assert out["energy"].abs().sum() == 0 and out["grad"].abs().sum() == 0
        assert_same(out, base.evaluate(base.pack(scenes), with_grad=True))
    # a batch whose only colliding scene is the last one, after many without pairs
    sunk = Scene(ZONE, (obj("a", (50, 30, 5), (10, 10, 10)),
                        obj("b", (58, 30, 5), (10, 10, 10), math.pi / 8)))
    scenes = [lone] * 30 + [far] * 5 + [sunk]
    out = eng.evaluate(eng.pack(scenes), with_grad=True)
    ref = base.evaluate(base.pack(scenes), with_grad=True)
    assert out["energy"][-1] > 0 and out["energy"][:-1].abs().sum() == 0
    assert_same(out, ref)


# like conftest's BENCH_DEVICES: the CUDA cases exist where there is a CUDA device
CUDA_CASES = [(8, 256), (32, 256), (32, 64), (16, 32)] if torch.cuda.is_available() else []


@pytest.mark.cuda
@pytest.mark.parametrize("lanes,block_dim", CUDA_CASES)
def test_cuda_worklist_equals_cpu_buckets(library, lanes, block_dim):
    scenes = random_scenes(np.random.default_rng(41), 64, max_obj=12)
    cpu = BucketsEngine(library, "cpu", PhysicsConfig())
    gpu = PhysicsEngine(library, "cuda", PhysicsConfig(lanes_cuda=lanes, narrowphase_block_dim=block_dim))
    ref = cpu.evaluate(cpu.pack(scenes), with_grad=True)
    batch = gpu.pack(scenes)
    out = gpu.evaluate(batch, with_grad=True)
    for key in KEYS:
        torch.testing.assert_close(out[key].cpu(), ref[key], rtol=1e-4, atol=1e-4, msg=key)
    assert float((out["grad"].cpu() - ref["grad"]).abs().max() / ref["grad"].abs().max()) < 1e-4
    again = gpu.evaluate(batch, with_grad=True)  # atomic append order varies; the sums must not
    for key in ("energy", "pair_depth", "grad"):
        assert torch.equal(again[key], out[key]), key

    # a launch far smaller than the work list: every thread loops over many items
    from physcene.kernels import penetration

    resident = penetration._RESIDENT.copy()
    penetration._RESIDENT[str(gpu.device)] = 64
    try:
        small = gpu.evaluate(batch, with_grad=True)
    finally:
        penetration._RESIDENT.update(resident)
    for key in ("energy", "pair_depth", "grad"):
        assert torch.equal(small[key], out[key]), key


