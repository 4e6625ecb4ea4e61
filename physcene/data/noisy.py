"""Seeded noisy tabletop scenes with stacks and overlaps: the TTO acceptance and benchmark input.

Each scene is built collision-free first (groups on a jittered grid of cells inside the zone), then
perturbed the way a generator errs: whole groups pushed into their neighbours, small yaw errors,
``on`` children sunk into or floating above their support by up to ``sink_cm``, children slid a
little over their support. Groups:

- ``stack``: a box with a book on it, sometimes a cup on the book (``on`` edges);
- ``container``: a pot with a fruit or cup in it (an ``in`` edge; the content rests on the pot's
  floor, 0.7 cm up);
- ``single``: one object standing on the table.

Sizes are in cm; every scene has exactly ``n_objects`` objects (the last group is cut short).
"""

from __future__ import annotations

import math

import numpy as np

from physcene.scene import Scene, SceneObject, Zone

__all__ = ["noisy_scenes"]

_SINGLES = ("mug", "book", "box", "plate", "apple", "bottle", "notebook", "cup")


def _box(rng, lo, hi) -> tuple[float, float, float]:
    return tuple(float(v) for v in rng.uniform(lo, hi))


def _group(rng: np.random.Generator, k: int, budget: int) -> list[tuple[str, tuple, float, tuple]]:
    """Objects of one group in its own frame: (category, size, relative z of the bottom, xy offset)."""
    kind = rng.choice(["stack", "container", "single", "single"]) if budget > 1 else "single"
    if kind == "stack":
        base = _box(rng, (18, 14, 6), (26, 20, 12))
        book = _box(rng, (10, 8, 2), (15, 12, 4))
        out = [("box", base, 0.0, (0.0, 0.0)),
               ("book", book, base[2], tuple(rng.uniform(-1.5, 1.5, 2)))]
        if budget > 2 and rng.random() < 0.5:
            out.append(("cup", _box(rng, (6, 6, 7), (8, 8, 10)), base[2] + book[2], (0.0, 0.0)))
        return out
    if kind == "container":
        diameter = float(rng.uniform(16, 20))
        pot = (diameter, diameter, float(rng.uniform(8, 10)))
        content = _box(rng, (6, 6, 6), (8, 8, 8))
        return [("pot", pot, 0.0, (0.0, 0.0)), (str(rng.choice(["apple", "cup"])), content, 0.7,
                                                tuple(rng.uniform(-1.5, 1.5, 2)))]
    return [(str(rng.choice(_SINGLES)), _box(rng, (5, 5, 3), (16, 14, 15)), 0.0, (0.0, 0.0))]


def _scene(rng: np.random.Generator, index: int, n_objects: int, noise_cm: float, push_cm: float,
           sink_cm: float) -> Scene:
    zone = Zone(0.0, 120.0, 0.0, 80.0)
    groups = []
    total = 0
    while total < n_objects:
        g = _group(rng, len(groups), n_objects - total)[: n_objects - total]
        groups.append(g)
        total += len(g)
    cols = max(1, math.ceil(math.sqrt(len(groups) * zone.width / zone.depth)))
    rows = max(1, math.ceil(len(groups) / cols))
    cw, cd = zone.width / cols, zone.depth / rows
    cells = rng.permutation(rows * cols)[: len(groups)]
    objects = []
    for g, cell in zip(groups, cells):
        r, c = divmod(int(cell), cols)
        w, d = g[0][1][0], g[0][1][1]
        yaw = float(rng.normal(0.0, 0.1))
        reach = 0.5 * (abs(math.cos(yaw)) * w + abs(math.sin(yaw)) * d), \
            0.5 * (abs(math.sin(yaw)) * w + abs(math.cos(yaw)) * d)
        slack = max(cw / 2 - reach[0], 0.0), max(cd / 2 - reach[1], 0.0)
        x = (c + 0.5) * cw + rng.uniform(-slack[0], slack[0])
        y = (r + 0.5) * cd + rng.uniform(-slack[1], slack[1])
        # The generator's error: a random shift, often straight into a neighbour.
        shift = rng.normal(0.0, noise_cm, 2)
        if rng.random() < 0.5:
            angle = rng.uniform(0, 2 * math.pi)
            shift += push_cm * rng.uniform(0.5, 1.0) * np.array([math.cos(angle), math.sin(angle)])
        x, y = x + shift[0], y + shift[1]
        cy, sy = math.cos(yaw), math.sin(yaw)
        base = f"{index}"
        top = 0.0  # the actual top of the object below (stacks are bottom-up)
        for k, (cat, size, z0, (ox, oy)) in enumerate(g):
            z = z0 + size[2] / 2
            if k > 0 and g[0][0] != "pot":  # on children sunk into or floating above their support
                z = top + size[2] / 2 + float(rng.uniform(-sink_cm, sink_cm))
            top = z + size[2] / 2
            objects.append(SceneObject(
                instance_id=f"{k}_{cat}_{len(objects)}_{base}", category=cat,
                center=(x + cy * ox - sy * oy, y + sy * ox + cy * oy, z), size=size,
                yaw=yaw + (float(rng.normal(0.0, 0.05)) if k > 0 else 0.0)))
    return Scene(zone=zone, objects=tuple(objects), scene_type="noisy",
                 meta={"id": f"noisy-{index}"})


def noisy_scenes(n: int, n_objects: int = 16, *, seed: int = 0, noise_cm: float = 2.0,
                 push_cm: float = 8.0, sink_cm: float = 0.6) -> list[Scene]:
    """``n`` seeded noisy scenes of ``n_objects`` objects each (see the module docstring)."""
    if n < 0 or n_objects < 0:
        raise ValueError(f"noisy_scenes: n and n_objects must be >= 0, got {n}, {n_objects}")
    rng = np.random.default_rng(seed)
    return [_scene(rng, k, n_objects, noise_cm, push_cm, sink_cm) for k in range(n)]
