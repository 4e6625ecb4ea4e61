"""What a repair says about each scene: the typed :class:`TTOReport`, and :func:`summarize`.

A report is built on the host from the chosen poses (the best iterate, or the input when nothing
beat it): depths before/after, the residual collisions (pairs deeper than ``collision_depth_cm``),
the relations kept (the graph of the result rebuilt from its geometry), and a sentence for every
requirement that could not be met. :meth:`TTOReport.as_dict` is the JSON form written by
``physcene repair`` (its keys and their order are part of that file's format).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from physcene.relations import relation_preservation
from physcene.scene import Scene
from physcene.tto.config import TTOConfig
from physcene.tto.optimise import TTOSolution
from physcene.tto.problem import TTOProblem

__all__ = ["RelationReport", "ResidualCollision", "TTOReport", "TTOResult", "scene_results", "summarize"]


@dataclass(frozen=True, kw_only=True)
class ResidualCollision:
    """A pair still deeper than ``collision_depth_cm`` after the repair."""

    a: str
    """Instance id of the first object."""
    b: str
    """Instance id of the second object."""
    depth_cm: float
    """Penetration depth in cm, rounded to 4 decimals."""
    frozen: bool
    """Both in one rigid in-body (``in_children=frozen``: TTO may not move them relative to each other)."""
    in_body: bool
    """Both in one container body (a container and its contents), whichever the mode."""

    def as_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "depth_cm": self.depth_cm, "frozen": self.frozen,
                "in_body": self.in_body}


@dataclass(frozen=True, kw_only=True)
class RelationReport:
    """How much of the input's hierarchy the result keeps
    (:func:`physcene.relations.relation_preservation`)."""

    in_on_edges: int
    """``in``/``on`` edges of the input."""
    in_on_kept: float
    """Fraction of them the result's rebuilt graph keeps (1.0 when there are none)."""
    in_on_broken: tuple[str, ...]
    """Children whose ``in``/``on`` edge the result lost."""
    near_relations: int
    """Near references of the input's table-level objects."""
    near_kept: float
    """Fraction of near directions kept (1.0 when there are none)."""
    near_broken: tuple[str, ...]
    """Objects whose near direction to their reference was lost."""

    @classmethod
    def from_dict(cls, kept: dict) -> RelationReport:
        """From :func:`~physcene.relations.relation_preservation`'s dict."""
        return cls(in_on_edges=kept["in_on_edges"], in_on_kept=kept["in_on_kept"],
                   in_on_broken=tuple(kept["in_on_broken"]), near_relations=kept["near_relations"],
                   near_kept=kept["near_kept"], near_broken=tuple(kept["near_broken"]))

    def as_dict(self) -> dict:
        return {"in_on_edges": self.in_on_edges, "in_on_kept": self.in_on_kept,
                "in_on_broken": list(self.in_on_broken), "near_relations": self.near_relations,
                "near_kept": self.near_kept, "near_broken": list(self.near_broken)}


@dataclass(frozen=True, kw_only=True)
class TTOReport:
    """One scene's repair report; energies and lengths in cm."""

    n_objects: int
    """Objects in the scene (0: an empty scene, returned as it came)."""
    max_depth_before_cm: float = 0.0
    """Deepest pair of the input."""
    max_depth_after_cm: float = 0.0
    """Deepest pair of the result."""
    collision_free: bool = True
    """No pair of the result deeper than ``collision_depth_cm`` (every pair counted)."""
    residual_collisions: tuple[ResidualCollision, ...] = ()
    """The result's pairs deeper than ``collision_depth_cm``."""
    relations: RelationReport | None = None
    """Relations kept (None when ``report_relations`` is off or the scene is empty)."""
    unsatisfied: tuple[str, ...] = ()
    """One sentence per requirement the result does not meet."""
    reattached: tuple[tuple[str, str], ...] = ()
    """(object, support): table-level objects optimised as ``on`` a support they hovered over."""
    energy_before: float = 0.0
    """Penetration energy of the input over the pairs outside any rigid in-body."""
    energy_after: float = 0.0
    """The same energy of the result (never more than ``energy_before``)."""
    max_displacement_cm: float = 0.0
    """Largest centre displacement of an object."""
    mean_displacement_cm: float = 0.0
    """Mean centre displacement over the objects."""
    steps: int = 0
    """Adam steps taken before the scene stopped."""
    kept_input: bool = True
    """No iterate had less energy than the input: the input was returned unchanged."""
    held: tuple[str, ...] | None = None
    """Ids held where the input had them by the second pass (None: the first pass's result)."""

    def as_dict(self) -> dict:
        """The JSON form (``physcene repair``'s report file): the keys in their written order."""
        residual = [p.as_dict() for p in self.residual_collisions]
        relations = self.relations.as_dict() if self.relations is not None else None
        if self.n_objects == 0:  # an empty scene's report has its own, shorter key set
            return {"n_objects": 0, "energy_before": self.energy_before, "energy_after": self.energy_after,
                    "max_depth_before_cm": self.max_depth_before_cm,
                    "max_depth_after_cm": self.max_depth_after_cm, "collision_free": self.collision_free,
                    "residual_collisions": residual, "max_displacement_cm": self.max_displacement_cm,
                    "steps": self.steps, "kept_input": self.kept_input, "relations": relations,
                    "unsatisfied": list(self.unsatisfied)}
        out = {"n_objects": self.n_objects, "max_depth_before_cm": self.max_depth_before_cm,
               "max_depth_after_cm": self.max_depth_after_cm, "collision_free": self.collision_free,
               "residual_collisions": residual, "relations": relations,
               "unsatisfied": list(self.unsatisfied),
               "reattached": [{"object": a, "on": b} for a, b in self.reattached],
               "energy_before": self.energy_before, "energy_after": self.energy_after,
               "max_displacement_cm": self.max_displacement_cm,
               "mean_displacement_cm": self.mean_displacement_cm, "steps": self.steps,
               "kept_input": self.kept_input}
        if self.held is not None:
            out["held"] = list(self.held)
        return out


@dataclass
class TTOResult:
    """One repaired scene: energies in cm (engine units, optimised pairs), displacement in cm."""

    scene: Scene
    energy_before: float
    energy_after: float
    max_displacement_cm: float
    report: TTOReport


def empty_result(scene: Scene) -> TTOResult:
    """The result of an empty scene: returned as it came."""
    return TTOResult(scene, 0.0, 0.0, 0.0, TTOReport(n_objects=0))


def _free_energy(engine, problem: TTOProblem, poses: torch.Tensor) -> np.ndarray:
    """(S,) float64 cm: Σ pair energies over pairs outside any rigid in-body (exact, for reports)."""
    out = engine.evaluate(problem.batch, poses)
    slots = problem.batch.pair_slots()
    if len(slots) == 0:
        return np.zeros(problem.n_scene)
    free = problem.group[slots[:, 0], slots[:, 1]] != problem.group[slots[:, 0], slots[:, 2]]
    energy = out["pair_energy"].detach().cpu().numpy().astype(np.float64)
    return np.bincount(slots[free, 0], weights=energy[free], minlength=problem.n_scene)


def scene_results(problem: TTOProblem, solution: TTOSolution, inputs: list[Scene], hier: list[Scene],
                  engine, config: TTOConfig) -> list[TTOResult]:
    """Host side: choose best-or-input per scene, score both, and write the reports."""
    e_before = _free_energy(engine, problem, problem.raw_poses)
    e_best = _free_energy(engine, problem, solution.poses)
    kept = ~(e_best <= e_before)  # NaN or worse: keep the input
    keep = torch.as_tensor(kept, device=solution.poses.device)[:, None, None]
    final = torch.where(keep, problem.raw_poses, solution.poses.detach())
    before_score = engine.score(problem.batch, problem.raw_poses)
    after_score = engine.score(problem.batch, final)
    poses = final.cpu().numpy().astype(np.float64)
    steps = solution.steps.cpu().numpy()
    results = []
    for s, scene in enumerate(inputs):
        after = scene if kept[s] else scene.with_poses(poses[s, :len(scene)])
        disp = np.linalg.norm(after.poses()[:, :3] - scene.poses()[:, :3], axis=1)
        e_after = float(e_before[s] if kept[s] else e_best[s])
        residual, unsatisfied = _residual(after, problem.group[s, :len(after)], problem.body[s, :len(after)],
                                          after_score.pairs[s], config)
        unsatisfied += _zone_sentences(after, config)
        relations = None
        if config.report_relations:
            relations = RelationReport.from_dict(relation_preservation(hier[s], after))
            unsatisfied += [f"{oid}: {hier[s].get(oid).relation} edge to {hier[s].get(oid).parent} broken"
                            for oid in relations.in_on_broken]
            unsatisfied += [f"{oid}: near direction to its reference lost" for oid in relations.near_broken]
        if kept[s]:
            unsatisfied.append("no iterate had less penetration energy than the input: "
                               "input returned unchanged")
        report = TTOReport(
            n_objects=len(after), max_depth_before_cm=float(before_score.max_depth[s]),
            max_depth_after_cm=float(after_score.max_depth[s]), collision_free=not residual,
            residual_collisions=tuple(residual), relations=relations, unsatisfied=tuple(unsatisfied),
            reattached=tuple(problem.reattached[s]), energy_before=float(e_before[s]), energy_after=e_after,
            max_displacement_cm=float(disp.max()), mean_displacement_cm=float(disp.mean()),
            steps=int(steps[s]), kept_input=bool(kept[s]))
        results.append(TTOResult(after, float(e_before[s]), e_after, float(disp.max()), report))
    return results


def _residual(after: Scene, group: np.ndarray, body: np.ndarray, pairs,
              config: TTOConfig) -> tuple[list[ResidualCollision], list[str]]:
    """The result's pairs deeper than ``collision_depth_cm``, and a sentence for each."""
    ids = after.ids()
    residual, unsatisfied = [], []
    for i, j, depth in pairs:
        if float(depth) > config.collision_depth_cm:
            frozen, in_body = bool(group[i] == group[j]), bool(body[i] == body[j])
            residual.append(ResidualCollision(a=ids[i], b=ids[j], depth_cm=round(float(depth), 4),
                                              frozen=frozen, in_body=in_body))
            why = (" (both in one rigid in-body: frozen by the hierarchy)" if frozen else
                   " (inside one container: the content does not fit where the in edge allows)"
                   if in_body else "")
            unsatisfied.append(f"{ids[i]} and {ids[j]} still penetrate by {float(depth):.2f} cm{why}")
    return residual, unsatisfied


def _zone_sentences(after: Scene, config: TTOConfig) -> list[str]:
    """Objects larger than, outside of, or overlapping restricted parts of the placement zone."""
    unsatisfied = []
    zone = after.zone
    for o in after.objects:
        box = o.aabb()
        if box[1] - box[0] > zone.width + 1e-6 or box[3] - box[2] > zone.depth + 1e-6:
            unsatisfied.append(f"{o.instance_id} ({box[1] - box[0]:.1f} x {box[3] - box[2]:.1f} cm) is "
                               f"larger than the placement zone ({zone.width:.1f} x {zone.depth:.1f} cm)")
        out = max(zone.xmin - box[0], box[1] - zone.xmax, zone.ymin - box[2], box[3] - zone.ymax)
        if out > config.zone_tolerance_cm:
            unsatisfied.append(f"{o.instance_id} lies {out:.2f} cm outside the placement zone")
        for k, rz in enumerate(after.restricted_zones):
            depth = min(box[1] - rz.xmin, rz.xmax - box[0], box[3] - rz.ymin, rz.ymax - box[2])
            if depth > config.zone_tolerance_cm:
                unsatisfied.append(f"{o.instance_id} overlaps restricted zone {k} by {depth:.2f} cm")
    return unsatisfied


def summarize(results: Sequence[TTOResult]) -> dict:
    """Dataset figures of :func:`physcene.tto.repair` results (the acceptance measures).

    ``collision_free``: fraction of scenes without any pair deeper than ``collision_depth_cm``
    (every pair counted); ``collision_free_excluding_frozen`` leaves out pairs inside one rigid
    in-body (``in_children=frozen`` only: TTO may not move those); ``scenes_with_frozen_residual`` /
    ``scenes_with_in_body_residual`` count scenes whose residual collisions include such a pair / a
    pair inside one container body. Relation fractions are pooled over all edges.
    """
    n = len(results)
    reports = [r.report for r in results]
    rel = [r.relations for r in reports if r.relations]
    edges = sum(k.in_on_edges for k in rel)
    nears = sum(k.near_relations for k in rel)
    disp = [r.max_displacement_cm for r in results]
    residual = [r.residual_collisions for r in reports]
    return {
        "scenes": n,
        "collision_free": sum(not pairs for pairs in residual) / max(n, 1),
        "collision_free_excluding_frozen":
            sum(all(p.frozen for p in pairs) for pairs in residual) / max(n, 1),
        "scenes_with_frozen_residual": sum(any(p.frozen for p in pairs) for pairs in residual),
        "scenes_with_in_body_residual": sum(any(p.in_body for p in pairs) for pairs in residual),
        "energy_increased": sum(r.energy_after > r.energy_before for r in results),
        "kept_input": sum(bool(r.kept_input) for r in reports),
        "in_on_edges": edges,
        "in_on_kept": sum(k.in_on_edges - len(k.in_on_broken) for k in rel) / edges if edges else 1.0,
        "near_relations": nears,
        "near_kept": sum(k.near_relations - len(k.near_broken) for k in rel) / nears if nears else 1.0,
        "median_max_displacement_cm": float(np.median(disp)) if disp else 0.0,
        "mean_steps": float(np.mean([r.steps for r in reports])) if reports else 0.0,
    }
