"""Benchmark metrics of the paper (appendix "Metric") over batches of scored scenes.

Everything here works on :class:`ScenePhysics` records, one per scene, built from the physics
engine's :class:`~physcene.physics.Score` by :func:`physics_from_score` (or by hand in tests):
per-pair penetration depths (cm), floating objects and objects outside the placement zone.

- ACR = mean over scenes of 2/(N(N−1)) · #{i<j : pen(i,j) > t}   (scenes with N < 2 count 0)
- SCR = mean over scenes of 1[∃ i<j : pen(i,j) > t]
- QPR(τ) = mean over scenes of 1[judge average ≥ τ] · 1[no pair with pen > t0]  (t0 = 0 cm)

Rates are fractions in [0, 1]; reports print them as percentages.
"""

from __future__ import annotations

import math
import re
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from physcene.data.splits import level_of  # one definition of the levels, shared with the data
from physcene.relations import relation_preservation
from physcene.scene import ZONE_TOLERANCE_CM, Scene, zone_overshoot

__all__ = ["CRITERIA", "DIFFICULTY_LEVELS", "THRESHOLDS_CM", "ScenePhysics", "SceneResult", "breakdown",
           "collision_rates", "deepest_pairs", "diversity", "floating_rate", "level_of",
           "measure_reference", "out_of_zone", "out_of_zone_rate", "paired_collisions", "parse_error_kinds",
           "physics_from_score", "qpr", "relation_preservation_rate", "summarize"]

# The paper's GPT-score criteria, in table order.
CRITERIA = ("CwT", "OSR", "PPI", "LCR", "OV")
# Penetration thresholds of the threshold-robustness table (appendix, Table "SCR under varying
# collision thresholds"), cm.
THRESHOLDS_CM = (0.0, 0.5, 1.0)
QPR_TAUS = (7, 8, 9)
# Difficulty levels by object count (paper Table "Benchmark statistics"): 1-4, 5-8, 9-12, 13-16, 17+.
DIFFICULTY_LEVELS = (1, 2, 3, 4, 5)


@dataclass(frozen=True)
class ScenePhysics:
    """Physical facts about one scene (what the metrics need from the engine)."""

    n_objects: int
    pair_depths: tuple[tuple[int, int, float], ...] = ()
    """(i, j, depth_cm) for every pair with penetration depth > 0 (i < j)."""
    floating: tuple[int, ...] = ()
    """Indices of objects with no support below them."""
    out_of_zone: tuple[int, ...] = ()
    """Indices of objects whose footprint leaves the placement zone."""
    table_penetration_cm: float = 0.0
    """Deepest penetration of any object below the table plane z = 0, cm."""

    def colliding_pairs(self, threshold_cm: float = 0.0) -> int:
        """Number of pairs deeper than ``threshold_cm``."""
        return sum(1 for _, _, d in self.pair_depths if d > threshold_cm)

    def collision_free(self, threshold_cm: float = 0.0) -> bool:
        return self.colliding_pairs(threshold_cm) == 0

    def to_dict(self) -> dict:
        return {"n_objects": self.n_objects, "pair_depths": [list(p) for p in self.pair_depths],
                "floating": list(self.floating), "out_of_zone": list(self.out_of_zone),
                "table_penetration_cm": self.table_penetration_cm}

    @classmethod
    def from_dict(cls, d: dict) -> ScenePhysics:
        return cls(int(d["n_objects"]), tuple((int(i), int(j), float(x)) for i, j, x in d["pair_depths"]),
                   tuple(d.get("floating", ())), tuple(d.get("out_of_zone", ())),
                   float(d.get("table_penetration_cm", 0.0)))


def out_of_zone(scene: Scene, tolerance_cm: float = ZONE_TOLERANCE_CM) -> tuple[int, ...]:
    """Indices of objects whose yawed footprint leaves the zone by more than ``tolerance_cm``."""
    if not scene.objects:
        return ()
    boxes = np.array([(*o.center[:2], *o.size[:2], o.yaw) for o in scene.objects], dtype=np.float64)
    z = scene.zone
    zone = np.array([z.xmin, z.xmax, z.ymin, z.ymax])
    past = zone_overshoot(boxes[:, :2], boxes[:, 2:4], boxes[:, 4], zone)
    return tuple(np.flatnonzero(past > tolerance_cm).tolist())


def physics_from_score(scenes: Sequence[Scene], score) -> list[ScenePhysics]:
    """One :class:`ScenePhysics` per scene from an engine ``Score`` (``pairs``, ``floating``,
    ``table_penetration``) computed on the same scenes in the same order."""
    table = np.asarray(score.table_penetration.detach().cpu() if hasattr(score.table_penetration, "detach")
                       else score.table_penetration, dtype=np.float64).reshape(-1)
    out = []
    for s, scene in enumerate(scenes):
        pairs = tuple(sorted((min(int(i), int(j)), max(int(i), int(j)), float(d))
                             for i, j, d in score.pairs[s] if float(d) > 0))
        out.append(ScenePhysics(len(scene), pairs, tuple(int(i) for i in score.floating[s]),
                                out_of_zone(scene), float(table[s]) if s < table.size else 0.0))
    return out


def collision_rates(scenes: Sequence[ScenePhysics], thresholds: Iterable[float] = THRESHOLDS_CM) -> dict:
    """SCR and ACR (fractions) at each penetration threshold (cm): ``{t: {"SCR": .., "ACR": ..}}``."""
    out = {}
    for t in thresholds:
        if not scenes:
            out[float(t)] = {"SCR": float("nan"), "ACR": float("nan")}
            continue
        scr = np.mean([0.0 if s.collision_free(t) else 1.0 for s in scenes])
        acr = np.mean([s.colliding_pairs(t) * 2.0 / (s.n_objects * (s.n_objects - 1))
                       if s.n_objects > 1 else 0.0 for s in scenes])
        out[float(t)] = {"SCR": float(scr), "ACR": float(acr)}
    return out


def floating_rate(scenes: Sequence[ScenePhysics]) -> dict:
    """Fraction of objects that float and fraction of scenes with at least one floating object."""
    n_obj = sum(s.n_objects for s in scenes)
    return {"objects": sum(len(s.floating) for s in scenes) / n_obj if n_obj else float("nan"),
            "scenes": float(np.mean([bool(s.floating) for s in scenes])) if scenes else float("nan")}


def out_of_zone_rate(scenes: Sequence[ScenePhysics]) -> dict:
    """Fraction of objects outside the zone and fraction of scenes with one."""
    n_obj = sum(s.n_objects for s in scenes)
    return {"objects": sum(len(s.out_of_zone) for s in scenes) / n_obj if n_obj else float("nan"),
            "scenes": float(np.mean([bool(s.out_of_zone) for s in scenes])) if scenes else float("nan")}


def qpr(judge_averages: Sequence[float], scenes: Sequence[ScenePhysics], taus: Iterable[float] = QPR_TAUS,
        threshold_cm: float = 0.0) -> dict:
    """QPR(τ) for each τ: the fraction of scenes whose judge average is ≥ τ AND that have no pair
    deeper than ``threshold_cm``. A missing judge average (NaN: the judge failed) never passes."""
    if len(judge_averages) != len(scenes):
        raise ValueError(f"qpr: {len(judge_averages)} judge averages for {len(scenes)} scenes")
    avg = np.asarray(judge_averages, dtype=np.float64)
    free = np.array([s.collision_free(threshold_cm) for s in scenes], dtype=bool)
    with np.errstate(invalid="ignore"):
        return {float(t): float(np.mean((avg >= t) & free)) if len(avg) else float("nan") for t in taus}


def relation_preservation_rate(before: Sequence[Scene], after: Sequence[Scene]) -> dict:
    """Mean share of ``in``/``on`` (and ``near``) relations of each ``before`` layout that still hold
    in the matching ``after`` layout (:func:`physcene.relations.relation_preservation`, per pair)."""
    if len(before) != len(after):
        raise ValueError(f"relation_preservation_rate: {len(before)} layouts before, {len(after)} after")
    kept = [relation_preservation(b, a) for b, a in zip(before, after)]
    return {"in_on_kept": float(np.mean([k["in_on_kept"] for k in kept])) if kept else float("nan"),
            "near_kept": float(np.mean([k["near_kept"] for k in kept])) if kept else float("nan")}


def diversity(scenes: Sequence[Scene]) -> dict:
    """The appendix's diversity figures: distinct asset types (categories; and asset ids where the
    layouts name them) and the standard deviation of object centres along x and y (cm), pooled
    over every object of every scene."""
    cats = {o.category for s in scenes for o in s.objects}
    assets = {o.asset_id for s in scenes for o in s.objects if o.asset_id}
    xy = np.array([o.center[:2] for s in scenes for o in s.objects], dtype=np.float64).reshape(-1, 2)
    std = xy.std(axis=0) if len(xy) else np.array([float("nan")] * 2)
    return {"asset_types": len(cats), "asset_ids": len(assets), "pos_std_x": float(std[0]),
            "pos_std_y": float(std[1]), "n_objects": int(len(xy))}


@dataclass
class SceneResult:
    """Everything measured about one generated scene."""

    id: str
    scene_type: str
    level: int
    physics: ScenePhysics
    judge: dict = field(default_factory=dict)
    """Criterion name (``CwT`` ...) -> score 1..10; ``avg``; optional ``error`` when the judge failed."""
    extra: dict = field(default_factory=dict)
    """Optional columns: ``stable`` (bool, from physcene.settle), ``relation_preservation`` (float),
    ``parse_error`` (str) ..."""

    @property
    def judge_avg(self) -> float:
        return float(self.judge.get("avg", float("nan")))

    def to_dict(self) -> dict:
        return {"id": self.id, "scene_type": self.scene_type, "level": self.level,
                "physics": self.physics.to_dict(), "judge": self.judge, "extra": self.extra}

    @classmethod
    def from_dict(cls, d: dict) -> SceneResult:
        return cls(d["id"], d["scene_type"], int(d["level"]), ScenePhysics.from_dict(d["physics"]),
                   dict(d.get("judge", {})), dict(d.get("extra", {})))


def _mean(values) -> float:
    vals = [float(v) for v in values if v is not None and np.isfinite(float(v))]
    return float(np.mean(vals)) if vals else float("nan")


def summarize(results: Sequence[SceneResult], thresholds: Iterable[float] = THRESHOLDS_CM,
              taus: Iterable[float] = QPR_TAUS) -> dict:
    """The table row of one method: QPR(τ), mean criteria and their average, SCR/ACR at every
    threshold, floating and out-of-zone rates, and the optional columns present in ``extra``."""
    # Unparsable outputs and failed generations fail QPR (no judge average) but have no geometry
    # for the physics rates.
    parsed = [r for r in results if not (r.extra.get("parse_error") or r.extra.get("generation_error"))]
    phys = [r.physics for r in parsed]
    row = {"n": len(results),
           "QPR": qpr([r.judge_avg for r in results], [r.physics for r in results], taus),
           "judge": {c: _mean(r.judge.get(c) for r in parsed) for c in (*CRITERIA, "avg")},
           "judge_failures": sum(1 for r in parsed if r.judge.get("error")),
           "collision": collision_rates(phys, thresholds),
           "floating": floating_rate(phys),
           "out_of_zone": out_of_zone_rate(phys)}
    stable = [r.extra["stable"] for r in results if "stable" in r.extra]
    if stable:
        row["stability_rate"] = float(np.mean(stable))
    rel = [r.extra["relation_preservation"] for r in results if "relation_preservation" in r.extra]
    if rel:
        row["relation_preservation"] = _mean(rel)
    failed = sum(1 for r in results if r.extra.get("generation_error"))
    if failed:
        row["generation_failures"] = failed
    reasons = [r.extra["parse_error"] for r in results if r.extra.get("parse_error")]
    if reasons:
        row["parse_errors"] = len(reasons)
        row["parse_error_kinds"] = parse_error_kinds(reasons)
    return row


def paired_collisions(first: Sequence[SceneResult], second: Sequence[SceneResult],
                      threshold_cm: float = 0.0) -> dict:
    """Two methods' layouts of the same scenes compared scene by scene (matched by id; a scene counts
    when both parsed it): how many collide in both, in the first only, in the second only and in
    neither, both SCRs on those scenes, ``difference`` (second − first) and ``p_value``, the exact
    two-sided McNemar test: the chance, were both methods equally likely to collide on a scene, of a
    split of the discordant scenes at least this uneven (a binomial at 1/2). Pairing removes the draw of
    scenes from the comparison, so it separates much smaller differences than two unpaired SCRs."""
    def collides(results):
        return {r.id: not r.physics.collision_free(threshold_cm) for r in results
                if not (r.extra.get("parse_error") or r.extra.get("generation_error"))}

    a, b = collides(first), collides(second)
    ids = [i for i in a if i in b]
    both = sum(a[i] and b[i] for i in ids)
    only_first = sum(a[i] and not b[i] for i in ids)
    only_second = sum(b[i] and not a[i] for i in ids)
    discordant, n = only_first + only_second, len(ids)
    tail = sum(math.comb(discordant, k) for k in range(min(only_first, only_second) + 1))
    p_value = min(1.0, 2 * tail / 2 ** discordant) if discordant else 1.0
    return {"scenes": n, "both": both, "only_first": only_first, "only_second": only_second,
            "neither": n - both - only_first - only_second,
            "scr_first": (both + only_first) / n if n else float("nan"),
            "scr_second": (both + only_second) / n if n else float("nan"),
            "difference": (only_second - only_first) / n if n else float("nan"), "p_value": p_value}


def parse_error_kinds(reasons: Iterable[str], top: int = 8) -> list[tuple[str, int]]:
    """The most common kinds of ParseError reason, most frequent first, as (kind, count).

    A kind is the reason with quoted names and numbers blanked (``object '3_cup_1', field 'size':
    ... got [1.0, -2.0, 3.0]`` -> ``object '…', field '…': ... got [#, #, #]``), so a model's
    failure modes (truncation, unknown parent, bad extents, ...) group together.
    """
    counts: dict[str, int] = defaultdict(int)
    for reason in reasons:
        kind = re.sub(r"'[^']*'|\"[^\"]*\"", "'…'", str(reason))
        kind = re.sub(r"-?\d+(\.\d+)?(e[-+]?\d+)?", "#", kind)
        counts[kind[:120]] += 1
    return sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))[:top]


def breakdown(results: Sequence[SceneResult], key: Callable[[SceneResult], object] | str) -> dict:
    """:func:`summarize` per group: ``key`` is ``"scene_type"``, ``"level"`` or a function."""
    get = (lambda r: getattr(r, key)) if isinstance(key, str) else key
    groups: dict = defaultdict(list)
    for r in results:
        groups[get(r)].append(r)
    return {k: summarize(v) for k, v in sorted(groups.items(), key=lambda kv: str(kv[0]))}


def deepest_pairs(scenes: list[Scene], engine, batch_size: int = 32, *,
                  progress: bool = False) -> list[float]:
    """Each scene's deepest penetrating pair (cm; 0.0 when it has none: collision-free at 0 cm), scored
    with ``engine`` in batches of ``batch_size``; ``progress``: a bar on stderr over the batches."""
    from tqdm.auto import tqdm

    depths = []
    for start in tqdm(range(0, len(scenes), batch_size), desc="measure", disable=not progress):
        chunk = scenes[start:start + batch_size]
        depths += [max((d for _, _, d in ph.pair_depths), default=0.0)
                   for ph in physics_from_score(chunk, engine.score(chunk))]
    return depths


def measure_reference(scenes: list[Scene], engine=None) -> dict:
    """SCR/ACR at 0 / 0.5 / 1.0 cm and floating rates of ``scenes`` with the engine (one batch)."""
    from physcene.physics import PhysicsEngine  # here: Warp loads only when a split is measured

    engine = engine or PhysicsEngine()
    score = engine.score(scenes)
    phys = physics_from_score(scenes, score)
    rates = collision_rates(phys)
    return {
        "collision": {f"{t:g}cm": v for t, v in rates.items()},
        "floating": floating_rate(phys),
        "per_scene_pairs": [len(p) for p in score.pairs],
    }
