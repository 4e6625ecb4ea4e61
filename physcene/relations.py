"""Which hierarchy relations a layout keeps: the measure shared by TTO and evaluation.

A layout's meaning (docs/scene_language.md, "Hierarchical scene graph") is its forest of
``in``/``on`` edges plus, for every table-level object, the direction of its ``near`` reference
(:func:`physcene.graph.near_references`: the nearest table-level object placed before it in
Algorithm 1's anchor order). :func:`relation_preservation` compares two layouts of the same
objects: the ``after`` layout's graph is rebuilt from its geometry with :mod:`physcene.graph`, so a
repair is only credited with what the geometry really shows.
"""

from __future__ import annotations

from physcene.graph import build_hierarchy, ensure_hierarchy, near_direction, near_references
from physcene.scene import TABLE, Scene

__all__ = ["DIRECTION_AXES", "relation_preservation"]

# near_direction label -> (axis, sign): where a lies relative to b along world x (right) or
# y (away from the viewer). "in front of" is towards the viewer, i.e. -y.
DIRECTION_AXES: dict[str, tuple[int, int]] = {
    "left of": (0, -1),
    "right of": (0, 1),
    "behind": (1, 1),
    "in front of": (1, -1),
}


def relation_preservation(before: Scene, after: Scene, graph_config=None) -> dict:
    """How much of ``before``'s hierarchy ``after`` keeps.

    ``before`` keeps its own annotation when it has one (else its graph is built); ``after``'s
    graph is always rebuilt from geometry. Returns ``in_on_kept``/``near_kept`` (fractions in
    [0, 1], 1.0 when there is nothing to keep), the counts, and the ids of broken relations.
    Objects are matched by instance id; an object missing from ``after`` counts as broken.
    """
    before = ensure_hierarchy(before, graph_config)
    stripped = after.with_objects(o.moved(parent=None, relation=None) for o in after.objects)
    rebuilt = build_hierarchy(stripped, graph_config).by_id()

    edges = [o for o in before.objects if o.relation in ("in", "on") and o.parent not in (None, TABLE)]
    broken_edges = [
        o.instance_id for o in edges
        if o.instance_id not in rebuilt
        or (rebuilt[o.instance_id].parent, rebuilt[o.instance_id].relation) != (o.parent, o.relation)
    ]
    refs = {k: v for k, v in near_references(before).items() if v is not None}
    broken_near = []
    for oid, (ref, direction) in refs.items():
        if (oid not in rebuilt or ref not in rebuilt
                or near_direction(rebuilt[oid], rebuilt[ref]) != direction):
            broken_near.append(oid)
    return {
        "in_on_edges": len(edges),
        "in_on_kept": 1.0 - len(broken_edges) / len(edges) if edges else 1.0,
        "in_on_broken": broken_edges,
        "near_relations": len(refs),
        "near_kept": 1.0 - len(broken_near) / len(refs) if refs else 1.0,
        "near_broken": broken_near,
    }
