"""The procedural generator: an instruction's objects placed by the benchmark synthesiser.

The instruction (:mod:`physcene.generation.instruction`) gives the scene type, the named objects
with their counts and the stated in/on relations. They become the *anchors* of a scene-type spec
(:class:`physcene.data.scene_types.SceneTypeSpec`): each stated relation a hierarchy (a
:class:`GroupSpec` whose base is the parent and whose child slots are the contents), each other
object a single. The synthesiser places anchors first and then fills the table with what the
scene type usually holds, so the layout is clean by construction (no pair interpenetrates, in/on
contents seated on the container's own shape). A layout that lost a requested object (it did not
fit) or a relation (a content that could not be seated) is drawn again.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass

import numpy as np

from physcene.assets.categories import CATEGORY_PRIORS
from physcene.data.captions import describe
from physcene.data.scene_types import GroupSpec, spec_for
from physcene.data.splits import level_of
from physcene.data.synth import SynthError, synthesize_layout
from physcene.generation.instruction import Instruction
from physcene.scene import Scene

__all__ = ["GenerationError", "Request", "plan_request", "procedural_scene", "unmet"]

# Weight of a requested hierarchy among the type's groups: placed as an anchor, never drawn again
# as a fill-in unless nothing else fits.
_REQUESTED_WEIGHT = 1e-9


class GenerationError(ValueError):
    """A generator could not produce a layout (the message says which request and why)."""


@dataclass(frozen=True)
class Request:
    """One draw of what a layout must hold: concrete categories, counts and hierarchies."""

    singles: tuple[str, ...]
    """Table-level objects, one entry per object."""
    groups: tuple[tuple[str, tuple[tuple[str, str], ...]], ...]
    """(parent category, ((relation in/on, child category), ...)) per parent a relation names."""
    fill: int
    """Objects the scene type adds beyond the named ones."""

    @property
    def n_objects(self) -> int:
        return len(self.singles) + sum(1 + len(c) for _, c in self.groups) + self.fill

    def counts(self) -> Counter:
        """Objects per category the layout must hold at least."""
        out = Counter(self.singles)
        for parent, children in self.groups:
            out[parent] += 1
            out.update(c for _, c in children)
        return out


def _count(mention, instruction: Instruction, rng: np.random.Generator, child: bool, shrink: int) -> int:
    if mention.count is not None:
        return mention.count
    if mention.plural or len(mention.categories) > 1:
        if instruction.diners and not child:
            return instruction.diners
        # contents with no number: two or three, fewer after draws that could not seat them all
        return max(1, int(rng.integers(2, 4)) - shrink) if child else 2
    return 1


def plan_request(instruction: Instruction, rng: np.random.Generator, fill: int | None = None,
                 shrink: int = 0) -> Request:
    """Concrete categories for the instruction's mentions (a choice such as fruit drawn here);
    ``shrink`` lowers the number of contents the instruction left open."""
    children_of: dict[int, list] = {}
    is_child = set()
    for r in instruction.relations:
        children_of.setdefault(r.parent, []).append(r)
        is_child.add(r.child)
    singles: list[str] = []
    groups = []
    for k, m in enumerate(instruction.mentions):
        if k in is_child:
            continue
        draw = [m.categories[int(rng.integers(len(m.categories)))] for _ in
                range(_count(m, instruction, rng, child=False, shrink=shrink))]
        if k in children_of:
            parent, kids = draw.pop(0), []
            for r in children_of[k]:
                cm = instruction.mentions[r.child]
                kids += [(r.relation, cm.categories[int(rng.integers(len(cm.categories)))])
                         for _ in range(_count(cm, instruction, rng, child=True, shrink=shrink))]
            groups.append((parent, tuple(kids)))
        singles += draw
    named = len(singles) + sum(1 + len(c) for _, c in groups)
    if fill is None:
        fill = 0 if instruction.only else int(rng.integers(2, 5)) if named < 10 else int(rng.integers(0, 2))
    # largest footprints first: they are the hardest to fit once the table fills up
    singles.sort(key=lambda c: -CATEGORY_PRIORS[c].mean_cm[0] * CATEGORY_PRIORS[c].mean_cm[1])
    return Request(singles=tuple(singles), groups=tuple(groups), fill=max(0, int(fill)))


def _spec(instruction: Instruction, request: Request):
    base = spec_for(instruction.scene_type)
    mine, anchors = [], []
    for k, (parent, children) in enumerate(request.groups):
        slots = tuple((relation, (c,), 1, 1) for relation, c in children)
        name = f"requested {k}: {parent}"
        mine.append(GroupSpec(name, (parent,), slots, _REQUESTED_WEIGHT, False, name))
        anchors.append((f"group:{name}", 1.0))
    anchors += [(c, 1.0) for c in request.singles]
    return dataclasses.replace(base, groups=base.groups + tuple(mine), anchors=tuple(anchors))


def unmet(scene: Scene, request: Request) -> list[str]:
    """What ``scene`` lacks of ``request``: missing objects, relations not built as asked."""
    have = Counter(o.category for o in scene.objects)
    missing = [f"{need - have[c]} x {c}" for c, need in sorted(request.counts().items()) if have[c] < need]
    for parent, children in request.groups:
        want = Counter(children)
        if not any(o.category == parent and _holds(scene, o.instance_id, want) for o in scene.objects):
            missing.append(", ".join(f"{c} {r}" for r, c in children) + f" the {parent}")
    return missing


def _holds(scene: Scene, parent_id: str, want: Counter) -> bool:
    got = Counter((c.relation, c.category) for c in scene.objects if c.parent == parent_id)
    return all(got[key] >= n for key, n in want.items())


def procedural_scene(instruction: Instruction, rng: np.random.Generator, *, fill: int | None = None,
                     tries: int = 24) -> Scene:
    """A clean layout holding every object and relation ``instruction`` names (see the module
    docstring); raises :class:`GenerationError` naming what did not fit after ``tries`` draws."""
    last: list[str] = []
    for attempt in range(tries):
        request = plan_request(instruction, rng, fill, shrink=3 * attempt // tries)
        spec = _spec(instruction, request)
        try:
            scene = synthesize_layout(spec, request.n_objects, level_of(request.n_objects), rng)
        except SynthError:
            last = [f"{request.n_objects} objects on one {instruction.scene_type}"]
            continue
        last = unmet(scene, request)
        if not last:
            objects = [o.moved(description=describe(o.category, o.size, rng)) for o in scene.objects]
            meta = {**scene.meta, "groups": [g for g in scene.meta.get("groups", [])
                                             if not g.startswith("requested ")]}
            return dataclasses.replace(scene, objects=tuple(objects), instruction=instruction.text, meta=meta)
    raise GenerationError(f"the procedural generator could not fit {'; '.join(last)} "
                          f"(after {tries} draws); ask for fewer objects or a larger table type")
