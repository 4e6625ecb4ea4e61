"""Clean synthetic tabletop layouts (centimetres): no pair interpenetrates by construction.

A scene is built from *units*: a single object, or a typical hierarchy (:class:`GroupSpec`: a
base with children ``on`` or ``in`` it). Units are placed on the table by rejection sampling of
their footprints (the yawed base's axis-aligned box, inflated by a per-scene margin) under the
scene's arrangement style, outside restricted zones (sinks). Inside a unit:

- ``on``: exact contact, ``zmin(child) == zmax(parent)`` (+ ``contact_gap_cm``), the child's
  footprint inside the parent's top;
- ``in``: the content's footprint inside the container's inner rectangle; its height is found on
  the container's own SDF (the asset the engine will use): the content is lowered from the rim
  until one more step would make a surface point of either shape cross the other's surface, so
  a pen stands on the holder's floor and an apple rests on a bowl's curved wall.

Because every asset lies inside its normalised box, disjoint footprints (plus the in/on rules)
mean no pair interpenetrates; tests confirm it with the engine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from physcene.data.scene_types import STANDING, GroupSpec, SceneTypeSpec
from physcene.data.seating import ContainerFit
from physcene.data.units import (
    Node,
    boxes_touch,
    choose_yaw,
    counts_as_in,
    footprint_halfextents,
    rotated,
    rotated_rel,
    sample_size,
    uniform_offset,
    weighted_choice,
)
from physcene.scene import TABLE, Scene, SceneObject, Zone

__all__ = ["ContainerFit", "SynthConfig", "SynthError", "synthesize_layout"]


# Containers in which long things stand upright (pens in a holder, toothbrushes in a cup).
_UPRIGHT_CONTAINERS = frozenset({"pen_holder", "toothbrush_cup", "cup", "mug", "glass", "jar", "vase"})
# Objects tall enough to go to the back in the "back_row" style.
_BACK_ROW_HEIGHT_CM = 15.0


class SynthError(RuntimeError):
    """The generator could not fit the requested objects (after all its retries)."""


@dataclass(frozen=True, kw_only=True)
class SynthConfig:
    """Knobs of the clean generator (cm)."""

    margin_cm: tuple[float, float] = (0.6, 3.0)
    """Range of the per-scene gap kept between table-level footprints."""
    edge_margin_cm: float = 0.5
    """Gap kept between footprints and the zone's edges."""
    contact_gap_cm: float = 0.001
    """Extra height between an ``on`` child and its support: 10 µm, below any physical meaning
    but above the engine's float32 round-off (~1e-6 cm), so exact contact never reads as a
    0-cm collision."""
    in_clearance_cm: float = 0.02
    """Clearance kept between a content's surface and its container's surface."""
    in_step_cm: float = 0.05
    """Step of the downward search that seats contents in containers."""
    size_clip_sigma: float = 1.5
    """Sampled sizes stay within this many standard deviations of the prior mean."""
    placement_tries: int = 120
    """Candidate positions tried per unit before it is dropped."""
    scene_retries: int = 12
    """Whole-scene restarts (new zone) before giving up."""


class _Builder:
    """One scene under construction (see the module docstring)."""

    def __init__(
        self,
        spec: SceneTypeSpec,
        n_objects: int,
        level: int,
        rng: np.random.Generator,
        config: SynthConfig,
        fit: ContainerFit,
    ):
        self.spec, self.n, self.level, self.rng, self.config, self.fit = (
            spec,
            n_objects,
            level,
            rng,
            config,
            fit,
        )
        self.nodes: list[Node] = []
        self.used: dict[str, int] = {}
        self.boxes: list[tuple[float, float, float, float]] = []  # placed footprints xmin,xmax,ymin,ymax

    # Zone and sinks ---------------------------------------------------------------------------
    def make_zone(self) -> None:
        rng, spec = self.rng, self.spec
        # denser scenes get larger tables: t = U^(1/level) leans to the top of the range
        t = rng.random() ** (1.0 / (1.0 + 0.6 * (self.level - 1)))
        w = spec.zone_width_cm[0] + t * (spec.zone_width_cm[1] - spec.zone_width_cm[0])
        d = spec.zone_depth_cm[0] + (rng.random() ** 0.7) * (spec.zone_depth_cm[1] - spec.zone_depth_cm[0])
        self.zone = Zone(0.0, round(float(w), 1), 0.0, round(float(d), 1))
        self.margin = float(rng.uniform(*self.config.margin_cm))
        self.sinks: list[Zone] = []
        if spec.sink is not None:
            sw = float(rng.uniform(*spec.sink[0]))
            sd = min(float(rng.uniform(*spec.sink[1])), 0.75 * d)
            cx = float(rng.uniform(0.3, 0.7)) * w
            cy = 0.5 * d + float(rng.uniform(-0.1, 0.1)) * d
            self.sinks.append(
                Zone(
                    round(cx - 0.5 * sw, 1),
                    round(cx + 0.5 * sw, 1),
                    round(max(cy - 0.5 * sd, 0.0), 1),
                    round(min(cy + 0.5 * sd, d), 1),
                )
            )
        self.style = weighted_choice(rng, list(spec.styles), list(spec.styles.values()))
        n_clusters = int(rng.integers(1, 4))
        self.cluster_centres = [
            (float(rng.uniform(0.15, 0.85)) * w, float(rng.uniform(0.2, 0.8)) * d) for _ in range(n_clusters)
        ]

    # Units ------------------------------------------------------------------------------------
    def _category_weight(self, category: str, base: float) -> float:
        return base * (0.35 ** self.used.get(category, 0))

    def pick_single(self) -> str:
        cats = list(self.spec.vocabulary)
        return weighted_choice(
            self.rng, cats, [self._category_weight(c, self.spec.vocabulary[c]) for c in cats]
        )

    def pick_group(self, remaining: int) -> GroupSpec | None:
        groups = [
            g
            for g in self.spec.groups
            if 1 + sum(lo for _, _, lo, _ in g.children) <= remaining
            and 1 + sum(hi for _, _, _, hi in g.children) >= 2
        ]
        if not groups or remaining < 2:
            return None
        return weighted_choice(
            self.rng, groups, [g.weight * (0.6 ** self.used.get(g.name, 0)) for g in groups]
        )

    def instantiate_group(self, group: GroupSpec, remaining: int) -> list[Node]:
        rng = self.rng
        base_cat = group.base[int(rng.integers(len(group.base)))]
        base = Node(base_cat, sample_size(base_cat, rng, self.config.size_clip_sigma), group=group.name)
        nodes = [base]
        budget = remaining - 1
        for rel, cats, lo, hi in group.children:
            count = min(int(rng.integers(lo, hi + 1)), budget)
            for _ in range(count):
                cat = cats[int(rng.integers(len(cats)))]
                size = sample_size(cat, rng, self.config.size_clip_sigma)
                if rel == "in" and cat in STANDING and base_cat in _UPRIGHT_CONTAINERS:
                    size = (
                        np.array([size[1], size[2], size[0]])
                        if size[1] >= size[2]
                        else np.array([size[2], size[1], size[0]])
                    )
                nodes.append(Node(cat, size, relation=rel, group=group.name))
                budget -= 1
        if len(nodes) == 1:
            return []
        return nodes

    # Hierarchy inside a unit --------------------------------------------------------------------
    def _pack_local(self, halfw: float, halfd: float, sizes: list[np.ndarray], gap: float):
        """Disjoint local offsets for footprints inside [-halfw, halfw] × [-halfd, halfd]."""
        rng = self.rng
        placed: list[tuple[float, float, float, float]] = []
        out = []
        for s in sizes:
            hx, hy = 0.5 * s[0], 0.5 * s[1]
            if hx > halfw or hy > halfd:
                return None
            for _ in range(60):
                x = float(rng.uniform(-halfw + hx, halfw - hx))
                y = float(rng.uniform(-halfd + hy, halfd - hy))
                if all(
                    x + hx + gap <= a or x - hx - gap >= b or y + hy + gap <= c or y - hy - gap >= d
                    for a, b, c, d in placed
                ):
                    placed.append((x - hx, x + hx, y - hy, y + hy))
                    out.append((x, y))
                    break
            else:
                return None
        return out

    def fit_children(self, nodes: list[Node], group: GroupSpec) -> list[Node]:
        """Sizes and local layout of a unit's children; drops children that cannot fit.

        Poses are set relative to the base at the origin with yaw 0; :meth:`pose_unit` moves them.
        """
        base = nodes[0]
        kept = [base]
        # in: contents inside the inner rectangle, not taller than 1.6x the container
        ins = [n for n in nodes[1:] if n.relation == "in"]
        if ins:
            inner_w, inner_d = 0.72 * base.size[0], 0.72 * base.size[1]
            for n in ins:
                n.size[2] = min(n.size[2], 1.6 * base.size[2])
                scale = min(1.0, 0.95 * inner_w / n.size[0], 0.95 * inner_d / n.size[1])
                n.size[:2] *= scale
                n.parent = 0
                n.yaw = self._relative_yaw()
            offsets = None
            while ins and offsets is None:
                offsets = self._pack_local(0.5 * inner_w, 0.5 * inner_d, [rotated(n) for n in ins], 0.4)
                if offsets is None:
                    ins = ins[:-1]
            for n, (x, y) in zip(ins, offsets or []):
                n.center = np.array([x, y, 0.0])
                kept.append(n)
        ons = [n for n in nodes[1:] if n.relation == "on"]
        if group.stack:
            below = 0
            for n in ons:
                parent = kept[below] if below < len(kept) else base
                n.yaw = self._relative_yaw()
                for axis in (0, 1):
                    n.size[axis] = min(n.size[axis], 0.93 * parent.size[axis])
                slack = 0.5 * parent.size[:2] - 0.5 * rotated(n)[:2]
                off = np.array([uniform_offset(self.rng, slack[0]), uniform_offset(self.rng, slack[1])])
                n.center = np.array([parent.center[0] + off[0], parent.center[1] + off[1], 0.0])
                n.parent = kept.index(parent)
                kept.append(n)
                below = len(kept) - 1
        elif ons:
            for n in ons:
                n.size[0] = min(n.size[0], 0.9 * base.size[0])
                n.size[1] = min(n.size[1], 0.9 * base.size[1])
                n.parent = 0
                n.yaw = self._relative_yaw()
            offsets = None
            while ons and offsets is None:
                offsets = self._pack_local(
                    0.5 * base.size[0], 0.5 * base.size[1], [rotated(n) for n in ons], 0.5
                )
                if offsets is None:
                    ons = ons[:-1]
            for n, (x, y) in zip(ons, offsets or []):
                n.center = np.array([x, y, 0.0])
                kept.append(n)
        return kept

    def _relative_yaw(self) -> float:
        """A child's yaw relative to its base (rad): nearly aligned, as people set things down."""
        return float(np.deg2rad(np.clip(self.rng.normal(0.0, 3.0), -6.0, 6.0)))

    # Table-level placement ----------------------------------------------------------------------
    def _candidate(self, hx: float, hy: float, height: float, anchor: bool) -> tuple[float, float]:
        rng, z = self.rng, self.zone
        em = self.config.edge_margin_cm
        lo_x, hi_x = z.xmin + hx + em, z.xmax - hx - em
        lo_y, hi_y = z.ymin + hy + em, z.ymax - hy - em
        if lo_x > hi_x or lo_y > hi_y:
            return (math.nan, math.nan)
        style = self.style
        if style == "back_row" and (height >= _BACK_ROW_HEIGHT_CM or anchor) and rng.random() < 0.85:
            return float(rng.uniform(lo_x, hi_x)), float(hi_y - abs(rng.normal(0.0, 2.0)))
        if style == "clusters" and rng.random() < 0.8:
            cx, cy = self.cluster_centres[int(rng.integers(len(self.cluster_centres)))]
            x = cx + rng.normal(0.0, 0.18 * z.width)
            y = cy + rng.normal(0.0, 0.22 * z.depth)
            return float(np.clip(x, lo_x, hi_x)), float(np.clip(y, lo_y, hi_y))
        if style == "place_settings" and anchor:
            # place settings along the front and back edges
            edge = (
                lo_y + abs(rng.normal(0.0, 1.5)) if rng.random() < 0.6 else hi_y - abs(rng.normal(0.0, 1.5))
            )
            return float(rng.uniform(lo_x, hi_x)), float(edge)
        return float(rng.uniform(lo_x, hi_x)), float(rng.uniform(lo_y, hi_y))

    def _free(self, box: tuple[float, float, float, float]) -> bool:
        m = self.margin
        a0, a1, b0, b1 = box
        for x0, x1, y0, y1 in self.boxes:
            if not (a1 + m <= x0 or a0 - m >= x1 or b1 + m <= y0 or b0 - m >= y1):
                return False
        for s in self.sinks:
            if not (a1 + 1.0 <= s.xmin or a0 - 1.0 >= s.xmax or b1 + 1.0 <= s.ymin or b0 - 1.0 >= s.ymax):
                return False
        return True

    def place_unit(self, nodes: list[Node], anchor: bool) -> bool:
        base = nodes[0]
        if self.style == "place_settings" and base.group == "place setting":
            anchor = True
        yaw = (
            choose_yaw(base.category, self.rng)
            if len(nodes) == 1
            else float(self.rng.choice([0.0, 0.0, 0.0, 0.5 * math.pi]))
            + float(np.deg2rad(self.rng.normal(0, 3)))
        )
        hx, hy = footprint_halfextents(base.size, yaw)
        height = max(base.size[2], *(n.size[2] for n in nodes))
        for _ in range(self.config.placement_tries):
            x, y = self._candidate(hx, hy, height, anchor)
            if math.isnan(x):
                break
            box = (x - hx, x + hx, y - hy, y + hy)
            if self._free(box):
                self.boxes.append(box)
                self.pose_unit(nodes, np.array([x, y]), yaw)
                return True
        return False

    def pose_unit(self, nodes: list[Node], xy: np.ndarray, yaw: float) -> None:
        """Turn a unit's local layout into world poses; seats ``in`` contents on the SDFs."""
        offset = len(self.nodes)
        seated: list[tuple] = []  # (local box, zmax) of contents already in the base
        for k, n in enumerate(nodes):
            local = n.center[:2].copy()
            n.center = np.array([*self._world_xy(xy, yaw, local), 0.0])
            n.yaw = yaw + (0.0 if k == 0 else n.yaw)  # children carry their yaw relative to the base
            if n.parent is None:
                n.center[2] = 0.5 * n.size[2]
            elif n.relation == "on":
                parent = nodes[n.parent]
                n.center[2] = (
                    parent.center[2] + 0.5 * parent.size[2] + self.config.contact_gap_cm + 0.5 * n.size[2]
                )
            else:
                self._seat_content(nodes[n.parent], n, local, xy, yaw, seated)
        for n in nodes:
            if n.parent is not None:
                n.parent += offset
        for n in nodes:
            self.used[n.category] = self.used.get(n.category, 0) + 1
        self.nodes.extend(nodes)

    @staticmethod
    def _world_xy(xy: np.ndarray, yaw: float, local: np.ndarray) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([xy[0] + c * local[0] - s * local[1], xy[1] + s * local[0] + c * local[1]])

    def _seat_content(
        self, parent: Node, n: Node, local: np.ndarray, xy: np.ndarray, yaw: float, seated: list[tuple]
    ) -> None:
        """Lower ``n`` into ``parent``; if it would not count as ``in`` (it rests too high, e.g.
        on a bowl's curved wall or a basket's handle), try other spots in the cavity and
        smaller sizes. Falls back to resting on top (``on``) of the container and its contents.

        ``seated`` holds (local box [x0, x1, y0, y1], zmax) of the contents already in ``parent``.
        """
        inner = 0.5 * 0.72 * parent.size[:2]
        for attempt in range(8):
            if attempt and attempt % 2 == 0:
                n.size *= 0.85
            half = 0.5 * rotated_rel(n, n.yaw - yaw)
            if attempt:
                lo, hi = -inner + half, inner - half
                if np.any(lo > hi):
                    continue
                local = np.array([self.rng.uniform(lo[0], hi[0]), self.rng.uniform(lo[1], hi[1])])
            box = np.array([local[0] - half[0], local[0] + half[0], local[1] - half[1], local[1] + half[1]])
            if any(boxes_touch(box, b, 0.4) for b, _ in seated):
                continue
            n.center = np.array([*self._world_xy(xy, yaw, local), parent.center[2]])
            z = self.fit.seat(parent, n, self.config)
            if z is not None and counts_as_in(parent, n, z):
                n.center[2] = z
                seated.append((box, z + 0.5 * n.size[2]))
                return
        n.relation = "on"  # cannot go in: rest it on top of the container and whatever sticks out
        top = max([parent.center[2] + 0.5 * parent.size[2]] + [zmax for _, zmax in seated])
        n.center[2] = top + 0.5 * n.size[2] + self.config.contact_gap_cm

    # Whole scene --------------------------------------------------------------------------------
    def build(self) -> bool:
        self.make_zone()
        anchors = [a for a, p in self.spec.anchors if self.rng.random() < p]
        failures = 0
        while len(self.nodes) < self.n:
            remaining = self.n - len(self.nodes)
            anchor = bool(anchors)
            nodes: list[Node] = []
            group = None
            if anchors:
                name = anchors.pop(0)
                if name.startswith("group:"):
                    group = self.spec.group(name[6:])
                    nodes = self.instantiate_group(group, remaining) if remaining >= 2 else []
                elif remaining >= 1:
                    nodes = [Node(name, sample_size(name, self.rng, self.config.size_clip_sigma))]
            elif self.rng.random() < self.spec.group_rate:
                group = self.pick_group(remaining)
                if group is not None:
                    nodes = self.instantiate_group(group, remaining)
            if not nodes:
                cat = self.pick_single()
                nodes = [Node(cat, sample_size(cat, self.rng, self.config.size_clip_sigma))]
            if group is not None and len(nodes) > 1:
                nodes = self.fit_children(nodes, group)
                self.used[group.name] = self.used.get(group.name, 0) + 1
            if not self.place_unit(nodes, anchor):
                failures += 1
                if failures > 40:
                    return False
        return True

    def scene(self, scene_type: str) -> Scene:
        counters: dict[str, int] = {}
        first: dict[str, int] = {}
        ids = []
        for n in self.nodes:
            first.setdefault(n.category, len(first) + 1)
            j = counters.get(n.category, 0)
            counters[n.category] = j + 1
            ids.append(f"{first[n.category]}_{n.category}_{j}")
        objects = []
        for n, oid in zip(self.nodes, ids):
            objects.append(
                SceneObject(
                    instance_id=oid,
                    category=n.category,
                    center=tuple(float(v) for v in n.center),
                    size=tuple(float(v) for v in n.size),
                    yaw=math.remainder(n.yaw, 2 * math.pi),
                    parent=TABLE if n.parent is None else ids[n.parent],
                    relation=n.relation,
                )
            )
        groups = sorted({n.group for n in self.nodes if n.group})
        phrases = [self.spec.group(g).phrase for g in groups]
        return Scene(
            zone=self.zone,
            objects=tuple(objects),
            scene_type=scene_type,
            restricted_zones=tuple(self.sinks),
            meta={
                "arrangement_style": self.style,
                "margin_cm": round(self.margin, 3),
                "groups": groups,
                "group_phrases": phrases,
            },
        )


def synthesize_layout(
    spec: SceneTypeSpec,
    n_objects: int,
    level: int,
    rng: np.random.Generator,
    config: SynthConfig | None = None,
    fit: ContainerFit | None = None,
) -> Scene:
    """A clean layout of ``n_objects`` objects of type ``spec`` (cm), with its intended hierarchy.

    Every object carries ``parent`` (an instance id or ``TABLE``) and ``relation`` (``in``,
    ``on``, ``near``) as built; ``meta`` records the arrangement style, margin and groups.
    Raises :class:`SynthError` if no layout fits after ``config.scene_retries`` restarts.
    """
    config = config or SynthConfig()
    fit = fit or ContainerFit()
    for _ in range(config.scene_retries):
        builder = _Builder(spec, n_objects, level, rng, config, fit)
        if builder.build():
            return builder.scene(spec.name)
    raise SynthError(
        f"could not fit {n_objects} objects on a {spec.name!r} after {config.scene_retries} tries"
    )
