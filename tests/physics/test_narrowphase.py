"""The engine's narrowphase (the work list): table contact, config checks, graph replays.

Its agreement with the ``buckets`` variant that lost (up to float summation order) is
benchmarks/test_narrowphase_buckets.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from test_physics import ZONE, PrimitiveLibrary, obj, random_scenes, reference

from physcene.config import ConfigError
from physcene.physics import PhysicsConfig, PhysicsEngine
from physcene.scene import Scene


@pytest.fixture(scope="module")
def library() -> PrimitiveLibrary:
    return PrimitiveLibrary(n_points=256)


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
    with pytest.raises(ConfigError, match="narrowphase_block_dim=2048"):
        PhysicsConfig.load(["narrowphase_block_dim=2048"])
    # one narrowphase in the engine: the variant that lost is benchmarks/narrowphase_buckets.py
    with pytest.raises(ConfigError, match="narrowphase"):
        PhysicsConfig.load(["narrowphase=buckets"])
    assert replace(PhysicsConfig(), narrowphase_block_dim=64).narrowphase_block_dim == 64


def _graph_engines(library, device):
    config = PhysicsConfig(lanes_cpu=2, lanes_cuda=16)
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
