"""Baseline generators for ``physcene eval``: reference data, reference + TTO, zero-shot LLM through
an endpoint with the paper's Prompt 3, and a non-learned heuristic placer.

A generator maps benchmark items (:class:`~physcene.eval.harness.BenchmarkItem`) to one result
each: a :class:`~physcene.scene.Scene`, or a :class:`~physcene.ctrc.ParseError` when a model's
output did not parse (a value, never an exception).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from physcene import ctrc
from physcene.scene import TABLE, Scene

__all__ = ["heuristic_place", "zero_shot_prompt"]

def zero_shot_prompt(reference: Scene) -> str:
    """The paper's Prompt 3 (:func:`physcene.ctrc.zero_shot_prompt`) filled with the reference's
    zone, instruction and object list."""
    return ctrc.zero_shot_prompt(reference.instruction, reference.zone, reference.objects)


def heuristic_place(reference: Scene, seed: int = 0, gap_cm: float = 1.0, cell_cm: float = 1.0) -> Scene:
    """A non-learned placer: every requested object (its size from the request) stands on the
    table at a uniformly random free spot of the zone, largest footprint first, yaw 0 or 90°
    (whichever fits), ``gap_cm`` apart, with no stacking, containment or other semantics. Objects
    for which no free spot is left are dropped. Occupancy is a ``cell_cm`` grid; free spots come
    from a summed-area table, so a placement is O(grid)."""
    rng = np.random.default_rng(seed)
    z = reference.zone
    nx, ny = int(math.floor(z.width / cell_cm)), int(math.floor(z.depth / cell_cm))
    occ = np.zeros((nx, ny), dtype=np.int32)
    restricted = np.zeros_like(occ)
    for r in reference.restricted_zones:
        i0, i1 = int((r.xmin - z.xmin) // cell_cm), int(math.ceil((r.xmax - z.xmin) / cell_cm))
        j0, j1 = int((r.ymin - z.ymin) // cell_cm), int(math.ceil((r.ymax - z.ymin) / cell_cm))
        restricted[max(i0, 0):max(i1, 0), max(j0, 0):max(j1, 0)] = 1
    occ |= restricted
    placed = []
    order = sorted(reference.objects, key=lambda o: -o.size[0] * o.size[1])
    for o in order:
        options = []
        for yaw, (w, d) in ((0.0, o.size[:2]), (0.5 * math.pi, o.size[1::-1])):
            kw, kd = int(math.ceil((w + gap_cm) / cell_cm)), int(math.ceil((d + gap_cm) / cell_cm))
            if kw > nx or kd > ny:
                continue
            sat = np.zeros((nx + 1, ny + 1), dtype=np.int64)
            sat[1:, 1:] = occ.cumsum(0).cumsum(1)
            window = sat[kw:, kd:] - sat[:-kw, kd:] - sat[kw:, :-kd] + sat[:-kw, :-kd]  # (nx-kw+1, ny-kd+1)
            free = np.argwhere(window == 0)
            if len(free):
                options.append((yaw, kw, kd, free))
        if not options:
            continue  # no room left: the placer drops it (CwT will notice)
        yaw, kw, kd, free = options[int(rng.integers(len(options)))]
        i, j = free[int(rng.integers(len(free)))]
        occ[i:i + kw, j:j + kd] = 1
        cx = z.xmin + (i + 0.5 * kw) * cell_cm
        cy = z.ymin + (j + 0.5 * kd) * cell_cm
        placed.append(o.moved(center=(cx, cy, 0.5 * o.size[2]), yaw=yaw, parent=TABLE, relation="near"))
    by_order = {o.instance_id: k for k, o in enumerate(reference.objects)}
    placed.sort(key=lambda o: by_order[o.instance_id])
    return reference.with_objects(placed)


def heuristic_generator(references: Sequence[Scene], seed: int = 0) -> list[Scene]:
    """:func:`heuristic_place` over a benchmark, one seed per scene."""
    return [heuristic_place(r, seed=seed * 100003 + k) for k, r in enumerate(references)]
