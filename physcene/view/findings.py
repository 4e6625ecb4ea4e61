"""What the viewer marks on a scene: penetrating pairs with their depth, floating objects, and the
scene graph's in / on / near edges (:mod:`physcene.graph`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from physcene.graph import ensure_hierarchy, near_references
from physcene.physics import PhysicsEngine
from physcene.scene import TABLE, Scene

__all__ = ["RELATIONS", "SceneFindings", "find"]

RELATIONS = ("in", "on", "near")


@dataclass(frozen=True)
class SceneFindings:
    """The engine's and the scene graph's verdict on one scene."""

    pairs: tuple[tuple[str, str, float], ...]
    """(id a, id b, depth cm) of every penetrating pair, deepest first."""
    floating: tuple[str, ...]
    """Ids of the objects resting on nothing (physics ``floating_tolerance_cm``)."""
    edges: tuple[tuple[str, str, str], ...]
    """(child id, other id, relation): ``in`` / ``on`` to the support, ``near`` to the nearest
    table-level object placed before it (the anchor has none)."""


def _edges(scene: Scene) -> tuple[tuple[str, str, str], ...]:
    graph = ensure_hierarchy(scene)
    edges = [(o.instance_id, o.parent, o.relation) for o in graph.objects
             if o.parent not in (None, TABLE) and o.relation in ("in", "on")]
    edges += [(child, ref[0], "near") for child, ref in near_references(graph).items() if ref is not None]
    return tuple(edges)


def find(scenes: Sequence[Scene], engine: PhysicsEngine | None = None) -> list[SceneFindings]:
    """:class:`SceneFindings` of every scene, scored in one engine call."""
    engine = engine or PhysicsEngine(device="cpu")
    score = engine.score(list(scenes))
    out = []
    for s, scene in enumerate(scenes):
        ids = scene.ids()
        pairs = sorted(((ids[i], ids[j], float(d)) for i, j, d in score.pairs[s]), key=lambda p: -p[2])
        out.append(SceneFindings(pairs=tuple(pairs), floating=tuple(ids[i] for i in score.floating[s]),
                                 edges=_edges(scene)))
    return out
