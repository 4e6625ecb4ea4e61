"""The work-list narrowphase against the buckets one: same results up to float summation order."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_physics import ZONE, PrimitiveLibrary, obj, random_scenes, reference

from physcene.config import ConfigError
from physcene.physics import PhysicsConfig, PhysicsEngine
from physcene.scene import Scene

KEYS = ("energy", "max_depth", "depth_sum", "pair_energy", "pair_depth", "table_depth", "table_energy",
        "table_below")


@pytest.fixture(scope="module")
def library() -> PrimitiveLibrary:
    return PrimitiveLibrary(n_points=256)


def engines(library, device="cpu", lanes=(1, 4, 16)):
    """(buckets engine at 16 lanes, [worklist engines at each lane count])."""
    base = PhysicsEngine(library, device, PhysicsConfig(narrowphase="buckets", lanes_cpu=16, lanes_cuda=32))
    worklist = [PhysicsConfig(narrowphase="worklist", lanes_cpu=k, lanes_cuda=k) for k in lanes]
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


def test_table_contact_skip_is_exact(library):
    """Objects resting exactly on z = 0 skip their points; sunk ones are measured as before."""
    eng = PhysicsEngine(library)
    rest = obj("rest", (10, 10, 5), (10, 10, 10))
    sunk = obj("sunk", (40, 10, 4.25), (6, 6, 10), 0.7, "cylinder")
    ball = obj("ball", (70, 10, 2.5), (6, 6, 6), 0.0, "sphere")
    batch = eng.pack([Scene(ZONE, (rest, sunk, ball))])
    out = eng.evaluate(batch)
    ref = reference(eng, batch)
    torch.testing.assert_close(out["table_depth"].double(), ref["table_depth"], rtol=0, atol=1e-5)
    assert out["table_depth"][0, :2].tolist() == pytest.approx([0.0, 0.75], abs=1e-5)
    assert 0.45 < out["table_depth"][0, 2] <= 0.5  # the sphere's lowest sample is near its pole
    assert out["table_below"][0, 0] == 0 and out["table_below"][0, 1:].min() > 0


def test_narrowphase_config_is_checked():
    with pytest.raises(ConfigError, match="narrowphase='tiles'"):
        PhysicsConfig(narrowphase="tiles")
    with pytest.raises(ConfigError, match="narrowphase_block_dim=2048"):
        PhysicsConfig.load(["narrowphase_block_dim=2048"])
    assert PhysicsConfig.load(["narrowphase=buckets"]).narrowphase == "buckets"
    assert replace(PhysicsConfig(), narrowphase="worklist").narrowphase == "worklist"


@pytest.mark.cuda
@pytest.mark.parametrize("lanes,block_dim", [(8, 256), (32, 256), (32, 64), (16, 32)])
def test_cuda_worklist_equals_cpu_buckets(library, lanes, block_dim):
    scenes = random_scenes(np.random.default_rng(41), 64, max_obj=12)
    cpu = PhysicsEngine(library, "cpu", PhysicsConfig(narrowphase="buckets"))
    gpu = PhysicsEngine(library, "cuda", PhysicsConfig(narrowphase="worklist", lanes_cuda=lanes,
                                                       narrowphase_block_dim=block_dim))
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


def _graph_engines(library, device):
    config = PhysicsConfig(narrowphase="worklist", lanes_cpu=2, lanes_cuda=16)
    return PhysicsEngine(library, device, config), PhysicsEngine(library, device, replace(config, graph=True))


def _check_graph_replays(library, device):
    from physcene.kernels import penetration

    direct, graphed = _graph_engines(library, device)
    scenes = random_scenes(np.random.default_rng(51), 16, max_obj=8)
    batch = graphed.pack(scenes)
    ref_batch = direct.pack(scenes)
    kept = None
    for call in range(4):  # direct, direct + capture, replay, replay
        poses = batch.poses + 0.3 * call
        for grad in (False, True):
            out = graphed.evaluate(batch, poses, with_grad=grad)
            ref = direct.evaluate(ref_batch, ref_batch.poses + 0.3 * call, with_grad=grad)
            assert set(out) == set(ref)
            for key in ref:
                assert torch.equal(out[key], ref[key]), (call, grad, key)
            if call == 2 and not grad:  # a replay's outputs
                kept = {key: (value, value.clone()) for key, value in out.items()}
    # the graph was captured, and replaying it again did not overwrite earlier outputs
    assert any(plan.args["n_pairs"] == batch.n_pairs and plan.poses.shape == batch.poses.shape
               for plan in penetration._PLANS.values())
    for key, (value, copy) in kept.items():
        assert torch.equal(value, copy), key
    # autograd through a replayed graph
    for _ in range(3):
        p = batch.poses.clone().requires_grad_(True)
        graphed.penetration_energy(batch, p).sum().backward()
    assert torch.equal(p.grad, direct.energy_and_grad(ref_batch)[1])
    # more layouts than plans kept: each still scores as without the graph
    for k in range(penetration._MAX_PLANS + 2):
        sub = scenes[:k + 2]
        for _ in range(3):
            out = graphed.evaluate(graphed.pack(sub), with_grad=True)
        ref = direct.evaluate(direct.pack(sub), with_grad=True)
        for key in ("energy", "pair_depth", "grad"):
            assert torch.equal(out[key], ref[key]), (k, key)
    lone = [Scene(ZONE, (obj("a", (10, 10, 5), (10, 10, 10)),))]
    for _ in range(3):  # no pairs: never captured
        assert graphed.evaluate(graphed.pack(lone), with_grad=True)["energy"].tolist() == [0.0]


def test_graph_replay_equals_direct_launches_on_cpu(library):
    _check_graph_replays(library, "cpu")


@pytest.mark.cuda
def test_cuda_graph_replay_equals_direct_launches(library):
    _check_graph_replays(library, "cuda")
