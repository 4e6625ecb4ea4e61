"""Sound penetration (docs/physics.md): deep and coincident overlaps never read as clean.

pen(i, j) is the deepest surface-or-interior sample of either object inside the other, read at most
``depth_cap_ratio`` × half the thinner object's smallest size: never zero for overlapping volumes,
never falling as an overlap grows, exact for shallow overlaps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_physics import PrimitiveLibrary, reference

from physcene.assets import sample_sdf
from physcene.assets.interior import interior_points
from physcene.physics import PhysicsConfig, PhysicsEngine
from physcene.scene import Scene, SceneObject, Zone

ZONE = Zone(-100.0, 100.0, -100.0, 100.0)
OVERLAPS = [k / 4 for k in range(41)]  # 0 ... 10 cm


@pytest.fixture(scope="module")
def engine() -> PhysicsEngine:
    return PhysicsEngine(PrimitiveLibrary())


def depth(engine: PhysicsEngine, *objects: SceneObject) -> float:
    score = engine.score([Scene(ZONE, objects)])
    return max((d for _, _, d in score.pairs[0]), default=0.0)


def offset_pair(kind: str, size, overlap: float, yaw_deg: float, along: int = 0):
    """Two equal objects at one yaw, the second moved along their own x (``along`` 0) or y axis so
    that their boxes overlap by ``overlap`` cm on that axis."""
    yaw = math.radians(yaw_deg)
    gap = size[along] - overlap
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = (gap * c, gap * s) if along == 0 else (-gap * s, gap * c)
    z = size[2] / 2
    return (SceneObject("a", kind, (0.0, 0.0, z), tuple(size), yaw),
            SceneObject("b", kind, (dx, dy, z), tuple(size), yaw))


def assert_sound(readings: list[float], overlaps: list[float], bound: float, exact_upto: float | None):
    """At least 0.8 × min(overlap, bound) for every overlap; never falling; exact while shallow."""
    for s, r in zip(overlaps, readings):
        if s > 0:
            assert r >= 0.8 * min(s, bound) - 1e-4, (s, r)
        if exact_upto is not None and s <= exact_upto:
            assert abs(r - s) <= 1e-4, (s, r)
    assert all(b >= a - 1e-5 for a, b in zip(readings, readings[1:])), readings


@pytest.mark.parametrize("yaw_deg", [0, 20, 45, 70, 135])
def test_equal_cubes_read_their_overlap_up_to_the_cap(engine, yaw_deg):
    readings = [depth(engine, *offset_pair("box", (10.0, 10.0, 10.0), s, yaw_deg)) for s in OVERLAPS]
    assert_sound(readings, OVERLAPS, bound=5.0, exact_upto=4.0)
    assert readings[-1] == pytest.approx(4.0, abs=1e-4)  # coincident: the cap, not 0


@pytest.mark.parametrize("kind", ["sphere", "cylinder"])
@pytest.mark.parametrize("yaw_deg", [0, 45])
def test_equal_spheres_and_cylinders_never_read_clean_while_they_overlap(engine, kind, yaw_deg):
    readings = [depth(engine, *offset_pair(kind, (10.0, 10.0, 10.0), s, yaw_deg)) for s in OVERLAPS]
    assert_sound(readings, OVERLAPS, bound=5.0, exact_upto=None)
    assert readings[-1] > 3.9


@pytest.mark.parametrize("along", [0, 2])
def test_a_cube_and_a_slab_read_at_most_the_slab_s_half_thickness(engine, along):
    """A 1 cm slab sunk into a 10 cm cube from the side (``along`` 0) or from above (2)."""
    cube = SceneObject("cube", "box", (0.0, 0.0, 5.0), (10.0, 10.0, 10.0), 0.0)
    readings = []
    overlaps = [k / 20 for k in range(21)]  # 0 ... 1 cm: the slab fully inside at 1
    for s in overlaps:
        if along == 0:
            slab = SceneObject("slab", "box", (5.0 + 0.5 - s, 0.0, 5.0), (1.0, 30.0, 30.0), 0.0)
        else:
            slab = SceneObject("slab", "box", (0.0, 0.0, 10.0 + 0.5 - s), (30.0, 30.0, 1.0), 0.0)
        readings.append(depth(engine, cube, slab))
    assert_sound(readings, overlaps, bound=0.5, exact_upto=0.4)


def test_coincident_objects_collide(engine):
    for kind, size in (("box", (10.0, 10.0, 10.0)), ("sphere", (8.0, 8.0, 8.0)),
                       ("cylinder", (6.0, 6.0, 12.0)), ("box", (30.0, 20.0, 1.0))):
        a = SceneObject("a", kind, (0.0, 0.0, size[2] / 2), size, 0.3)
        b = SceneObject("b", kind, (0.0, 0.0, size[2] / 2), size, 0.3)
        assert depth(engine, a, b) == pytest.approx(0.8 * min(size) / 2, abs=1e-3), kind
    stack = [SceneObject(f"c{k}", "box", (0.0, 0.0, 5.0), (10.0, 10.0, 10.0), 0.0) for k in range(6)]
    score = engine.score([Scene(ZONE, stack)])
    assert len(score.pairs[0]) == 15 and min(d for _, _, d in score.pairs[0]) > 3.9


def test_surface_samples_alone_read_coincident_cubes_as_clean():
    """The hole the interior samples close: the paper's surface-only measure (interior_per_axis 0)."""
    surface_only = PhysicsEngine(PrimitiveLibrary(),
                                 config=PhysicsConfig(interior_per_axis=0, depth_cap_ratio=0.0))
    a, b = offset_pair("box", (10.0, 10.0, 10.0), 10.0, 0)
    assert depth(surface_only, a, b) < 0.01
    a, b = offset_pair("box", (10.0, 10.0, 10.0), 8.0, 0)
    assert depth(surface_only, a, b) == pytest.approx(2.0, abs=1e-4)  # folds back: min(10 − s, s)


def test_the_energy_of_equal_cubes_is_least_at_coincidence_nearby(engine):
    """Why TTO parts deep pairs before its gradient steps (TTOConfig.separate_deep): every surface
    sample of one cube lies on the other's surface at coincidence, so a small offset raises the
    energy (the pair reads deep throughout)."""
    energies = []
    for offset in (0.0, 0.3, 1.0):
        a, b = offset_pair("box", (10.0, 10.0, 10.0), 10.0 - offset, 0)
        energies.append(engine.energy_and_grad(engine.pack([Scene(ZONE, (a, b))]))[0].item())
    assert energies[0] > 0 and energies[0] < energies[1] < energies[2]


def test_the_reference_reads_the_same_measure(engine):
    rng = np.random.default_rng(3)
    scenes = []
    for _ in range(4):
        size = tuple(rng.uniform(4.0, 12.0, 3))
        shift = rng.uniform(-2.0, 2.0, 2)
        objects = [SceneObject("a", "box", (0.0, 0.0, size[2] / 2), size, float(rng.uniform(-3, 3))),
                   SceneObject("b", str(rng.choice(["box", "sphere", "cylinder"])),
                               (shift[0], shift[1], size[2] / 2), size, float(rng.uniform(-3, 3)))]
        scenes.append(Scene(ZONE, objects))
    batch = engine.pack(scenes)
    out = engine.evaluate(batch)
    ref = reference(engine, batch)
    assert torch.allclose(out["pair_depth"].double(), ref["pair_depth"], atol=1e-3)
    assert torch.allclose(out["energy"].double(), ref["energy"], rtol=1e-3, atol=1e-2)
    assert (out["pair_depth"] > 0.5).all()


def test_interior_samples_fill_solids_and_walls_not_cavities():
    from physcene.assets import default_library

    library = default_library()
    box = interior_points(library.get("primitive:box").sdf)
    assert len(box) == 7**3 and np.abs(box).max() < 1.0
    for hollow in ("procedural:bowl", "procedural:pen_holder", "procedural:mug"):
        asset = library.get(hollow)
        points = interior_points(asset.sdf)
        assert len(points) > 20, hollow
        assert (sample_sdf(asset, points) < 0).all(), hollow  # every sample inside the walls
    assert len(interior_points(library.get("primitive:box").sdf, 0)) == 0
    with pytest.raises(ValueError, match="per axis"):
        interior_points(library.get("primitive:box").sdf, -1)
    with pytest.raises(ValueError, match="grid"):
        interior_points(box)


COINCIDENT = {
    "boxes": ("box", (10.0, 10.0, 10.0), 2),
    "spheres": ("sphere", (8.0, 8.0, 8.0), 2),
    "cylinders": ("cylinder", (6.0, 6.0, 12.0), 2),
    "slabs": ("box", (30.0, 20.0, 1.0), 2),
    "six cubes": ("box", (10.0, 10.0, 10.0), 6),
}


@pytest.mark.parametrize("name", list(COINCIDENT))
def test_repair_parts_coincident_objects(engine, name):
    from physcene.graph import footprint_overlap
    from physcene.tto import repair

    kind, size, n = COINCIDENT[name]
    zone = Zone(0.0, 120.0, 0.0, 60.0)
    objects = tuple(SceneObject(f"{k + 1}_{kind}_{k}", kind, (60.0, 30.0, size[2] / 2), size, 0.2)
                    for k in range(n))
    result = repair([Scene(zone, objects)], engine=engine)[0]
    after = result.scene
    assert max((d for _, _, d in engine.score([after]).pairs[0]), default=0.0) <= 0.1  # 1 mm
    for i, a in enumerate(after.objects):
        for b in after.objects[i + 1:]:
            assert footprint_overlap(a, b) <= 0.05, (a.instance_id, b.instance_id)
    assert result.report.energy_after <= result.report.energy_before
