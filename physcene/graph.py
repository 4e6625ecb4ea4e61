"""The hierarchical scene graph (HSG): who stands in / on what, and the anchor-first order.

Relations (paper appendix A.1, docs/scene_language.md "Hierarchical scene graph"), priority in ≻ on ≻ near:

- ``in``  (A in B): vol(B)/vol(A) ≥ ``in_volume_ratio``, footprint overlap |A∩B|xy/|A|xy ≥
  ``in_footprint_overlap`` (yaw-aware polygon overlap), and at least ``in_height_fraction`` of
  A's height inside B's z-range. Several containers: the innermost (smallest volume) wins.
  With ``in_requires_container`` (default), B must also be able to hold things: a category known
  to :data:`physcene.assets.CATEGORY_PRIORS` must have the role ``container`` (a knife is never
  *in* a cutting board, a lemon never *in* an orange); categories the priors do not know keep the
  geometric rule alone (:func:`container_role`).
- ``on``  (A on B): |zmin(A) − zmax(B)| < ``on_gap_cm`` and |A∩B|xy/|A|xy > ``on_footprint_overlap``.
  Several supports: the highest top wins (then the larger overlap).
- ``near``: otherwise; the parent is the table (:data:`~physcene.scene.TABLE`). Its reference is the
  nearest table-level object placed before it in the anchor order (:func:`near_references`).

The result is always a forest: objects are attached bottom-up, and an edge that would close a
cycle (possible only for degenerate, sub-centimetre boxes) is skipped for the next candidate.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

from shapely.geometry import Polygon

from physcene.config import load_dataclass
from physcene.scene import TABLE, Scene, SceneObject

__all__ = [
    "GraphConfig",
    "anchor_order",
    "build_hierarchy",
    "can_contain",
    "container_role",
    "ensure_hierarchy",
    "footprint_overlap",
    "near_direction",
    "near_references",
    "relation_candidates",
]

NEAR_DIRECTIONS = ("left of", "right of", "in front of", "behind")


@dataclass(frozen=True, kw_only=True)
class GraphConfig:
    """Thresholds of the relation tests (``configs/graph.yaml``)."""

    in_volume_ratio: float = 1.5
    """vol(container) / vol(content) must be at least this."""
    in_footprint_overlap: float = 0.9
    """|content ∩ container|xy / |content|xy must be at least this."""
    in_height_fraction: float = 0.5
    """At least this fraction of the content's height lies inside the container's z-range."""
    on_gap_cm: float = 1.0
    """|zmin(top) − zmax(support)| must be below this (cm)."""
    on_footprint_overlap: float = 0.3
    """|top ∩ support|xy / |top|xy must exceed this."""
    in_requires_container: bool = True
    """``in`` only into a parent whose category can contain (:func:`can_contain`); False = the
    purely geometric rule (docs/scene_language.md)."""

    @classmethod
    def load(cls, overrides: Sequence[str] = ()) -> GraphConfig:
        """Read ``configs/graph.yaml`` with ``key=value`` overrides."""
        return load_dataclass(cls, "graph", list(overrides))


@functools.lru_cache(maxsize=4096)
def container_role(category: str) -> str | None:
    """The hierarchy role (``container``/``support``/``object``) of ``category``, None if unknown.

    The name is resolved as the asset library resolves it, without its fuzzy last resort:
    lower_snake_case singular (:func:`physcene.assets.normalise_category`), then
    :data:`~physcene.assets.CATEGORY_ALIASES`, then the longest trailing phrase (the head noun:
    ``ceramic_bowl`` -> ``bowl``, ``kitchen_knife`` -> ``knife``). A name none of these finds in
    :data:`~physcene.assets.CATEGORY_PRIORS` (an arbitrary MesaTask mesh category) is unknown.
    """
    # Imported here: physcene.assets pulls in trimesh (~1 s), which parsing CTRC text never needs.
    from physcene.assets.categories import CATEGORY_ALIASES, CATEGORY_PRIORS
    from physcene.assets.mesh_folder import normalise_category

    key = normalise_category(category)
    words = key.split("_") if key else []
    for size in range(len(words), 0, -1):  # the whole name first, then ever shorter tails
        tail = "_".join(words[-size:])
        for candidate in (tail, CATEGORY_ALIASES.get(tail)):
            if candidate in CATEGORY_PRIORS:
                return CATEGORY_PRIORS[candidate].role
    return None


def can_contain(category: str) -> bool:
    """Whether an object of ``category`` may be an ``in`` parent under ``in_requires_container``:
    its prior's role is ``container``, or the priors do not know the category."""
    return container_role(category) in ("container", None)


def _polygon(o: SceneObject) -> Polygon:
    return Polygon(o.footprint())


def footprint_overlap(a: SceneObject, b: SceneObject) -> float:
    """|A∩B|xy / |A|xy of the yawed footprints (0..1)."""
    return _overlap(a, b)


def _axis_aligned(o: SceneObject) -> bool:
    return abs(math.sin(2.0 * o.yaw)) < 1e-12  # yaw a multiple of 90 degrees


def _overlap(a: SceneObject, b: SceneObject, ba=None, bb=None, pa: Polygon | None = None,
             pb: Polygon | None = None) -> float:
    """|A∩B|xy / |A|xy; ``ba``/``bb`` are the objects' aabb() and ``pa``/``pb`` their footprint
    polygons when the caller has them cached."""
    ba = a.aabb() if ba is None else ba
    bb = b.aabb() if bb is None else bb
    ix = min(ba[1], bb[1]) - max(ba[0], bb[0])
    iy = min(ba[3], bb[3]) - max(ba[2], bb[2])
    if ix <= 0.0 or iy <= 0.0:
        return 0.0  # cheap reject before the polygon clip
    if _axis_aligned(a) and _axis_aligned(b):
        return ix * iy / (a.size[0] * a.size[1])
    pa = pa if pa is not None else _polygon(a)
    pb = pb if pb is not None else _polygon(b)
    return float(pa.intersection(pb).area) / (a.size[0] * a.size[1])


def relation_candidates(scene: Scene, config: GraphConfig | None = None) -> dict[str, list[tuple[str, str]]]:
    """For every object, the (parent_id, relation) candidates in preference order.

    ``in`` candidates (innermost container first) come before ``on`` candidates (highest support
    first); an object with none is ``near`` the table. With ``config.in_requires_container`` only
    objects that :func:`can_contain` are ``in`` candidates.
    """
    config = config or GraphConfig()
    objs = list(scene.objects)
    boxes = [o.aabb().tolist() for o in objs]
    volumes = [o.volume() for o in objs]
    holds = [not config.in_requires_container or can_contain(o.category) for o in objs]
    polys: dict[int, Polygon] = {}

    def poly(k: int) -> Polygon:
        if k not in polys:
            polys[k] = _polygon(objs[k])
        return polys[k]

    out: dict[str, list[tuple[str, str]]] = {}
    for i, a in enumerate(objs):
        ins, ons = [], []
        a_zmin, a_zmax, a_h = boxes[i][4], boxes[i][5], a.size[2]
        for j, b in enumerate(objs):
            if i == j:
                continue
            # The z tests are cheap; the footprint overlap is computed only when one of them holds.
            b_zmin, b_zmax = boxes[j][4], boxes[j][5]
            inside_z = min(a_zmax, b_zmax) - max(a_zmin, b_zmin)
            could_in = (holds[j] and volumes[j] >= config.in_volume_ratio * volumes[i]
                        and inside_z >= config.in_height_fraction * a_h)
            # A support starts below what stands on it: without this, of two stacked objects both
            # thinner than on_gap_cm, the lower one would also read as "on" the upper one.
            could_on = abs(a_zmin - b_zmax) < config.on_gap_cm and b_zmin < a_zmin
            if not (could_in or could_on):
                continue
            exact = _axis_aligned(a) and _axis_aligned(b)
            overlap = _overlap(a, b, boxes[i], boxes[j], None if exact else poly(i),
                               None if exact else poly(j))
            if could_in and overlap >= config.in_footprint_overlap:
                ins.append((volumes[j], b.instance_id))
            if could_on and overlap > config.on_footprint_overlap:
                ons.append((-b_zmax, -overlap, b.instance_id))
        out[a.instance_id] = ([(iid, "in") for _, iid in sorted(ins)]
                              + [(iid, "on") for *_, iid in sorted(ons)])
    return out


def build_hierarchy(scene: Scene, config: GraphConfig | None = None) -> Scene:
    """``scene`` with every object's ``parent`` (an instance id or TABLE) and ``relation`` set.

    The hierarchy is recomputed from geometry (any existing one is replaced); it is a forest.
    """
    candidates = relation_candidates(scene, config)
    parent: dict[str, str] = {}

    def is_ancestor(node: str, of: str) -> bool:
        while of in parent:
            of = parent[of]
            if of == node:
                return True
        return False

    relation: dict[str, str] = {}
    # Bottom-up, so a support gets its own parent before anything is stacked on it.
    for o in sorted(scene.objects, key=lambda o: (o.zmin, o.zmax, o.instance_id)):
        for pid, rel in candidates[o.instance_id]:
            if pid != o.instance_id and not is_ancestor(o.instance_id, pid):
                parent[o.instance_id], relation[o.instance_id] = pid, rel
                break
        else:
            parent[o.instance_id], relation[o.instance_id] = TABLE, "near"
    return scene.with_objects(o.moved(parent=parent[o.instance_id], relation=relation[o.instance_id])
                              for o in scene.objects)


def ensure_hierarchy(scene: Scene, config: GraphConfig | None = None) -> Scene:
    """``scene`` itself if every object already has a parent, else :func:`build_hierarchy`."""
    return scene if scene.has_hierarchy else build_hierarchy(scene, config)


def near_direction(a: SceneObject, b: SceneObject) -> str:
    """Where ``a`` is relative to ``b`` from the dominant axis of the centroid offset.

    +x is right, +y away from the viewer: "left of", "right of", "in front of" or "behind".
    Ties between the axes go to left/right.
    """
    dx = a.center[0] - b.center[0]
    dy = a.center[1] - b.center[1]
    if abs(dx) >= abs(dy):
        return "right of" if dx > 0 else "left of"
    return "behind" if dy > 0 else "in front of"


def _xy_distance(a: SceneObject, b: SceneObject) -> float:
    return math.hypot(a.center[0] - b.center[0], a.center[1] - b.center[1])


def _root_order(scene: Scene) -> list[SceneObject]:
    """Table-level objects: the anchor (closest to the zone centre), then by proximity to placed ones."""
    roots = [o for o in scene.objects if o.parent == TABLE]
    if not roots:
        return []
    cx, cy = scene.zone.center
    anchor = min(roots, key=lambda o: (math.hypot(o.center[0] - cx, o.center[1] - cy), o.instance_id))
    order = [anchor]
    remaining = [o for o in roots if o is not anchor]
    best = [_xy_distance(o, anchor) for o in remaining]  # distance to the nearest placed root
    while remaining:
        k = min(range(len(remaining)), key=lambda i: (best[i], remaining[i].instance_id))
        placed = remaining.pop(k)
        best.pop(k)
        order.append(placed)
        best = [min(d, _xy_distance(o, placed)) for d, o in zip(best, remaining)]
    return order


def anchor_order(scene: Scene) -> list[str]:
    """Instance ids in the order of the paper's Algorithm 1.

    The anchor is the table-level object closest to the zone centre; the other table-level
    objects follow by proximity to those already placed; every object's children come right
    after it, bottom-up (by zmin, then by distance to the parent). Builds a hierarchy if the
    scene has none.
    """
    scene = ensure_hierarchy(scene)
    children: dict[str, list[SceneObject]] = {}
    for o in scene.objects:
        children.setdefault(o.parent, []).append(o)
    by_id = scene.by_id()
    order: list[str] = []

    def expand(node: SceneObject) -> None:
        stack = [node]
        while stack:  # iterative pre-order: deep stacks cannot hit the recursion limit
            o = stack.pop()
            order.append(o.instance_id)
            kids = sorted(children.get(o.instance_id, []),
                          key=lambda c: (c.zmin, _xy_distance(c, by_id[o.instance_id]), c.instance_id))
            stack.extend(reversed(kids))

    for root in _root_order(scene):
        expand(root)
    return order


def near_references(scene: Scene) -> dict[str, tuple[str, str] | None]:
    """For every table-level object, (reference id, direction) or None for the anchor.

    The reference is the nearest table-level object placed before it in the anchor order; the
    direction says where the object is relative to that reference (:func:`near_direction`).
    """
    scene = ensure_hierarchy(scene)
    roots = _root_order(scene)
    refs: dict[str, tuple[str, str] | None] = {}
    for k, o in enumerate(roots):
        if k == 0:
            refs[o.instance_id] = None
            continue
        ref = min(roots[:k], key=lambda r: (_xy_distance(o, r), r.instance_id))
        refs[o.instance_id] = (ref.instance_id, near_direction(o, ref))
    return refs
