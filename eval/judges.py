"""Judges scoring the paper's five criteria (CwT, OSR, PPI, LCR, OV) on a 1-10 scale.

- :class:`RuleJudge` (offline default) scores from the layout, the request (instruction, object
  list, stated relations) and the engine's physics facts. Formulas: docs/eval.md.
- :class:`~physcene.eval.endpoint.EndpointJudge` (:mod:`physcene.eval.endpoint`) asks any
  OpenAI-compatible chat-completions endpoint with image input, using the paper's Prompts 4-5
  verbatim and the front + perspective renders.

Both return a dict ``{"CwT": .., "OSR": .., "PPI": .., "LCR": .., "OV": .., "avg": ..}``; a judge
that cannot produce scores returns ``{"error": reason}`` (and ``avg`` NaN) instead of raising.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from physcene.assets import CATEGORY_PRIORS, canonical_category
from physcene.eval.metrics import CRITERIA, ScenePhysics
from physcene.graph import build_hierarchy
from physcene.scene import TABLE, Scene

__all__ = ["EvalCase", "JudgeError", "LayoutStats", "RuleJudge", "adjacency_pairs", "canonical_category",
           "layout_features", "stated_relations"]


class JudgeError(ValueError):
    """A judge was configured wrongly (bad URL, bad cache directory ...)."""


def _role(category: str) -> str:
    prior = CATEGORY_PRIORS.get(canonical_category(category))
    return prior.role if prior else "object"


@dataclass(frozen=True)
class EvalCase:
    """What a generator was asked for: the judge's view of one benchmark request."""

    instruction: str
    scene_type: str
    requested: tuple[str, ...]
    """Requested object categories (canonical, one entry per instance)."""
    relations: tuple[tuple[str, str, str], ...] = ()
    """Stated relations (child category, "in"|"on", parent category)."""
    adjacency: tuple[tuple[str, str], ...] = ()
    """Functional neighbours (category, category of its nearest object) of the reference layout:
    mouse next to keyboard, fork next to plate."""

    @classmethod
    def from_reference(cls, scene: Scene) -> EvalCase:
        """The request behind a reference layout: its objects, in/on relations and neighbours."""
        return cls(scene.instruction, scene.scene_type,
                   tuple(canonical_category(o.category) for o in scene.objects), stated_relations(scene),
                   tuple(sorted(adjacency_pairs(scene, k=1).elements())))


def adjacency_pairs(scene: Scene, k: int = 1) -> Counter:
    """Multiset of (category, neighbour category) over every object and the categories among its
    ``k`` nearest other objects (centre distance in the table plane, cm)."""
    objs = list(scene.objects)
    pairs: Counter = Counter()
    if len(objs) < 2:
        return pairs
    cats = [canonical_category(o.category) for o in objs]
    xy = np.array([o.center[:2] for o in objs])  # (n, 2)
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(objs)) * 1e12
    for i, row in enumerate(np.argsort(d, axis=1)[:, :k]):
        for b in {cats[j] for j in row}:
            pairs[(cats[i], b)] += 1
    return pairs


def _held(need: Counter, got: Counter) -> tuple[float, int]:
    """(share of ``need`` found in ``got`` as multisets, size of ``need``)."""
    n = sum(need.values())
    return (sum(min(c, got[key]) for key, c in need.items()) / n if n else 1.0), n


def stated_relations(scene: Scene) -> tuple[tuple[str, str, str], ...]:
    """(child category, relation, parent category) of every ``in``/``on`` edge of the hierarchy
    (built with :func:`physcene.graph.build_hierarchy` when the scene carries none)."""
    if not scene.has_hierarchy:
        scene = build_hierarchy(scene)
    by_id = scene.by_id()
    rels = []
    for o in scene.objects:
        if o.relation in ("in", "on") and o.parent not in (None, TABLE) and o.parent in by_id:
            parent = canonical_category(by_id[o.parent].category)
            rels.append((canonical_category(o.category), o.relation, parent))
    return tuple(sorted(rels))


# --------------------------------------------------------------------------------------------
# Layout statistics for LCR
# --------------------------------------------------------------------------------------------
LCR_FEATURES = ("coverage", "nn_spacing", "spread", "edge_fraction")
# Lower bounds on each feature's spread so a tiny reference set does not make LCR brittle.
_FEATURE_STD_FLOOR = {"coverage": 0.05, "nn_spacing": 0.03, "spread": 0.04, "edge_fraction": 0.12}
_EDGE_BAND_CM = 3.0


def layout_features(scene: Scene) -> dict[str, float]:
    """Density, spacing and spread of the table-level objects (those whose bottom is within 1 cm
    of the table): ``coverage`` = Σ footprint area / zone area; ``nn_spacing`` = mean
    nearest-neighbour centre distance / zone diagonal; ``spread`` = RMS distance of centres from
    their centroid / zone half-diagonal; ``edge_fraction`` = share of objects whose footprint lies
    within 3 cm of the zone boundary."""
    z = scene.zone
    base = [o for o in scene.objects if o.zmin < 1.0] or list(scene.objects)
    if not base:
        return {k: 0.0 for k in LCR_FEATURES}
    diag = math.hypot(z.width, z.depth)
    xy = np.array([o.center[:2] for o in base])  # (n, 2)
    coverage = sum(o.size[0] * o.size[1] for o in base) / (z.width * z.depth)
    if len(base) > 1:
        d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(base)) * 1e9
        nn = float(d.min(axis=1).mean()) / diag
    else:
        nn = 0.0
    spread = float(np.sqrt(((xy - xy.mean(axis=0)) ** 2).sum(axis=1).mean())) / (0.5 * diag)
    edge = 0
    for o in base:
        fp = o.footprint()
        gap = min(fp[:, 0].min() - z.xmin, z.xmax - fp[:, 0].max(),
                  fp[:, 1].min() - z.ymin, z.ymax - fp[:, 1].max())
        edge += gap < _EDGE_BAND_CM
    return {"coverage": float(coverage), "nn_spacing": nn, "spread": spread,
            "edge_fraction": edge / len(base)}


@dataclass
class LayoutStats:
    """Mean and standard deviation of :func:`layout_features` per scene type (and pooled)."""

    mean: dict[str, dict[str, float]] = field(default_factory=dict)
    std: dict[str, dict[str, float]] = field(default_factory=dict)

    @classmethod
    def fit(cls, scenes: Sequence[Scene]) -> LayoutStats:
        """Fit on reference scenes; a type's std is at least half the pooled std and a floor."""
        feats: dict[str, list[dict]] = {}
        for s in scenes:
            f = layout_features(s)
            feats.setdefault(s.scene_type, []).append(f)
            feats.setdefault("*", []).append(f)
        stats = cls()
        if not feats:
            return stats
        pooled_std = {k: float(np.std([f[k] for f in feats["*"]])) for k in LCR_FEATURES}
        for t, fs in feats.items():
            stats.mean[t] = {k: float(np.mean([f[k] for f in fs])) for k in LCR_FEATURES}
            stats.std[t] = {k: max(float(np.std([f[k] for f in fs])), 0.5 * pooled_std[k],
                                   _FEATURE_STD_FLOOR[k]) for k in LCR_FEATURES}
        return stats

    def z_scores(self, scene: Scene) -> dict[str, float]:
        key = scene.scene_type if scene.scene_type in self.mean else "*"
        if key not in self.mean:
            raise JudgeError("LayoutStats has no reference scenes: fit it on reference layouts first")
        f = layout_features(scene)
        return {k: (f[k] - self.mean[key][k]) / self.std[key][k] for k in LCR_FEATURES}


# --------------------------------------------------------------------------------------------
# The rule judge
# --------------------------------------------------------------------------------------------
def _to_score(quality: float) -> float:
    """Quality in [0, 1] -> score in [1, 10]."""
    return round(1.0 + 9.0 * float(np.clip(quality, 0.0, 1.0)), 3)


def _mean_min(values: Sequence[float]) -> float:
    """Half the mean, half the worst: one glaring object matters, as it does to a human judge."""
    return 0.5 * float(np.mean(values)) + 0.5 * float(np.min(values)) if len(values) else 1.0


_IDENTIFIABLE_FRACTION = 0.5


def _overlap_1d(a0, a1, b0, b1) -> float:
    return max(0.0, min(a1, b1) - max(a0, b0))


@dataclass
class RuleJudge:
    """Offline judge of the five criteria from the layout, the request and the physics facts.

    ``stats`` holds the reference distribution of layout features per scene type (LCR); fit it
    with :meth:`LayoutStats.fit` on the benchmark's reference layouts.
    """

    stats: LayoutStats
    size_tolerance: float = 1.0
    """OSR: a size within this many prior standard deviations (in log space) is not penalised."""
    penalty_scale: float = 4.0
    """PPI: score = 10 − 9·(1 − exp(−P / penalty_scale)) for penalty points P."""
    name: str = "rule"

    # -- criteria ---------------------------------------------------------------------------
    def consistency_with_task(self, scene: Scene, case: EvalCase) -> float:
        """CwT: q = present · (0.25 + 0.75·kept). *present*: share of requested objects in the
        layout (multiset over categories). *kept*: share of the request's functional relations
        that hold — its in/on relations (hierarchy of the generated layout) and its neighbour
        pairs (an object's reference neighbour category among its 2 nearest objects)."""
        if not case.requested:
            return 10.0
        want = Counter(case.requested)
        have = Counter(canonical_category(o.category) for o in scene.objects)
        present = sum(min(n, have[c]) for c, n in want.items()) / sum(want.values())
        return _to_score(present * (0.25 + 0.75 * self._relations_kept(scene, case)))

    @staticmethod
    def _adjacency_kept(scene: Scene, case: EvalCase) -> float:
        return _held(Counter(case.adjacency), adjacency_pairs(scene, k=2))[0]

    def _relations_kept(self, scene: Scene, case: EvalCase) -> float:
        if not len(scene):
            return 0.0
        got = Counter(stated_relations(scene)) if case.relations else Counter()
        rel, n_rel = _held(Counter(case.relations), got)
        adj, n_adj = _held(Counter(case.adjacency), adjacency_pairs(scene, k=2))
        return (rel * n_rel + adj * n_adj) / (n_rel + n_adj) if n_rel + n_adj else 1.0

    def object_size_reasonableness(self, scene: Scene) -> float:
        """OSR: per object with a size prior, the log-ratio of each dimension to the prior mean in
        units of the prior's relative std (floor ``SIZE_SIGMA_FLOOR``); beyond ``size_tolerance`` it costs
        exp(−½·excess²). Dimensions are compared sorted (objects may lie or stand either way)."""
        per_object = []
        for o in scene.objects:
            prior = CATEGORY_PRIORS.get(canonical_category(o.category))
            if prior is None:
                continue
            size, mean, sigma = prior.aligned(o.size)
            excess = np.maximum(np.abs(np.log(size / mean)) / sigma - self.size_tolerance, 0.0)
            per_object.append(float(np.exp(-0.5 * np.mean(excess**2))))
        return _to_score(_mean_min(per_object))

    def placement_plausibility(self, scene: Scene, physics: ScenePhysics) -> float:
        """PPI: penalty points P = 1.5 per floating object + Σ_pairs min(depth / 1 cm, 1) + 1 per
        object out of zone + min(table penetration / 1 cm, 1); score 10 − 9·(1 − e^(−P/4))."""
        p = 1.5 * len(physics.floating)
        p += sum(min(d / 1.0, 1.0) for _, _, d in physics.pair_depths)
        p += 1.0 * len(physics.out_of_zone)
        p += min(max(physics.table_penetration_cm, 0.0) / 1.0, 1.0)
        return round(10.0 - 9.0 * (1.0 - math.exp(-p / self.penalty_scale)), 3)

    def layout_coherence(self, scene: Scene, case: EvalCase | None = None) -> float:
        """LCR: z-scores of coverage, spacing, spread and edge fraction against the reference
        layouts of the scene type (a feature within 1 std costs nothing, beyond it
        exp(−½·mean(excess²))), times 0.4 + 0.6·(share of the request's neighbour pairs kept)
        when the request ``case`` is given."""
        if not len(scene):
            return 1.0
        z = self.stats.z_scores(scene)
        excess = np.array([max(abs(v) - 1.0, 0.0) for v in z.values()])
        spatial = math.exp(-0.5 * float(np.mean(excess**2)))
        if case is None:
            return _to_score(spatial)
        # Coherence: related objects stay together (keyboard by the monitor, fork by the plate).
        return _to_score(spatial * (0.4 + 0.6 * self._adjacency_kept(scene, case)))

    def object_visibility(self, scene: Scene) -> float:
        """OV: per object, visibility = 0 if it sits inside a non-container, else the larger of its
        top-view and front-view visible fractions (boxes covered by other boxes above it /
        in front of it; an open container does not hide its contents from the top), divided by
        0.5 and capped at 1 (half in sight is identifiable); OV = 1 + 9·(½ mean + ½ min)."""
        objs = list(scene.objects)
        if not objs:
            return 1.0
        boxes = [o.aabb() for o in objs]  # [xmin, xmax, ymin, ymax, zmin, zmax]
        vis = []
        for a, (o, ba) in enumerate(zip(objs, boxes)):
            area_top = (ba[1] - ba[0]) * (ba[3] - ba[2])
            area_front = (ba[1] - ba[0]) * (ba[5] - ba[4])
            top_cover, front_cover, enclosed = 0.0, 0.0, False
            for b, (p, bb) in enumerate(zip(objs, boxes)):
                if a == b:
                    continue
                ox = _overlap_1d(ba[0], ba[1], bb[0], bb[1])
                oy = _overlap_1d(ba[2], ba[3], bb[2], bb[3])
                oz = _overlap_1d(ba[4], ba[5], bb[4], bb[5])
                container = _role(p.category) == "container"
                inside = (ox * oy >= 0.9 * area_top and oz >= 0.9 * (ba[5] - ba[4])
                          and p.volume() > o.volume())
                if inside and not container:
                    enclosed = True
                    break
                if bb[5] > ba[5] + 0.5 and not (inside and container):
                    top_cover += ox * oy
                if bb[2] < ba[2] - 0.5:  # in front (toward the viewer at −y)
                    front_cover += ox * oz
            if enclosed:
                vis.append(0.0)
                continue
            v_top = 1.0 - min(top_cover / area_top, 1.0) if area_top > 0 else 1.0
            v_front = 1.0 - min(front_cover / area_front, 1.0) if area_front > 0 else 1.0
            # Half an object in sight is enough to identify it (Prompt 5: "identifiable in at
            # least one of the views").
            vis.append(min(1.0, max(v_top, v_front) / _IDENTIFIABLE_FRACTION))
        return _to_score(_mean_min(vis))

    # -- entry point ------------------------------------------------------------------------
    def score(self, scene: Scene, case: EvalCase, physics: ScenePhysics) -> dict:
        """The five criteria and their mean for one scene."""
        out = {"CwT": self.consistency_with_task(scene, case),
               "OSR": self.object_size_reasonableness(scene),
               "PPI": self.placement_plausibility(scene, physics),
               "LCR": self.layout_coherence(scene, case),
               "OV": self.object_visibility(scene)}
        out["avg"] = round(float(np.mean([out[c] for c in CRITERIA])), 4)
        return out
