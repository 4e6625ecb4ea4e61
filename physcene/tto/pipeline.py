""":func:`repair`: scenes in batches -> problem -> Adam -> reports, and the second pass that holds
the chains whose in/on edge the first pass broke."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import replace

from tqdm import tqdm

from physcene.graph import build_hierarchy, ensure_hierarchy
from physcene.scene import Scene
from physcene.tto.config import TTOConfig
from physcene.tto.optimise import optimise
from physcene.tto.problem import build_problem
from physcene.tto.report import TTOResult, empty_result, scene_results

__all__ = ["repair"]


def repair(scenes: Sequence[Scene], config: TTOConfig | None = None, engine=None,
           freeze: Sequence[set[str]] | None = None, progress: bool = False) -> list[TTOResult]:
    """Project each scene onto the collision-free set without breaking its hierarchy.

    ``scenes`` may carry a hierarchy (parent/relation, e.g. from CTRC) or not (it is built with
    :func:`physcene.graph.build_hierarchy`). ``freeze``: per scene, ids held exactly where the
    input has them (their subtrees still follow them; a scene with held objects is not
    re-attached), e.g. every object but the ones a reward blamed. Returns one :class:`TTOResult`
    per scene, in order; the returned scene is the input with new poses (annotations as in the
    input). ``progress``: a bar on stderr over the scenes, when there is more than one batch.
    """
    config = config or TTOConfig.load()
    if engine is None:
        from physcene.physics import PhysicsEngine  # here: Warp loads only when a repair needs an engine

        engine = PhysicsEngine(device=config.device)
    scenes = list(scenes)
    if freeze is not None and len(freeze) != len(scenes):
        raise ValueError(f"freeze: {len(freeze)} sets of held ids for {len(scenes)} scenes")
    results: list[TTOResult | None] = [None] * len(scenes)
    todo = [i for i, sc in enumerate(scenes) if len(sc) > 0]
    for i, sc in enumerate(scenes):
        if len(sc) == 0:
            results[i] = empty_result(sc)
    bar = tqdm(total=len(todo), desc="repair", unit="scene", file=sys.stderr,
               disable=not progress or len(todo) <= config.batch_size)
    for start in range(0, len(todo), config.batch_size):
        chunk = todo[start:start + config.batch_size]
        hier = [ensure_hierarchy(scenes[i]) for i in chunk]
        held = [set(freeze[i]) for i in chunk] if freeze is not None else None
        problem = build_problem(hier, engine, config, held)
        solution = optimise(problem, engine, config)
        for k, result in enumerate(scene_results(problem, solution, [scenes[i] for i in chunk], hier,
                                                 engine, config)):
            results[chunk[k]] = result
        _second_pass(chunk, hier, scenes, results, engine, config, held)
        bar.update(len(chunk))
    bar.close()
    return results


def _second_pass(chunk: list[int], hier: list[Scene], scenes: list[Scene], results: list, engine,
                 config: TTOConfig, held: list[set[str]] | None = None) -> None:
    """Re-run scenes whose rebuilt graph lost an in/on edge, with that child's chain held.

    Why: sliding an ``on`` child (or its support, or a container over it), or snapping it onto its
    support, can make another container's ``in`` test true, and the graph ranks ``in`` above
    ``on``. The child, its ancestors and the object that took it (with its ancestors) are held
    exactly where the input had them (z included, no snapping, no reattachment); the rest of the
    scene is still optimised. The second result is taken when it keeps more
    in/on edges and is not worse in energy.
    """
    if not config.report_relations:
        return
    redo = [k for k, i in enumerate(chunk) if results[i].report.relations.in_on_broken]
    if not redo:
        return
    freeze = []
    for k in redo:
        after = results[chunk[k]].scene
        taken = build_hierarchy(after.with_objects(o.moved(parent=None, relation=None)
                                                   for o in after.objects))
        by_id, ids = hier[k].by_id(), set()
        for child in results[chunk[k]].report.relations.in_on_broken:
            # the child's chain and the chain of what the rebuilt graph gave it to
            for oid in (child, taken.get(child).parent):
                while oid in by_id and oid not in ids:
                    ids.add(oid)
                    oid = by_id[oid].parent
        freeze.append(ids | held[k] if held is not None else ids)
    sub = [hier[k] for k in redo]
    problem = build_problem(sub, engine, config, freeze)
    solution = optimise(problem, engine, config)
    for k, again in zip(redo, scene_results(problem, solution, [scenes[chunk[k]] for k in redo], sub,
                                            engine, config)):
        first = results[chunk[k]]
        if (again.report.relations.in_on_kept > first.report.relations.in_on_kept
                and again.energy_after <= first.energy_before):
            again.report = replace(again.report, held=tuple(sorted(freeze[redo.index(k)])))
            results[chunk[k]] = again
