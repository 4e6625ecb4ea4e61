"""Hierarchy-constrained test-time optimisation (paper Sec. "Hierarchy-Constrained TTO").

min_ξ λ_sdf·L_sdf + λ_rel·L_rel(G) + λ_reg·‖ξ − ξ_init‖² + λ_zone·L_zone, batched over scenes of
different sizes (padded slots, masks) in one Adam optimisation. docs/tto.md has the formulas.

Parametrisation ξ (METRES and radians; the engine and the scene work in cm):
- table-level objects (parent = TABLE): (x, y, yaw) absolute; z held at h/2 (resting on the table);
- ``on`` children: (u, v, ψ) = the centre offset in the parent's yawed frame and the yaw relative to
  the parent; z held at the support's top (zmax(parent) + h/2);
- ``in`` children (``in_children``): ``slide`` (default) = (u, v, ψ) in the container's yawed
  frame like an ``on`` child, z offset to the container held (the content stays in, at its height),
  footprint kept inside the container's; ``frozen`` (the paper's, DESIGN) = offset, z offset and
  relative yaw are constants, so a container and its contents move as one rigid body.
Absolute poses come from a differentiable forward kinematics over the forest, one batched gather
per tree depth. Pairs inside one rigid body cannot change and are left out of L_sdf (``frozen``
only; with ``slide`` the container–content pairs are optimised like any other).

L_rel = support term (an ``on`` child's footprint may not slide further off its support than it
started, hinge on the offset in the parent frame, plus a hard projection after every step) + near
term (hinge keeping each table-level object's direction to its reference). L_zone = footprint
corners outside the placement zone + overlap depth with restricted zones.

Every scene returns its best iterate (lowest penetration energy; among collision-free iterates the
lowest remaining objective), and never more energy than its input: if nothing beat the input,
the input is returned unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from physcene.relations import DIRECTION_AXES, relation_preservation
from physcene.scene import TABLE, Scene, SceneObject

__all__ = ["TTOConfig", "TTOProblem", "TTOResult", "build_problem", "forward_kinematics", "optimise",
           "relation_preservation", "repair", "summarize"]

# Kinds of parametrisation per object slot.
ROOT, ON, IN = 0, 1, 2
IN_MODES = ("slide", "frozen")
_CM = 100.0  # cm per metre: ξ is in metres, poses in cm
_LIFT_CM = 10.0  # cm per unit of ξ's lift component: an Adam step of lr 0.01 lifts by 0.1 cm


@dataclass(kw_only=True)
class TTOConfig:
    """TTO settings (``configs/tto.yaml``); lengths in cm unless the name says otherwise."""

    steps: int = 100
    """Adam iterations (paper: 100)."""
    lr: float = 0.01
    """Adam step size in metres / radians (paper: 0.01)."""
    lr_final: float = 0.01
    """Learning rate reached at the last step by cosine decay (= lr: constant, the paper's)."""
    lambda_sdf: float = 10.0
    """Weight of the penetration energy, taken in metres (engine cm / 100)."""
    lambda_rel: float = 5.0
    """Weight of the structure term (support + near hinges, metres)."""
    lambda_reg: float = 1.0
    """Weight of ‖ξ − ξ_init‖² (metres², radians²)."""
    lambda_zone: float = 10.0
    """Weight of the zone term (metres)."""
    contact_gap_cm: float = 1e-5
    """An ``on`` child rests this far above its support's top: float32 rounding of a zero gap
    reads as ~1e-7 cm penetration; the gap is far below the 1e-4 cm placement requirement."""
    reattach_gap_cm: float = 3.0
    """A table-level object hovering over / sunk into a support by less than this is optimised as
    ``on`` it (0 disables; see :func:`_reattach`)."""
    in_children: str = "slide"
    """``slide``: an ``in`` child's (x, y, yaw) in its container's frame are parameters (z offset held,
    footprint kept inside the container's), so a content modelled into its container's wall can be
    fixed; ``frozen``: the paper's rigid container body (docs/tto.md, "in children")."""
    in_lr_scale: float = 0.25
    """``slide`` only: an ``in`` child's (u, v) take Adam steps of this fraction of ``lr`` (0.25 cm),
    smaller than its container's clearance, so a content does not step into a wall."""
    in_lift_cm: float = 3.0
    """``slide`` only: a content may also rise by up to this much in its container (never so far that
    less than 55 % of its height stays inside the container's z-range, the graph's ``in`` test
    needs 50 %), so a content sunk into its container's floor can come out (0: z offset fixed)."""
    footprint_proxy: bool = True
    """Add the footprint-overlap proxy of pairs that penetrate at the start (see docs/tto.md)."""
    near_margin_cm: float = 0.5
    """Slack a near direction keeps over the axis tie (never more than the input had)."""
    stop_energy_cm: float = 1e-3
    """Optimised energy at or below this counts as collision-free (early stop, best iterate)."""
    stop_violation_cm: float = 0.01
    """Hinge terms at or below this count as met (early stop)."""
    check_every: int = 10
    """Host check for "every scene stopped" every k steps."""
    early_stop: bool = True
    """Freeze each scene at its first collision-free iterate that meets the hinges."""
    collision_depth_cm: float = 0.1
    """Reporting: pairs deeper than this are residual collisions."""
    zone_tolerance_cm: float = 0.1
    """Reporting: footprints further outside the zone than this are reported."""
    device: str = "cpu"
    """Torch device of the optimisation."""
    report_relations: bool = True
    """Rebuild each result's graph and measure relation preservation (host work)."""
    batch_size: int = 512
    """Scenes per optimisation batch in :func:`repair`."""

    @classmethod
    def from_config(cls, overrides: Sequence[str] = ()) -> TTOConfig:
        """``configs/tto.yaml`` with ``key=value`` overrides."""
        from physcene.config import ConfigError, load_dataclass

        config = load_dataclass(cls, "tto", list(overrides))
        if config.in_children not in IN_MODES:
            raise ConfigError(f"tto: in_children must be one of {list(IN_MODES)}, got {config.in_children!r}")
        if not 0 < config.in_lr_scale <= 1:
            raise ConfigError(f"tto: in_lr_scale must be in (0, 1], got {config.in_lr_scale}")
        if config.steps < 0 or config.lr <= 0 or config.check_every < 1 or config.batch_size < 1:
            raise ConfigError(f"tto: steps >= 0, lr > 0, check_every >= 1, batch_size >= 1 required, "
                              f"got steps={config.steps} lr={config.lr} check_every={config.check_every} "
                              f"batch_size={config.batch_size}")
        return config


@dataclass
class TTOResult:
    """One repaired scene: energies in cm (engine units, optimised pairs), displacement in cm."""

    scene: Scene
    energy_before: float
    energy_after: float
    max_displacement_cm: float
    report: dict = field(default_factory=dict)


@dataclass
class TTOProblem:
    """A padded batch of S scenes × N slots on one device (host-built, see :func:`build_problem`)."""

    batch: object               # the engine's SceneBatch (poses/sizes/mask/ids)
    mask: torch.Tensor          # (S, N) bool, real objects
    kind: torch.Tensor          # (S, N) long, ROOT / ON / IN
    parent: torch.Tensor        # (S, N) long, parent slot (own slot for roots)
    depth_masks: list           # per depth d >= 1: (S, N) bool, slots at depth d
    xi0: torch.Tensor           # (S, N, 4) initial ξ: x|u, y|v (metres), yaw|ψ (rad), lift (10 cm units)
    trainable: torch.Tensor     # (S, N) bool, ξ free (roots, on children, sliding in children)
    bounded: torch.Tensor       # (S, N) bool, (u, v) kept over the parent (on + sliding in children)
    lift_max: torch.Tensor      # (S, N) ξ lift units, upper bound of the lift (0: no lift)
    zloc: torch.Tensor          # (S, N) cm: root h/2; on parent_h/2 + h/2; in z − z_parent
    sizes: torch.Tensor         # (S, N, 3) cm
    raw_poses: torch.Tensor     # (S, N, 4) cm / rad, the input
    parent_half: torch.Tensor   # (S, N, 2) cm, the parent's half width / depth (on children)
    zone: torch.Tensor          # (S, 4) cm, xmin xmax ymin ymax
    restricted: torch.Tensor    # (S, R, 4) cm
    restricted_mask: torch.Tensor  # (S, R) bool
    near: torch.Tensor          # (S, K, 2) long, (object slot, reference slot)
    near_axis: torch.Tensor     # (S, K) long, 0 = x, 1 = y
    near_sign: torch.Tensor     # (S, K) float, ±1
    near_margin: torch.Tensor   # (S, K) cm
    near_mask: torch.Tensor     # (S, K) bool
    frozen_energy: torch.Tensor  # (S,) cm, energy of pairs inside one rigid in-body (constant; 0 with slide)
    contact: torch.Tensor       # (S, P, 2) long, pairs penetrating in the input or its snapped start
    contact_mask: torch.Tensor  # (S, P) bool
    group: np.ndarray           # (S, N) rigid-body root slot of every object (host; own slot with slide)
    body: np.ndarray            # (S, N) container-body root slot: the top container of an in chain (host)
    reattached: list = field(default_factory=list)  # per scene, [(object id, support id)]

    @property
    def n_scene(self) -> int:
        return self.mask.shape[0]


# --------------------------------------------------------------------------------------------
# Host side: from hierarchical scenes to padded tensors
# --------------------------------------------------------------------------------------------
def _kinds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(kind, parent slot) per object of a hierarchical scene."""
    index = {o.instance_id: i for i, o in enumerate(scene.objects)}
    kind = np.zeros(len(scene), dtype=np.int64)
    parent = np.arange(len(scene), dtype=np.int64)
    for i, o in enumerate(scene.objects):
        if o.parent not in (None, TABLE):
            parent[i] = index[o.parent]
            kind[i] = IN if o.relation == "in" else ON
    return kind, parent


def _depths(parent: np.ndarray) -> np.ndarray:
    depth = np.zeros(len(parent), dtype=np.int64)
    for i in range(len(parent)):
        j = i
        while parent[j] != j:
            j = parent[j]
            depth[i] += 1
    return depth


def _relative(child: SceneObject, parent: SceneObject) -> tuple[float, float, float]:
    """The child's centre offset in the parent's yawed frame (cm) and relative yaw (rad)."""
    dx, dy = child.center[0] - parent.center[0], child.center[1] - parent.center[1]
    c, s = math.cos(parent.yaw), math.sin(parent.yaw)
    return c * dx + s * dy, -s * dx + c * dy, child.yaw - parent.yaw


def build_problem(scenes: Sequence[Scene], engine, config: TTOConfig,
                  freeze: Sequence[set[str]] | None = None) -> TTOProblem:
    """Pack hierarchical, non-empty ``scenes`` (every object has a parent) for :func:`optimise`.

    ``freeze``: per scene, ids whose ξ is held at its start (their subtrees still follow them).
    """
    from physcene.graph import near_references

    batch = engine.pack(list(scenes))
    n_scene, n_slot = batch.mask.shape
    for s, scene in enumerate(scenes):
        if list(batch.ids[s][: len(scene)]) != scene.ids():
            raise RuntimeError("engine.pack changed the object order; TTO relies on scene order")
    n_restricted = max([len(sc.restricted_zones) for sc in scenes] + [1])
    n_near = max([len(sc) for sc in scenes] + [1])
    kind = np.zeros((n_scene, n_slot), np.int64)
    parent = np.tile(np.arange(n_slot), (n_scene, 1))
    depth = np.zeros((n_scene, n_slot), np.int64)
    xi0 = np.zeros((n_scene, n_slot, 4))
    lift_max = np.zeros((n_scene, n_slot))
    zloc = np.zeros((n_scene, n_slot))
    parent_half = np.zeros((n_scene, n_slot, 2))
    zone = np.zeros((n_scene, 4))
    restricted = np.zeros((n_scene, n_restricted, 4))
    restricted_mask = np.zeros((n_scene, n_restricted), bool)
    near = np.zeros((n_scene, n_near, 2), np.int64)
    near_axis = np.zeros((n_scene, n_near), np.int64)
    near_sign = np.ones((n_scene, n_near))
    near_margin = np.zeros((n_scene, n_near))
    near_mask = np.zeros((n_scene, n_near), bool)
    body = np.tile(np.arange(n_slot), (n_scene, 1))
    reattached = []
    held = np.zeros((n_scene, n_slot), bool)
    for s, scene in enumerate(scenes):
        n = len(scene)
        hold = freeze[s] if freeze else set()
        held[s, :n] = [oid in hold for oid in scene.ids()]
        attached, notes = _reattach(scene, config) if not hold else (scene, [])
        reattached.append(notes)
        objs = attached.objects
        k, p = _kinds(attached)
        kind[s, :n], parent[s, :n], depth[s, :n] = k, p, _depths(p)
        for i in np.argsort(depth[s, :n], kind="stable"):  # parents before children
            o = objs[i]
            if k[i] == ROOT:
                xi0[s, i] = (o.center[0] / _CM, o.center[1] / _CM, o.yaw, 0.0)
                zloc[s, i] = o.center[2] if held[s, i] else 0.5 * o.size[2]  # held: exactly as input
                continue
            par = objs[p[i]]
            u, v, psi = _relative(o, par)
            xi0[s, i] = (u / _CM, v / _CM, psi, 0.0)
            if k[i] == IN and config.in_children == "slide" and not held[s, i]:
                # rise out of a floor it was sunk into, keeping > half its height inside
                room = par.zmax - o.zmin - 0.55 * o.size[2]
                lift_max[s, i] = max(0.0, min(config.in_lift_cm, room)) / _LIFT_CM
            parent_half[s, i] = (0.5 * par.size[0], 0.5 * par.size[1])
            zloc[s, i] = (0.5 * (par.size[2] + o.size[2]) + config.contact_gap_cm
                          if k[i] == ON and not held[s, i] else o.center[2] - par.center[2])
            body[s, i] = body[s, p[i]] if k[i] == IN else i
        zone[s] = scene.zone.to_list()
        for r, rz in enumerate(scene.restricted_zones):
            restricted[s, r], restricted_mask[s, r] = rz.to_list(), True
        index = {o.instance_id: i for i, o in enumerate(objs)}
        refs = [(a, r) for a, r in near_references(scene).items() if r is not None]
        for q, (a, (ref, direction)) in enumerate(refs):
            ia, ib = index[a], index[ref]
            axis, sign = DIRECTION_AXES[direction]
            off = np.subtract(objs[ia].center[:2], objs[ib].center[:2])
            slack = sign * off[axis] - abs(off[1 - axis])
            near[s, q], near_axis[s, q], near_sign[s, q] = (ia, ib), axis, sign
            near_margin[s, q] = min(config.near_margin_cm, max(slack, 0.0))
            near_mask[s, q] = True
    mask = batch.mask.detach().cpu().numpy().astype(bool)
    dev = torch.device(config.device)
    f32 = dict(dtype=torch.float32, device=dev)
    i64 = dict(dtype=torch.long, device=dev)
    max_depth = int(depth.max()) if depth.size else 0
    kind_t = torch.as_tensor(kind, **i64)
    slide = config.in_children == "slide"
    # frozen: a container and its in children are one rigid body; slide: every object its own
    group = np.tile(np.arange(n_slot), (n_scene, 1)) if slide else body
    bounded = (kind_t == ON) | ((kind_t == IN) & slide)
    problem = TTOProblem(
        batch=batch,
        mask=torch.as_tensor(mask, device=dev),
        kind=kind_t,
        parent=torch.as_tensor(parent, **i64),
        depth_masks=[torch.as_tensor(depth == d, device=dev) for d in range(1, max_depth + 1)],
        xi0=torch.as_tensor(xi0, **f32),
        trainable=torch.as_tensor(mask & ~held, device=dev) & ((kind_t != IN) | slide),
        bounded=bounded,
        lift_max=torch.as_tensor(lift_max, **f32),
        zloc=torch.as_tensor(zloc, **f32),
        sizes=batch.sizes.to(**f32),
        raw_poses=batch.poses.to(**f32),
        parent_half=torch.as_tensor(parent_half, **f32),
        zone=torch.as_tensor(zone, **f32),
        restricted=torch.as_tensor(restricted, **f32),
        restricted_mask=torch.as_tensor(restricted_mask, device=dev),
        near=torch.as_tensor(near, **i64),
        near_axis=torch.as_tensor(near_axis, **i64),
        near_sign=torch.as_tensor(near_sign, **f32),
        near_margin=torch.as_tensor(near_margin, **f32),
        near_mask=torch.as_tensor(near_mask, device=dev),
        frozen_energy=_frozen_energy(engine, batch, group).to(**f32),
        contact=torch.zeros(n_scene, 1, 2, **i64),
        contact_mask=torch.zeros(n_scene, 1, dtype=torch.bool, device=dev),
        group=group,
        body=body,
        reattached=reattached,
    )
    _seat_contents(engine, problem)
    problem.contact, problem.contact_mask = _contact_pairs(engine, problem)
    return problem


_SEAT_GRID = 13  # lifts tried per content: 0, 1/12, ..., 1 × its lift_max


def _seat_contents(engine, problem: TTOProblem) -> None:
    """Start every liftable ``in`` child at the lowest lift that minimises its energy with its container.

    Why: a content sunk into its container's floor by more than half the floor's thickness is
    pushed further down by the SDF (the nearest surface is the floor's underside), so gradient steps
    on the lift cannot bring it out; ``on`` children are snapped onto their support for the same
    reason. All contents are tried at once on a grid of lifts (``_SEAT_GRID`` engine passes over
    the batch); the lift stays a parameter afterwards.
    """
    lift_max = problem.lift_max.cpu().numpy()
    if not np.any(lift_max > 0):
        return
    slots = problem.batch.pair_slots()
    parent = problem.parent.cpu().numpy()
    s_, i_, j_ = slots[:, 0], slots[:, 1], slots[:, 2]
    # the (content, container) pairs: i < j, either may be the child
    child = np.where(parent[s_, j_] == i_, j_, np.where(parent[s_, i_] == j_, i_, -1))
    keep = (child >= 0) & (lift_max[s_, np.maximum(child, 0)] > 0)
    if not np.any(keep):
        return
    rows, s_, child = np.nonzero(keep)[0], s_[keep], child[keep]
    grid = np.linspace(0.0, 1.0, _SEAT_GRID)
    energy = np.zeros((_SEAT_GRID, len(rows)))
    xi = problem.xi0.clone()
    with torch.no_grad():
        for g, t in enumerate(grid):
            xi[..., 3] = problem.lift_max * float(t)
            out = engine.evaluate(problem.batch, forward_kinematics(problem, xi))
            energy[g] = out["pair_energy"].detach().cpu().numpy()[rows]
    best = energy.min(axis=0)
    first = np.argmax(energy <= best + 1e-6 * (1.0 + best), axis=0)  # the lowest lift that is as good
    lift = np.zeros_like(lift_max)
    lift[s_, child] = grid[first] * lift_max[s_, child]
    problem.xi0[..., 3] = torch.as_tensor(lift, dtype=problem.xi0.dtype, device=problem.xi0.device)


def _reattach(scene: Scene, config: TTOConfig) -> tuple[Scene, list[tuple[str, str]]]:
    """Put back on its support a table-level object that hovers over or is sunk into one.

    A table-level object whose bottom is off the table (|zmin| > 0.05 cm) but within
    ``reattach_gap_cm`` of the top of an object below it (lower centre, not in its own subtree)
    that covers more than the graph's on-overlap of its footprint is optimised as ``on`` the
    highest such support. Dropping it to the table instead would put it inside the support's
    footprint, where the SDF pushes only vertically (z is held) and the object is stuck.
    """
    if config.reattach_gap_cm <= 0:
        return scene, []
    from physcene.graph import GraphConfig, footprint_overlap

    min_overlap = GraphConfig().on_footprint_overlap
    children: dict[str, list[str]] = {}
    for o in scene.objects:
        children.setdefault(o.parent, []).append(o.instance_id)
    moves: dict[str, str] = {}
    for a in scene.objects:
        if a.parent not in (None, TABLE) or abs(a.zmin) <= 0.05:
            continue
        subtree, stack = {a.instance_id}, [a.instance_id]
        while stack:
            for c in children.get(stack.pop(), []):
                subtree.add(c)
                stack.append(c)
        supports = [b for b in scene.objects
                    if b.instance_id not in subtree and b.center[2] < a.center[2]
                    and abs(a.zmin - b.zmax) < config.reattach_gap_cm
                    and footprint_overlap(a, b) > min_overlap]
        if supports:
            moves[a.instance_id] = max(supports, key=lambda b: (b.zmax, b.instance_id)).instance_id
    if not moves:
        return scene, []
    return (scene.with_objects(o.moved(parent=moves[o.instance_id], relation="on")
                               if o.instance_id in moves else o for o in scene.objects),
            sorted(moves.items()))


def _frozen_energy(engine, batch, group: np.ndarray) -> torch.Tensor:
    """(S,) cm: the input's energy over pairs inside one rigid in-body.

    Such a pair keeps its relative pose under every ξ, so its energy is a constant the optimiser
    cannot change (and its gradient cancels through the forward kinematics); it is subtracted so
    that "collision-free" means free of the collisions TTO is responsible for.
    """
    slots = batch.pair_slots()
    n_scene = batch.mask.shape[0]
    if len(slots) == 0 or np.all(group == np.arange(group.shape[1])):  # no rigid in-body
        return torch.zeros(n_scene)
    out = engine.evaluate(batch)
    same = group[slots[:, 0], slots[:, 1]] == group[slots[:, 0], slots[:, 2]]
    energy = out["pair_energy"].detach().cpu().numpy().astype(np.float64)
    return torch.as_tensor(np.bincount(slots[same, 0], weights=energy[same], minlength=n_scene))


def _contact_pairs(engine, problem: TTOProblem) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs (outside one container body) that penetrate in the input or at ξ0: (S, P, 2), (S, P).

    They get the footprint proxy of :func:`_footprint_overlap`. Pairs inside one container body
    (a container and its contents, contents of one container) never do: the proxy would push a
    content out of its container's footprint, which the ``in`` edge forbids.
    """
    slots = problem.batch.pair_slots()
    n_scene = problem.n_scene
    if len(slots) == 0:
        return problem.contact, problem.contact_mask
    hot = np.zeros(len(slots), bool)
    for poses in (problem.raw_poses, forward_kinematics(problem, problem.xi0)):
        hot |= engine.evaluate(problem.batch, poses)["pair_energy"].detach().cpu().numpy() > 0
    hot &= problem.body[slots[:, 0], slots[:, 1]] != problem.body[slots[:, 0], slots[:, 2]]
    slots = slots[hot]
    counts = np.bincount(slots[:, 0], minlength=n_scene)
    width = max(1, int(counts.max()) if counts.size else 1)
    pairs = np.zeros((n_scene, width, 2), np.int64)
    mask = np.zeros((n_scene, width), bool)
    rank = np.arange(len(slots)) - np.repeat(np.cumsum(counts) - counts, counts)
    pairs[slots[:, 0], rank] = slots[:, 1:]
    mask[slots[:, 0], rank] = True
    dev = problem.mask.device
    return torch.as_tensor(pairs, device=dev), torch.as_tensor(mask, device=dev)


# --------------------------------------------------------------------------------------------
# Device side: forward kinematics, loss terms, the Adam loop
# --------------------------------------------------------------------------------------------
def forward_kinematics(problem: TTOProblem, xi: torch.Tensor) -> torch.Tensor:
    """Absolute poses (S, N, 4) cm / rad from ξ (S, N, 4); one gather per tree depth."""
    x, y, yaw = xi[..., 0] * _CM, xi[..., 1] * _CM, xi[..., 2]
    zloc = problem.zloc + xi[..., 3] * _LIFT_CM  # lift is 0 except for sliding in children
    pose = torch.stack((x, y, zloc, yaw), dim=-1)  # correct for roots
    index = problem.parent.unsqueeze(-1).expand(-1, -1, 4)
    for at_depth in problem.depth_masks:
        par = torch.gather(pose, 1, index)
        c, s = torch.cos(par[..., 3]), torch.sin(par[..., 3])
        child = torch.stack((par[..., 0] + c * x - s * y, par[..., 1] + s * x + c * y,
                             par[..., 2] + zloc, par[..., 3] + yaw), dim=-1)
        pose = torch.where(at_depth.unsqueeze(-1), child, pose)
    return pose


def _footprints(poses: torch.Tensor, sizes: torch.Tensor) -> torch.Tensor:
    """Yawed footprint corners (S, N, 4, 2) cm."""
    hw, hd = 0.5 * sizes[..., 0], 0.5 * sizes[..., 1]
    lx = torch.stack((-hw, hw, hw, -hw), dim=-1)
    ly = torch.stack((-hd, -hd, hd, hd), dim=-1)
    c, s = torch.cos(poses[..., 3:4]), torch.sin(poses[..., 3:4])
    return torch.stack((poses[..., 0:1] + c * lx - s * ly, poses[..., 1:2] + s * lx + c * ly), dim=-1)


def _footprint_overlap(problem: TTOProblem, poses: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """(S,) cm: Σ over contact pairs whose z-ranges overlap of the footprint-AABB penetration depth.

    Why: where one object stands in a thin one (a bottle in a tray's floor, both on the table) the
    SDF pushes only vertically, and z is held; this proxy gives the sideways direction out.
    """
    lo, hi = corners.amin(dim=2), corners.amax(dim=2)  # (S, N, 2)
    half_h = 0.5 * problem.sizes[..., 2]
    zlo, zhi = poses[..., 2] - half_h, poses[..., 2] + half_h

    def pick(t: torch.Tensor, k: int) -> torch.Tensor:
        idx = problem.contact[..., k]
        if t.dim() == 2:
            return torch.gather(t, 1, idx)
        return torch.gather(t, 1, idx.unsqueeze(-1).expand(-1, -1, t.shape[-1]))

    # the shortest of the four sideways moves that separates the boxes (also when one contains
    # the other, where the plain overlap width has no gradient)
    push = torch.minimum(pick(hi, 1) - pick(lo, 0), pick(hi, 0) - pick(lo, 1))  # (S, P, 2)
    z_overlap = torch.minimum(pick(zhi, 0), pick(zhi, 1)) - torch.maximum(pick(zlo, 0), pick(zlo, 1))
    depth = torch.relu(push.amin(dim=-1)) * (z_overlap > 0) * problem.contact_mask
    return depth.sum(-1)


def _zone_violation(problem: TTOProblem, poses: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """(S,) cm: Σ corner distance outside the zone + Σ overlap depth with restricted zones."""
    z = problem.zone[:, None, None, :]
    outside = (torch.relu(z[..., 0] - corners[..., 0]) + torch.relu(corners[..., 0] - z[..., 1])
               + torch.relu(z[..., 2] - corners[..., 1]) + torch.relu(corners[..., 1] - z[..., 3]))
    total = (outside.sum(-1) * problem.mask).sum(-1)
    lo, hi = corners.amin(dim=2), corners.amax(dim=2)  # (S, N, 2) footprint AABB
    r = problem.restricted[:, None, :, :]  # (S, 1, R, 4)
    depth = torch.minimum(
        torch.minimum(hi[..., None, 0] - r[..., 0], r[..., 1] - lo[..., None, 0]),
        torch.minimum(hi[..., None, 1] - r[..., 2], r[..., 3] - lo[..., None, 1]))
    inside = torch.relu(depth) * problem.restricted_mask[:, None, :] * problem.mask[..., None]
    return total + inside.sum((1, 2))


def _support_bounds(problem: TTOProblem, xi: torch.Tensor) -> torch.Tensor:
    """(S, N, 2) metres: how far an on (or sliding in) child's centre may sit from its parent's centre.

    Per axis of the parent frame, never further out than the input was and always allowed to be
    fully over the support: max(|u0|, |P − h(ψ)|), with h the child's half extent there.
    """
    psi = xi[..., 2]
    c, s = torch.cos(psi).abs(), torch.sin(psi).abs()
    hw, hd = 0.5 * problem.sizes[..., 0], 0.5 * problem.sizes[..., 1]
    half = torch.stack((c * hw + s * hd, s * hw + c * hd), dim=-1)
    return torch.maximum(problem.xi0[..., :2].abs(), (problem.parent_half - half).abs() / _CM)


def _support_violation(problem: TTOProblem, xi: torch.Tensor) -> torch.Tensor:
    """(S,) metres: on / sliding in children's offsets beyond their parents' bounds."""
    excess = torch.relu(xi[..., :2].abs() - _support_bounds(problem, xi)).sum(-1)
    return (excess * problem.bounded).sum(-1)


def _near_violation(problem: TTOProblem, poses: torch.Tensor) -> torch.Tensor:
    """(S,) cm: Σ ReLU(margin − (sign·d_axis − |d_other|)) over near relations."""
    a = torch.gather(poses[..., :2], 1, problem.near[..., 0:1].expand(-1, -1, 2))
    b = torch.gather(poses[..., :2], 1, problem.near[..., 1:2].expand(-1, -1, 2))
    d = a - b  # (S, K, 2)
    along = torch.gather(d, 2, problem.near_axis.unsqueeze(-1)).squeeze(-1) * problem.near_sign
    other = torch.gather(d, 2, (1 - problem.near_axis).unsqueeze(-1)).squeeze(-1).abs()
    return (torch.relu(problem.near_margin - (along - other)) * problem.near_mask).sum(-1)


def penetration(engine, problem: TTOProblem, poses: torch.Tensor) -> torch.Tensor:
    """(S,) cm: the engine's differentiable energy over the pairs the optimisation can change."""
    return engine.penetration_energy(problem.batch, poses) - problem.frozen_energy


@dataclass
class TTOSolution:
    """Device results of :func:`optimise` for S scenes."""

    xi: torch.Tensor          # (S, N, 4) best ξ
    poses: torch.Tensor       # (S, N, 4) cm, poses of the best ξ
    energy: torch.Tensor      # (S,) cm, optimised energy of the best ξ
    energy_input: torch.Tensor  # (S,) cm, the same energy of the unmodified input
    steps: torch.Tensor       # (S,) long, steps taken before the scene stopped


def optimise(problem: TTOProblem, engine, config: TTOConfig) -> TTOSolution:
    """Batched Adam over ξ; host syncs only every ``check_every`` steps (all-stopped test)."""
    xi0 = problem.xi0
    # (S, N, 4): x, y, yaw of every free object; the lift only where it has room
    trainable = problem.trainable.unsqueeze(-1) & torch.cat(
        (torch.ones_like(xi0[..., :3], dtype=torch.bool), (problem.lift_max > 0).unsqueeze(-1)), dim=-1)
    # Adam's first steps are about lr per coordinate whatever the gradient's size (1 cm): a sliding
    # content's (u, v) are optimised in units scaled by in_lr_scale, so that one step cannot carry
    # it through a container wall a few mm thick (it would then be pushed outwards, into the wall)
    unit = torch.ones_like(xi0)
    unit[..., :2] = torch.where(((problem.kind == IN) & problem.trainable).unsqueeze(-1),
                                config.in_lr_scale, 1.0)
    theta = (xi0 / unit).requires_grad_(True)  # (S, N, 4) Adam's parameter: ξ = θ · unit
    opt = torch.optim.Adam([theta], lr=config.lr, fused=xi0.device.type == "cuda")  # one kernel per step
    n = problem.n_scene
    dev = xi0.device
    inf = torch.full((n,), math.inf, device=dev)
    best_xi, best_e, best_rest = xi0.clone(), inf.clone(), inf.clone()
    active = torch.ones(n, dtype=torch.bool, device=dev)
    steps_taken = torch.full((n,), config.steps, dtype=torch.long, device=dev)
    on = problem.bounded
    for step in range(config.steps + 1):
        xi = theta * unit
        xi_eff = torch.where(trainable, xi, xi0)  # frozen in children, held objects, padding stay put
        poses = forward_kinematics(problem, xi_eff)
        energy = penetration(engine, problem, poses)
        corners = _footprints(poses, problem.sizes)  # (S, N, 4, 2)
        hinge_cm = (_CM * _support_violation(problem, xi_eff) + _near_violation(problem, poses),
                    _zone_violation(problem, poses, corners))
        drift = ((xi_eff - xi0) ** 2 * trainable).sum((1, 2))
        rest = (config.lambda_rel * hinge_cm[0] + config.lambda_zone * hinge_cm[1]) / _CM \
            + config.lambda_reg * drift
        with torch.no_grad():
            e, r = energy.detach(), rest.detach()
            free, best_free = e <= config.stop_energy_cm, best_e <= config.stop_energy_cm
            better = active & torch.where(free & best_free, r < best_rest, e < best_e)
            best_xi = torch.where(better[:, None, None], xi_eff.detach(), best_xi)
            best_e, best_rest = torch.where(better, e, best_e), torch.where(better, r, best_rest)
            if config.early_stop:
                done = active & free & (hinge_cm[0] + hinge_cm[1] <= config.stop_violation_cm)
                steps_taken = torch.where(done, torch.full_like(steps_taken, step), steps_taken)
                active = active & ~done
        if step == config.steps:
            break
        proxy = _footprint_overlap(problem, poses, corners) if config.footprint_proxy else 0.0
        loss = ((config.lambda_sdf * (energy + proxy) / _CM + rest) * active).sum()
        opt.zero_grad(set_to_none=False)
        loss.backward()
        # cosine decay lr -> lr_final: full-size steps travel, small ones settle at the contacts
        # (a host float: no sync)
        opt.param_groups[0]["lr"] = config.lr_final + 0.5 * (config.lr - config.lr_final) * (
            1.0 + math.cos(math.pi * step / max(config.steps, 1)))
        opt.step()
        with torch.no_grad():
            xi = theta * unit
            bound = _support_bounds(problem, xi)
            projected = torch.maximum(torch.minimum(xi[..., :2], bound), -bound)
            xi[..., :2] = torch.where(on.unsqueeze(-1), projected, xi[..., :2])
            xi[..., 3] = torch.minimum(xi[..., 3].clamp_min(0.0), problem.lift_max)
            theta.copy_(torch.where(active[:, None, None], xi, best_xi) / unit)
        if config.early_stop and (step + 1) % config.check_every == 0 and not bool(active.any()):
            break
    with torch.no_grad():
        poses = forward_kinematics(problem, best_xi)
        energy_input = penetration(engine, problem, problem.raw_poses)
    return TTOSolution(best_xi, poses, best_e, energy_input, steps_taken)


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------
def repair(scenes: Sequence[Scene], config: TTOConfig | None = None, engine=None,
           freeze: Sequence[set[str]] | None = None) -> list[TTOResult]:
    """Project each scene onto the collision-free set without breaking its hierarchy.

    ``scenes`` may carry a hierarchy (parent/relation, e.g. from CTRC) or not (it is built with
    :func:`physcene.graph.build_hierarchy`). ``freeze``: per scene, ids held exactly where the
    input has them (their subtrees still follow them; a scene with held objects is not
    re-attached), e.g. every object but the ones a reward blamed. Returns one :class:`TTOResult`
    per scene, in order; the returned scene is the input with new poses (annotations as in the
    input).
    """
    from physcene.graph import ensure_hierarchy

    config = config or TTOConfig.from_config()
    if engine is None:
        from physcene.physics import PhysicsEngine

        engine = PhysicsEngine(device=config.device)
    scenes = list(scenes)
    if freeze is not None and len(freeze) != len(scenes):
        raise ValueError(f"freeze: {len(freeze)} sets of held ids for {len(scenes)} scenes")
    results: list[TTOResult | None] = [None] * len(scenes)
    todo = [i for i, sc in enumerate(scenes) if len(sc) > 0]
    for i, sc in enumerate(scenes):
        if len(sc) == 0:
            results[i] = TTOResult(sc, 0.0, 0.0, 0.0, _empty_report(sc))
    for start in range(0, len(todo), config.batch_size):
        chunk = todo[start:start + config.batch_size]
        hier = [ensure_hierarchy(scenes[i]) for i in chunk]
        held = [set(freeze[i]) for i in chunk] if freeze is not None else None
        problem = build_problem(hier, engine, config, held)
        solution = optimise(problem, engine, config)
        for k, result in enumerate(_results(problem, solution, [scenes[i] for i in chunk], hier,
                                            engine, config)):
            results[chunk[k]] = result
        _second_pass(chunk, hier, scenes, results, engine, config, held)
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
    redo = [k for k, i in enumerate(chunk) if results[i].report["relations"]["in_on_broken"]]
    if not redo:
        return
    from physcene.graph import build_hierarchy

    freeze = []
    for k in redo:
        after = results[chunk[k]].scene
        taken = build_hierarchy(after.with_objects(o.moved(parent=None, relation=None)
                                                   for o in after.objects))
        by_id, ids = hier[k].by_id(), set()
        for child in results[chunk[k]].report["relations"]["in_on_broken"]:
            # the child's chain and the chain of what the rebuilt graph gave it to
            for oid in (child, taken.get(child).parent):
                while oid in by_id and oid not in ids:
                    ids.add(oid)
                    oid = by_id[oid].parent
        freeze.append(ids | held[k] if held is not None else ids)
    sub = [hier[k] for k in redo]
    problem = build_problem(sub, engine, config, freeze)
    solution = optimise(problem, engine, config)
    for k, again in zip(redo, _results(problem, solution, [scenes[chunk[k]] for k in redo], sub,
                                       engine, config)):
        first = results[chunk[k]]
        if (again.report["relations"]["in_on_kept"] > first.report["relations"]["in_on_kept"]
                and again.energy_after <= first.energy_before):
            again.report["held"] = sorted(freeze[redo.index(k)])
            results[chunk[k]] = again


def summarize(results: Sequence[TTOResult]) -> dict:
    """Dataset figures of :func:`repair` results (the issue's acceptance measures).

    ``collision_free``: fraction of scenes without any pair deeper than ``collision_depth_cm``
    (every pair counted, the issue's measure); ``collision_free_excluding_frozen`` leaves out pairs
    inside one rigid in-body (``in_children=frozen`` only: TTO may not move those);
    ``scenes_with_frozen_residual`` / ``scenes_with_in_body_residual`` count scenes whose residual
    collisions include such a pair / a pair inside one container body. Relation fractions are pooled
    over all edges.
    """
    n = len(results)
    reports = [r.report for r in results]
    rel = [r["relations"] for r in reports if r.get("relations")]
    edges = sum(k["in_on_edges"] for k in rel)
    nears = sum(k["near_relations"] for k in rel)
    disp = [r.max_displacement_cm for r in results]
    residual = [r.get("residual_collisions", []) for r in reports]
    return {
        "scenes": n,
        "collision_free": sum(not pairs for pairs in residual) / max(n, 1),
        "collision_free_excluding_frozen":
            sum(all(p["frozen"] for p in pairs) for pairs in residual) / max(n, 1),
        "scenes_with_frozen_residual": sum(any(p["frozen"] for p in pairs) for pairs in residual),
        "scenes_with_in_body_residual": sum(any(p.get("in_body") for p in pairs) for pairs in residual),
        "energy_increased": sum(r.energy_after > r.energy_before for r in results),
        "kept_input": sum(bool(r.get("kept_input")) for r in reports),
        "in_on_edges": edges,
        "in_on_kept": sum(k["in_on_edges"] - len(k["in_on_broken"]) for k in rel) / edges if edges else 1.0,
        "near_relations": nears,
        "near_kept": sum(k["near_relations"] - len(k["near_broken"]) for k in rel) / nears if nears else 1.0,
        "median_max_displacement_cm": float(np.median(disp)) if disp else 0.0,
        "mean_steps": float(np.mean([r.get("steps", 0) for r in reports])) if reports else 0.0,
    }


def _empty_report(scene: Scene) -> dict:
    return {"n_objects": 0, "energy_before": 0.0, "energy_after": 0.0, "max_depth_before_cm": 0.0,
            "max_depth_after_cm": 0.0, "collision_free": True, "residual_collisions": [],
            "max_displacement_cm": 0.0,
            "steps": 0, "kept_input": True, "relations": None, "unsatisfied": []}


def _free_energy(engine, problem: TTOProblem, poses: torch.Tensor) -> np.ndarray:
    """(S,) float64 cm: Σ pair energies over pairs outside any rigid in-body (exact, for reports)."""
    out = engine.evaluate(problem.batch, poses)
    slots = problem.batch.pair_slots()
    if len(slots) == 0:
        return np.zeros(problem.n_scene)
    free = problem.group[slots[:, 0], slots[:, 1]] != problem.group[slots[:, 0], slots[:, 2]]
    energy = out["pair_energy"].detach().cpu().numpy().astype(np.float64)
    return np.bincount(slots[free, 0], weights=energy[free], minlength=problem.n_scene)


def _results(problem: TTOProblem, solution: TTOSolution, inputs: list[Scene], hier: list[Scene],
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
        report = _describe(hier[s], after, problem.group[s, :len(after)], problem.body[s, :len(after)],
                           before_score, after_score, s, config)
        report["reattached"] = [{"object": a, "on": b} for a, b in problem.reattached[s]]
        report.update(energy_before=float(e_before[s]), energy_after=e_after,
                      max_displacement_cm=float(disp.max()), mean_displacement_cm=float(disp.mean()),
                      steps=int(steps[s]), kept_input=bool(kept[s]))
        if kept[s]:
            report["unsatisfied"].append("no iterate had less penetration energy than the input: "
                                         "input returned unchanged")
        results.append(TTOResult(after, float(e_before[s]), e_after, float(disp.max()), report))
    return results


def _describe(before: Scene, after: Scene, group: np.ndarray, body: np.ndarray, before_score,
              after_score, s: int, config: TTOConfig) -> dict:
    """Per-scene report: depths, residual collisions, relations kept, what could not be satisfied.

    A residual pair is ``frozen`` when both are in one rigid in-body (``in_children=frozen``: TTO may
    not move them relative to each other) and ``in_body`` when both are in one container body (a
    container and its contents), whichever the mode.
    """
    ids = after.ids()
    unsatisfied: list[str] = []
    residual = []
    for i, j, depth in after_score.pairs[s]:
        if float(depth) > config.collision_depth_cm:
            frozen, in_body = bool(group[i] == group[j]), bool(body[i] == body[j])
            residual.append({"a": ids[i], "b": ids[j], "depth_cm": round(float(depth), 4), "frozen": frozen,
                             "in_body": in_body})
            why = (" (both in one rigid in-body: frozen by the hierarchy)" if frozen else
                   " (inside one container: the content does not fit where the in edge allows)"
                   if in_body else "")
            unsatisfied.append(f"{ids[i]} and {ids[j]} still penetrate by {float(depth):.2f} cm{why}")
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
    report = {
        "n_objects": len(after),
        "max_depth_before_cm": float(before_score.max_depth[s]),
        "max_depth_after_cm": float(after_score.max_depth[s]),
        "collision_free": not residual,
        "residual_collisions": residual,
        "relations": None,
        "unsatisfied": unsatisfied,
    }
    if config.report_relations:
        kept = relation_preservation(before, after)
        report["relations"] = kept
        unsatisfied.extend(f"{oid}: {before.get(oid).relation} edge to {before.get(oid).parent} broken"
                           for oid in kept["in_on_broken"])
        unsatisfied.extend(f"{oid}: near direction to its reference lost" for oid in kept["near_broken"])
    return report
