"""The penetration engine: exactness on primitives, the torch oracle, gradients, batching, support."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from physcene.assets import Asset, grid_coordinates, primitive_asset
from physcene.physics import PhysicsEngine, SceneBatch, bucket_points
from physcene.physics.reference import reference_penetration, reference_support_gap
from physcene.scene import Scene, SceneObject, Zone

ZONE = Zone(0.0, 120.0, 0.0, 60.0)


@dataclass
class Retrieval:
    asset: Asset
    fallback: str | None = None


class PrimitiveLibrary:
    """A stand-in library: box/cylinder/sphere are the exact primitives, plus test fields."""

    def __init__(self, n_points: int = 1024, extra: dict[str, Asset] | None = None):
        self.assets = {k: primitive_asset(k, n_points=n_points) for k in ("box", "cylinder", "sphere")}
        self.assets.update(extra or {})

    def resolve(self, category: str, asset_id: str | None = None) -> Retrieval:
        if category in self.assets:
            return Retrieval(self.assets[category])
        return Retrieval(self.assets["box"], fallback="box")


@pytest.fixture(scope="module")
def engine() -> PhysicsEngine:
    return PhysicsEngine(PrimitiveLibrary())


def obj(name, center, size, yaw=0.0, category="box"):
    return SceneObject(name, category, tuple(center), tuple(size), yaw)


def scene(*objects) -> Scene:
    return Scene(ZONE, objects)


def pair_depth(engine, sc: Scene) -> float:
    score = engine.score([sc])
    return max((d for _, _, d in score.pairs[0]), default=0.0)


def random_scenes(rng, n_scene, max_obj=7, spread=25.0, kinds=("box", "sphere", "cylinder")):
    scenes = []
    for _ in range(n_scene):
        objects = []
        for m in range(int(rng.integers(1, max_obj + 1))):
            size = rng.uniform(4.0, 16.0, 3)
            center = (rng.uniform(20, 20 + spread), rng.uniform(10, 10 + spread),
                      size[2] / 2 + rng.uniform(-1.0, 2.0))
            objects.append(obj(f"{m + 1}_o_{m}", center, size, rng.uniform(-math.pi, math.pi),
                               kinds[int(rng.integers(len(kinds)))]))
        scenes.append(Scene(ZONE, objects))
    return scenes


def reference(engine: PhysicsEngine, batch: SceneBatch, poses=None, **kw):
    return reference_penetration(poses=(batch.poses if poses is None else poses).double(), sizes=batch.sizes,
                                 count=batch.count, obj_asset=batch.asset_index,
                                 assets=engine.packed_assets(), margin=engine.config.margin_cm,
                                 depth_cap_ratio=engine.config.depth_cap_ratio, **kw)


# Exactness on primitives -----------------------------------------------------------------------
@pytest.mark.parametrize("d", [0.5, 2.0, 3.0, 4.0])
@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("size_a,size_b", [((20.0, 20.0, 20.0), (20.0, 20.0, 20.0)),
                                            ((30.0, 12.0, 8.0), (16.0, 24.0, 10.0))])
def test_boxes_overlapping_along_one_axis_report_the_overlap(engine, d, axis, size_a, size_b):
    """Exact up to the depth cap (0.8 × half the thinner box's smallest size: 3.2 cm for the 8 cm
    thick box), the cap beyond it (docs/physics.md, "Sound penetration")."""
    ca = np.array([50.0, 30.0, 20.0])
    cb = ca.copy()
    cb[axis] += 0.5 * (size_a[axis] + size_b[axis]) - d
    depth = pair_depth(engine, scene(obj("a", ca, size_a), obj("b", cb, size_b)))
    cap = engine.config.depth_cap_ratio * 0.5 * min(*size_a, *size_b)
    assert abs(depth - min(d, cap)) <= 0.1, (depth, d, cap)


@pytest.mark.parametrize("gap", [0.0, 0.3, 2.0])
def test_touching_and_separated_boxes_report_almost_nothing(engine, gap):
    a = obj("a", (50.0, 30.0, 4.0), (30.0, 12.0, 8.0))
    b = obj("b", (50.0 + 15.0 + 8.0 + gap, 31.0, 5.0), (16.0, 24.0, 10.0))
    assert pair_depth(engine, scene(a, b)) < 0.05


@pytest.mark.parametrize("d", [0.5, 1.5, 3.0])
def test_box_yawed_45_degrees_pushes_its_corner_to_the_right_depth(engine, d):
    half_diag = 5.0 * math.sqrt(2.0)  # a 10 x 10 box yawed 45°: corner at this distance in x
    b = obj("b", (50.0, 30.0, 5.0), (20.0, 16.0, 10.0))
    a = obj("a", (50.0 + 10.0 + half_diag - d, 30.0, 5.0), (10.0, 10.0, 10.0), math.pi / 4)
    assert abs(pair_depth(engine, scene(a, b)) - d) <= 0.2


def test_sphere_sunk_into_a_box_top_reports_the_sink(engine):
    box = obj("box", (50.0, 30.0, 5.0), (30.0, 20.0, 10.0))
    ball = obj("ball", (53.0, 28.0, 10.0 + 3.0 - 1.0), (6.0, 6.0, 6.0), category="sphere")
    assert abs(pair_depth(engine, scene(box, ball)) - 1.0) <= 0.1


def test_translating_a_scene_changes_nothing(engine):
    scenes = random_scenes(np.random.default_rng(1), 6)
    moved = [s.with_poses(s.poses() + np.array([37.25, -12.5, 3.0, 0.0])) for s in scenes]
    a, b = engine.score(scenes), engine.score(moved)
    assert torch.allclose(a.energy, b.energy, rtol=1e-4, atol=1e-4)
    assert torch.allclose(a.max_depth, b.max_depth, rtol=1e-4, atol=1e-4)
    assert [[p[:2] for p in row] for row in a.pairs] == [[p[:2] for p in row] for row in b.pairs]


# The torch oracle and gradients ------------------------------------------------------------------
def test_forward_matches_the_float64_reference(engine):
    batch = engine.pack(random_scenes(np.random.default_rng(2), 12))
    out, ref = engine.evaluate(batch), reference(engine, batch)
    assert out["energy"].sum() > 0
    assert torch.equal(out["pair_hit"], ref["pair_hit"])
    torch.testing.assert_close(out["energy"].double(), ref["energy"], rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(out["pair_depth"].double(), ref["pair_depth"], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out["table_depth"].double(), ref["table_depth"], rtol=1e-4, atol=1e-5)


def test_gradient_matches_the_float64_reference_on_yawed_scenes(engine):
    batch = engine.pack(random_scenes(np.random.default_rng(3), 10))
    grad = engine.evaluate(batch, with_grad=True)["grad"].double()
    ref = reference(engine, batch, with_grad=True)["grad"]
    assert ref.abs().max() > 1.0
    rel = (grad - ref).abs().max() / ref.abs().max()
    assert rel < 1e-3, rel
    # every object's own gradient, not just the largest one
    per_obj = (grad - ref).norm(dim=-1) / ref.norm(dim=-1).clamp(min=1e-2 * ref.abs().max())
    assert per_obj.max() < 1e-3


def _field_asset(name: str, field, resolution: int = 9) -> Asset:
    g = grid_coordinates(resolution)
    q = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    return Asset(asset_id=f"test:{name}", category=name, source="test", sdf=field(q).astype(np.float32),
                 points=primitive_asset("box", n_points=64).points)


@pytest.mark.parametrize("field,cubic", [
    (lambda q: 0.3 * q[..., 0] - 0.2 * q[..., 1] + 0.6 * q[..., 2] - 0.4, False),  # planar: any sizes
    (lambda q: q[..., 0] * q[..., 1] * q[..., 2] + 0.5 * q[..., 0] - 0.3, True),  # multilinear: cubes
])
def test_gradient_matches_central_differences_on_exact_fields(field, cubic):
    eng = PhysicsEngine(PrimitiveLibrary(n_points=64, extra={"field": _field_asset("field", field)}))
    rng = np.random.default_rng(4)
    objects = [obj("f", (50.0, 30.0, 6.0), (12.0, 12.0, 12.0) if cubic else (14.0, 9.0, 11.0), 0.4, "field")]
    for m in range(3):
        size = (8.0, 8.0, 8.0) if cubic else tuple(rng.uniform(5.0, 9.0, 3))
        center = (50.0 + rng.uniform(-6, 6), 30.0 + rng.uniform(-5, 5), 6 + rng.uniform(-3, 3))
        # every object carries the exact field: finite differences across the box SDF's kinks
        # (edges, medial planes) compare nothing the engine could reproduce
        objects.append(obj(f"p{m}", center, size, rng.uniform(-3, 3), "field"))
    batch = eng.pack([scene(*objects)])
    grad = eng.evaluate(batch, with_grad=True)["grad"].double()[0]
    poses = batch.poses.double()
    fd = torch.zeros_like(poses)
    h = 1e-5
    for i in range(poses.shape[1]):
        for k in range(4):
            plus, minus = poses.clone(), poses.clone()
            plus[0, i, k] += h
            minus[0, i, k] -= h
            diff = reference(eng, batch, plus)["energy"] - reference(eng, batch, minus)["energy"]
            fd[0, i, k] = diff[0] / (2 * h)
    assert fd.abs().max() > 1.0
    assert (grad - fd[0]).abs().max() / fd.abs().max() < 1e-3, (grad, fd[0])


def test_autograd_function_matches_energy_and_grad_and_repeats(engine):
    batch = engine.pack(random_scenes(np.random.default_rng(5), 5))
    energy, grad = engine.energy_and_grad(batch)
    poses = batch.poses.double().clone().requires_grad_(True)
    e = engine.penetration_energy(batch, poses)
    assert e.dtype == torch.float64 and e.shape == (5,)
    weights = torch.arange(1.0, 6.0, dtype=torch.float64)
    (g1,) = torch.autograd.grad((e * weights).sum(), poses, retain_graph=True)
    (g2,) = torch.autograd.grad((e * weights).sum(), poses)
    assert torch.equal(g1, g2)
    torch.testing.assert_close(e, energy.double())
    torch.testing.assert_close(g1, grad.double() * weights[:, None, None])
    again = engine.energy_and_grad(batch)[1]
    assert torch.equal(again, grad)  # fixed-order reductions: bit-for-bit repeatable


# Batching -----------------------------------------------------------------------------------------
def test_scenes_of_different_sizes_in_one_batch_score_as_alone(engine):
    scenes = random_scenes(np.random.default_rng(6), 9, max_obj=9)
    together = engine.score(scenes)
    for k, sc in enumerate(scenes):
        alone = engine.score([sc])
        assert together.energy[k].item() == pytest.approx(alone.energy[0].item(), rel=1e-6, abs=1e-6)
        assert together.pairs[k] == alone.pairs[0]


def test_kernel_pair_order_is_the_csr_order_of_pair_slots(engine):
    scenes = random_scenes(np.random.default_rng(10), 7, max_obj=6)
    batch = engine.pack(scenes)
    out = engine.evaluate(batch)
    slots = batch.pair_slots()
    n_slot = batch.poses.shape[1]
    assert len(slots) == batch.n_pairs
    assert out["pair_a"].tolist() == (slots[:, 0] * n_slot + slots[:, 1]).tolist()
    assert out["pair_b"].tolist() == (slots[:, 0] * n_slot + slots[:, 2]).tolist()
    assert batch.asset_ids[0] and all(f is None for row in batch.fallbacks for f in row)


def test_a_single_scene_and_an_empty_scene(engine):
    sc = scene(obj("a", (10, 10, 5), (10, 10, 10)))
    score = engine.score([sc, Scene(ZONE, ())])
    assert score.energy.tolist() == [0.0, 0.0] and score.pairs == [[], []]
    energy, grad = engine.energy_and_grad(engine.pack(sc))
    assert energy.shape == (1,) and grad.abs().sum() == 0


def test_ten_thousand_scenes_in_one_batch():
    eng = PhysicsEngine(PrimitiveLibrary(n_points=64))
    rng = np.random.default_rng(7)
    scenes = random_scenes(rng, 10_000, max_obj=4, spread=30.0)
    score = eng.score(scenes)
    assert score.energy.shape == (10_000,)
    for k in rng.choice(10_000, 20, replace=False).tolist():
        alone = eng.score([scenes[k]])
        assert score.energy[k].item() == pytest.approx(alone.energy[0].item(), rel=1e-6, abs=1e-6)
        assert score.floating[k] == alone.floating[0]


def test_results_do_not_depend_on_the_narrowphase_lane_count():
    from physcene.physics import PhysicsConfig

    scenes = random_scenes(np.random.default_rng(11), 24, max_obj=8)
    outs = []
    for lanes in (1, 5, 16, 64):
        eng = PhysicsEngine(PrimitiveLibrary(), config=PhysicsConfig(lanes_cpu=lanes))
        outs.append(eng.evaluate(eng.pack(scenes), with_grad=True))
    for out in outs[1:]:  # only the float summation order changes
        for key in ("energy", "max_depth", "pair_depth"):
            torch.testing.assert_close(out[key], outs[0][key], rtol=1e-5, atol=1e-5)
        assert (out["grad"] - outs[0]["grad"]).abs().max() / outs[0]["grad"].abs().max() < 1e-5
    assert outs[0]["energy"].sum() > 0  # the scenes do collide: the comparison is not vacuous


def test_assets_of_different_resolutions_and_point_counts(engine):
    coarse = primitive_asset("sphere", resolution=24, n_points=300)
    eng = PhysicsEngine(PrimitiveLibrary(extra={"ball": coarse}))
    scenes = random_scenes(np.random.default_rng(8), 6, kinds=("box", "ball", "cylinder"))
    batch = eng.pack(scenes)
    out, ref = eng.evaluate(batch, with_grad=True), reference(eng, batch, with_grad=True)
    torch.testing.assert_close(out["energy"].double(), ref["energy"], rtol=1e-4, atol=1e-3)
    assert (out["grad"].double() - ref["grad"]).abs().max() / ref["grad"].abs().max() < 1e-3


def test_point_buckets_partition_the_points():
    points = primitive_asset("cylinder", n_points=500).points
    ordered, offsets = bucket_points(points, 4)
    assert offsets[0] == 0 and offsets[-1] == len(points) and np.all(np.diff(offsets) >= 0)
    assert sorted(map(tuple, ordered.tolist())) == sorted(map(tuple, points.tolist()))
    for cell in range(64):
        k = np.array([cell // 16, cell // 4 % 4, cell % 4])
        chunk = ordered[offsets[cell]:offsets[cell + 1]]
        assert np.all(chunk >= -1 + 0.5 * k - 1e-6) and np.all(chunk <= -1 + 0.5 * (k + 1) + 1e-6)


# Table and support ------------------------------------------------------------------------------
def test_table_penetration(engine):
    score = engine.score([scene(obj("a", (10, 10, 4.0), (10, 10, 10)), obj("b", (40, 10, 5.0), (6, 6, 10)))])
    assert score.table_penetration[0].item() == pytest.approx(1.0, abs=1e-4)
    assert score.table_depth[0].tolist() == pytest.approx([1.0, 0.0], abs=1e-4)


def test_floating_objects(engine):
    base = obj("base", (50, 30, 2.0), (30, 20, 4.0))
    on_base = obj("on_base", (55, 30, 4.0 + 3.0 + 0.5), (6, 6, 6))  # 0.5 cm gap: supported
    hovering = obj("hovering", (90, 30, 1.5 + 3.0), (6, 6, 3))  # 3 cm above the table
    above_base = obj("above_base", (40, 25, 4.0 + 2.0 + 2.0), (4, 4, 4))  # 2 cm above the base
    holder = obj("holder", (15, 45, 5.0), (8, 8, 10))
    pen = obj("pen", (15, 45, 2.0 + 7.0), (1, 1, 14))  # bottom inside the holder's box
    overhang = obj("overhang", (50 + 15 + 2.0, 30, 4.0 + 1.0), (6, 4, 2))  # half over the base's edge
    sc = scene(base, on_base, hovering, above_base, holder, pen, overhang)
    score = engine.score([sc])
    assert [sc.objects[i].instance_id for i in score.floating[0]] == ["hovering", "above_base"]
    batch = engine.pack([sc])
    ref = reference_support_gap(poses=batch.poses.double(), sizes=batch.sizes, count=batch.count,
                                overlap_eps=engine.config.footprint_overlap_cm)
    torch.testing.assert_close(engine.support_gap(batch).double(), ref, atol=1e-5, rtol=0)


# CUDA ---------------------------------------------------------------------------------------------
@pytest.mark.cuda
def test_cuda_matches_cpu():
    lib = PrimitiveLibrary()
    cpu, gpu = PhysicsEngine(lib, "cpu"), PhysicsEngine(lib, "cuda")
    scenes = random_scenes(np.random.default_rng(9), 64, max_obj=12)
    a, b = cpu.evaluate(cpu.pack(scenes), with_grad=True), gpu.evaluate(gpu.pack(scenes), with_grad=True)
    for key in ("energy", "max_depth", "pair_depth", "table_depth"):
        torch.testing.assert_close(b[key].cpu(), a[key], rtol=1e-4, atol=1e-4)
    assert (b["grad"].cpu() - a["grad"]).abs().max() / a["grad"].abs().max() < 1e-4
    worst = {key: float((b[key].cpu() - a[key]).abs().max() / a[key].abs().max().clamp_min(1e-12))
             for key in ("energy", "max_depth", "pair_depth", "grad")}
    print(f"cpu vs cuda, max |diff| / max |cpu| over {len(scenes)} scenes: {worst}")
    assert cpu.score(scenes).floating == gpu.score(scenes).floating
    batch = gpu.pack(scenes)
    poses = batch.poses.clone().requires_grad_(True)
    e = gpu.penetration_energy(batch, poses)
    e.sum().backward()
    assert poses.grad.is_cuda and torch.equal(poses.grad, b["grad"])


def test_assets_appended_pack_like_all_at_once():
    """The engine appends new assets to the uploaded arrays (physics.pack_assets ``before``): the
    result equals packing every asset at once, and scores do not depend on the order assets arrive."""
    from physcene.physics import pack_assets

    assets = [primitive_asset(k, resolution=r, n_points=n)
              for k, r, n in (("box", 16, 200), ("sphere", 24, 300), ("cylinder", 16, 250))]
    whole = pack_assets(assets, torch.device("cpu"))
    derived: dict = {}
    first = pack_assets(assets[:1], torch.device("cpu"), derived)
    appended = pack_assets(assets[1:], torch.device("cpu"), derived, before=first)
    assert whole.keys() == appended.keys()
    for k in whole:
        assert torch.equal(whole[k], appended[k]), k
    assert set(derived) == {a.asset_id for a in assets}

    scenes = random_scenes(np.random.default_rng(5), 6)
    grown = PhysicsEngine(PrimitiveLibrary())
    grown.score([scene(obj("ball", (10, 10, 5), (5, 5, 10), category="sphere"))])
    assert grown.packed_assets()["sdf_res"].numel() == 1  # one asset uploaded, the others appended next
    a, b = grown.score(scenes), PhysicsEngine(PrimitiveLibrary()).score(scenes)
    assert grown.packed_assets()["sdf_res"].numel() == 3
    assert torch.allclose(torch.as_tensor(a.energy), torch.as_tensor(b.energy))
    assert any(e > 0 for e in torch.as_tensor(b.energy).tolist())
