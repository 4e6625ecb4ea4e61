"""Annotation noise that mimics human-made layouts (centimetres), recorded per scene.

MesaTask-10k layouts were placed by hand; the paper measures 81.5 % of its reference scenes with
at least one interpenetrating pair and 8.19 % of all pairs colliding on average. A clean
synthetic layout is turned into such a layout by four kinds of error, each configurable:

- ``position``: every table-level unit slides by N(0, σ) in x and y (its subtree moves rigidly);
- ``size``: every object's extents are off by a relative N(0, σ) per axis (stacks are not
  re-seated: a support that grew swallows the bottom of what is on it, one that shrank leaves
  it hovering);
- ``interpenetration``: a number of neighbouring table-level units are pushed into each other
  by a depth drawn from ``depth_cm`` (the dense-clutter error of hand placement);
- ``support``: children sunk into (``sink``) or hovering over (``hover``) their support.

A fraction of scenes (``careful_by_level``, per difficulty level) is annotated carefully: only
position jitter that keeps every footprint apart and hovering are applied there. Every change is
listed in the returned record (``NoiseRecord.as_dict()``), so a user can undo or filter it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from physcene.scene import TABLE, Scene, SceneObject

__all__ = ["NoiseConfig", "NoiseRecord", "apply_noise"]


@dataclass(frozen=True, kw_only=True)
class NoiseConfig:
    """Magnitudes of each noise kind (cm unless stated); ``configs/data.yaml`` ``noise:``."""

    enabled: bool = True
    """False: layouts are written clean."""
    careful_by_level: tuple[float, float, float, float, float] = (0.45, 0.27, 0.1, 0.0, 0.0)
    """Probability that a scene of level 1..5 is annotated carefully (no interpenetration)."""
    position_sigma_cm: float = 0.35
    """σ of the x/y slide of each table-level unit."""
    size_sigma: float = 0.02
    """Relative σ of each object's extents (per axis)."""
    pair_rate: float = 0.6
    """Expected interpenetrating neighbour pairs per table-level unit in a careless scene."""
    depth_cm: tuple[float, float] = (1.8, 5.5)
    """Range of the push depth of an interpenetrating pair."""
    align: float = 0.5
    """Fraction of the across-push offset the pushed unit slides toward its partner."""
    neighbour_cm: float = 12.0
    """Units whose footprints are closer than this are neighbours."""
    sink_prob: float = 0.2
    """Probability that a stacked child (``on``/``in``) is sunk into its support."""
    sink_cm: tuple[float, float] = (0.5, 2.0)
    """Range of the sink depth."""
    hover_prob: float = 0.08
    """Probability that an object hovers over its support (table or object)."""
    hover_cm: tuple[float, float] = (0.1, 1.2)
    """Range of the hover height."""


@dataclass
class NoiseRecord:
    """What was done to one scene (all lengths cm)."""

    careful: bool = False
    position_sigma_cm: float = 0.0
    size_sigma: float = 0.0
    interpenetration: list[dict] = field(default_factory=list)
    sunk: list[dict] = field(default_factory=list)
    hover: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def _subtree(objects: list[SceneObject], root: str) -> list[int]:
    """Indices of ``root`` and everything stacked on or in it (by ``parent``)."""
    children: dict[str, list[int]] = {}
    for k, o in enumerate(objects):
        children.setdefault(o.parent or TABLE, []).append(k)
    index = {o.instance_id: k for k, o in enumerate(objects)}
    out, todo = [], [index[root]]
    while todo:
        k = todo.pop()
        out.append(k)
        todo.extend(children.get(objects[k].instance_id, []))
    return out


def _aabb(o: SceneObject, center: np.ndarray, size: np.ndarray) -> np.ndarray:
    return SceneObject(o.instance_id, o.category, tuple(center), tuple(size), o.yaw).aabb()


def _gap(a: np.ndarray, b: np.ndarray) -> tuple[float, int, float]:
    """(footprint distance, axis 0/1 of separation, sign of b relative to a) of two AABBs."""
    gx = max(b[0] - a[1], a[0] - b[1])
    gy = max(b[2] - a[3], a[2] - b[3])
    if gx >= gy:
        return gx, 0, 1.0 if b[0] >= a[1] else -1.0
    return gy, 1, 1.0 if b[2] >= a[3] else -1.0


def apply_noise(
    scene: Scene, level: int, rng: np.random.Generator, config: NoiseConfig | None = None
) -> tuple[Scene, NoiseRecord]:
    """A noisy copy of a clean ``scene`` (with its intended hierarchy) and the record of changes.

    ``scene`` must carry ``parent``/``relation`` on every object (the generator's hierarchy);
    the result keeps them (they describe the intent, not the noisy geometry).
    """
    config = config or NoiseConfig()
    record = NoiseRecord()
    if not config.enabled or len(scene) == 0:
        return scene, record
    objs = list(scene.objects)
    ids = [o.instance_id for o in objs]
    centers = np.array([o.center for o in objs], dtype=np.float64)  # (N, 3)
    sizes = np.array([o.size for o in objs], dtype=np.float64)  # (N, 3)
    roots = [k for k, o in enumerate(objs) if o.parent in (None, TABLE)]
    subtrees = {k: _subtree(objs, ids[k]) for k in roots}
    record.careful = bool(rng.random() < config.careful_by_level[min(max(level, 1), 5) - 1])

    # 1. position jitter of table-level units (careful scenes: only where footprints stay apart)
    record.position_sigma_cm = config.position_sigma_cm
    shifts = rng.normal(0.0, config.position_sigma_cm, size=(len(roots), 2))
    shifts = np.clip(shifts, -3 * config.position_sigma_cm, 3 * config.position_sigma_cm)
    for k, d in zip(roots, shifts):
        moved = centers.copy()
        moved[subtrees[k], :2] += d
        if record.careful and _any_overlap(objs, moved, sizes, roots):
            continue
        centers = moved

    if not record.careful:
        # 2. size jitter (stacks not re-seated)
        record.size_sigma = config.size_sigma
        sizes = sizes * np.clip(1.0 + rng.normal(0.0, config.size_sigma, size=sizes.shape), 0.9, 1.1)
        # bottoms of table-level objects stay on the table
        for k in roots:
            centers[k, 2] = 0.5 * sizes[k, 2]
        # 3. interpenetration of neighbouring units
        n_pairs = int(rng.poisson(config.pair_rate * len(roots)))
        n_pairs = max(1, n_pairs) if len(roots) >= 2 else 0
        boxes = {k: _aabb(objs[k], centers[k], sizes[k]) for k in roots}
        candidates = []
        for a_i, a in enumerate(roots):
            for b in roots[a_i + 1 :]:
                gap, axis, sign = _gap(boxes[a], boxes[b])
                candidates.append((a, b, gap, axis, sign))
        # neighbours first; a sparse scene falls back to its closest pair
        near = [c for c in candidates if c[2] < config.neighbour_cm] or sorted(
            candidates, key=lambda c: c[2]
        )[:1]
        candidates = near
        picks = rng.permutation(len(candidates))[:n_pairs] if candidates else []
        for p in picks:
            a, b, _, axis, sign = candidates[int(p)]
            gap, axis, sign = _gap(_aabb(objs[a], centers[a], sizes[a]), _aabb(objs[b], centers[b], sizes[b]))
            depth = float(rng.uniform(*config.depth_cm))
            mover = b if sizes[b, :2].prod() <= sizes[a, :2].prod() else a
            direction = -sign if mover == b else sign
            step = max(gap, 0.0) + depth if gap > 0 else depth
            centers[subtrees[mover], axis] += direction * step
            # slide part of the way toward the partner across the push, so the boxes' overlap
            # lies near the centres' line where round shapes really meet
            other = a if mover == b else b
            across = 1 - axis
            centers[subtrees[mover], across] += config.align * (
                centers[other, across] - centers[mover, across]
            )
            record.interpenetration.append(
                {
                    "a": ids[a],
                    "b": ids[b],
                    "moved": ids[mover],
                    "axis": "xy"[axis],
                    "depth_cm": round(depth, 4),
                }
            )
        # 4a. sunk children
        for k, o in enumerate(objs):
            if o.parent not in (None, TABLE) and rng.random() < config.sink_prob:
                depth = float(rng.uniform(*config.sink_cm))
                centers[_subtree(objs, ids[k]), 2] -= depth
                record.sunk.append({"id": ids[k], "support": o.parent, "depth_cm": round(depth, 4)})
    # 4b. hovering objects (floating, no interpenetration)
    for k in range(len(objs)):
        if rng.random() < config.hover_prob:
            height = float(rng.uniform(*config.hover_cm))
            centers[_subtree(objs, ids[k]), 2] += height
            record.hover.append(
                {"id": ids[k], "support": objs[k].parent or TABLE, "height_cm": round(height, 4)}
            )
    noisy = [
        o.moved(center=tuple(float(v) for v in c), size=tuple(float(v) for v in s))
        for o, c, s in zip(objs, centers, sizes)
    ]
    return scene.with_objects(noisy), record


def _any_overlap(objs: list[SceneObject], centers: np.ndarray, sizes: np.ndarray, roots: list[int]) -> bool:
    boxes = [_aabb(objs[k], centers[k], sizes[k]) for k in roots]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            a, b = boxes[i], boxes[j]
            if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                return True
    return False
