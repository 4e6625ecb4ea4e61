"""The TTO problem: hierarchical scenes packed as padded tensors, and ξ -> poses.

Parametrisation ξ (METRES and radians; the engine and the scene work in cm):
- table-level objects (parent = TABLE): (x, y, yaw) absolute; z held at h/2 (resting on the table);
- ``on`` children: (u, v, ψ) = the centre offset in the parent's yawed frame and the yaw relative to
  the parent; z held at the support's top (zmax(parent) + h/2);
- ``in`` children (``in_children``): ``slide`` (default) = (u, v, ψ) in the container's yawed
  frame like an ``on`` child, z offset to the container held (the content stays in, at its height),
  footprint kept inside the container's; ``frozen`` (the paper's) = offset, z offset and relative
  yaw are constants, so a container and its contents move as one rigid body.
Absolute poses come from a differentiable forward kinematics over the forest, one batched gather
per tree depth (:func:`forward_kinematics`; it lives here, beside the parametrisation it inverts,
because building a problem already evaluates it to seat contents and find contact pairs).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from physcene.graph import GraphConfig, footprint_overlap, near_references
from physcene.relations import DIRECTION_AXES
from physcene.scene import TABLE, Scene, SceneObject, footprint_half_extents
from physcene.tto.config import TTOConfig

__all__ = ["CM", "IN", "LIFT_CM", "ON", "ROOT", "TTOProblem", "build_problem", "forward_kinematics",
           "reattach", "separate_deep_pairs"]

# Kinds of parametrisation per object slot.
ROOT, ON, IN = 0, 1, 2
CM = 100.0  # cm per metre: ξ is in metres, poses in cm
LIFT_CM = 10.0  # cm per unit of ξ's lift component: an Adam step of lr 0.01 lifts by 0.1 cm


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


def forward_kinematics(problem: TTOProblem, xi: torch.Tensor) -> torch.Tensor:
    """Absolute poses (S, N, 4) cm / rad from ξ (S, N, 4); one gather per tree depth."""
    x, y, yaw = xi[..., 0] * CM, xi[..., 1] * CM, xi[..., 2]
    zloc = problem.zloc + xi[..., 3] * LIFT_CM  # lift is 0 except for sliding in children
    pose = torch.stack((x, y, zloc, yaw), dim=-1)  # correct for roots
    index = problem.parent.unsqueeze(-1).expand(-1, -1, 4)
    for at_depth in problem.depth_masks:
        par = torch.gather(pose, 1, index)
        c, s = torch.cos(par[..., 3]), torch.sin(par[..., 3])
        child = torch.stack((par[..., 0] + c * x - s * y, par[..., 1] + s * x + c * y,
                             par[..., 2] + zloc, par[..., 3] + yaw), dim=-1)
        pose = torch.where(at_depth.unsqueeze(-1), child, pose)
    return pose


# --------------------------------------------------------------------------------------------
# Host side: from hierarchical scenes to padded arrays, one step per concern
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


class _HostArrays:
    """The padded host (numpy) arrays of a problem while its scenes are encoded one by one."""

    def __init__(self, n_scene: int, n_slot: int, n_restricted: int, n_near: int) -> None:
        self.kind = np.zeros((n_scene, n_slot), np.int64)
        self.parent = np.tile(np.arange(n_slot), (n_scene, 1))
        self.depth = np.zeros((n_scene, n_slot), np.int64)
        self.xi0 = np.zeros((n_scene, n_slot, 4))
        self.lift_max = np.zeros((n_scene, n_slot))
        self.zloc = np.zeros((n_scene, n_slot))
        self.parent_half = np.zeros((n_scene, n_slot, 2))
        self.zone = np.zeros((n_scene, 4))
        self.restricted = np.zeros((n_scene, n_restricted, 4))
        self.restricted_mask = np.zeros((n_scene, n_restricted), bool)
        self.near = np.zeros((n_scene, n_near, 2), np.int64)
        self.near_axis = np.zeros((n_scene, n_near), np.int64)
        self.near_sign = np.ones((n_scene, n_near))
        self.near_margin = np.zeros((n_scene, n_near))
        self.near_mask = np.zeros((n_scene, n_near), bool)
        self.body = np.tile(np.arange(n_slot), (n_scene, 1))
        self.held = np.zeros((n_scene, n_slot), bool)
        self.reattached: list[list[tuple[str, str]]] = []


def _encode_hierarchy(host: _HostArrays, s: int, scene: Scene, hold: set[str],
                      config: TTOConfig) -> list[SceneObject]:
    """Kinds, parents, depths, ξ0, held z and lift room of scene ``s``; returns its objects as
    optimised (after :func:`reattach`)."""
    n = len(scene)
    host.held[s, :n] = [oid in hold for oid in scene.ids()]
    attached, notes = reattach(scene, config) if not hold else (scene, [])
    host.reattached.append(notes)
    objs = attached.objects
    k, p = _kinds(attached)
    host.kind[s, :n], host.parent[s, :n], host.depth[s, :n] = k, p, _depths(p)
    held = host.held[s]
    for i in np.argsort(host.depth[s, :n], kind="stable"):  # parents before children
        o = objs[i]
        if k[i] == ROOT:
            host.xi0[s, i] = (o.center[0] / CM, o.center[1] / CM, o.yaw, 0.0)
            host.zloc[s, i] = o.center[2] if held[i] else 0.5 * o.size[2]  # held: exactly as input
            continue
        par = objs[p[i]]
        u, v, psi = _relative(o, par)
        host.xi0[s, i] = (u / CM, v / CM, psi, 0.0)
        if k[i] == IN and config.in_children == "slide" and not held[i]:
            # rise out of a floor it was sunk into, keeping > half its height inside
            room = par.zmax - o.zmin - 0.55 * o.size[2]
            host.lift_max[s, i] = max(0.0, min(config.in_lift_cm, room)) / LIFT_CM
        host.parent_half[s, i] = (0.5 * par.size[0], 0.5 * par.size[1])
        host.zloc[s, i] = (0.5 * (par.size[2] + o.size[2]) + config.contact_gap_cm
                           if k[i] == ON and not held[i] else o.center[2] - par.center[2])
        host.body[s, i] = host.body[s, p[i]] if k[i] == IN else i
    return objs


def _encode_zones(host: _HostArrays, s: int, scene: Scene) -> None:
    """The placement zone and the restricted zones of scene ``s``."""
    host.zone[s] = scene.zone.to_list()
    for r, rz in enumerate(scene.restricted_zones):
        host.restricted[s, r], host.restricted_mask[s, r] = rz.to_list(), True


def _encode_near(host: _HostArrays, s: int, scene: Scene, objs: list[SceneObject],
                 config: TTOConfig) -> None:
    """The near relations of scene ``s``: (object, reference) slots, axis, sign and margin."""
    index = {o.instance_id: i for i, o in enumerate(objs)}
    refs = [(a, r) for a, r in near_references(scene).items() if r is not None]
    for q, (a, (ref, direction)) in enumerate(refs):
        ia, ib = index[a], index[ref]
        axis, sign = DIRECTION_AXES[direction]
        off = np.subtract(objs[ia].center[:2], objs[ib].center[:2])
        slack = sign * off[axis] - abs(off[1 - axis])
        host.near[s, q], host.near_axis[s, q], host.near_sign[s, q] = (ia, ib), axis, sign
        host.near_margin[s, q] = min(config.near_margin_cm, max(slack, 0.0))
        host.near_mask[s, q] = True


def _to_device(host: _HostArrays, batch, engine, config: TTOConfig) -> TTOProblem:
    """The host arrays as a :class:`TTOProblem` on ``config.device`` (contact pairs still empty)."""
    n_scene, n_slot = batch.mask.shape
    mask = batch.mask.detach().cpu().numpy().astype(bool)
    dev = torch.device(config.device)
    f32 = dict(dtype=torch.float32, device=dev)
    i64 = dict(dtype=torch.long, device=dev)
    depth = host.depth
    max_depth = int(depth.max()) if depth.size else 0
    kind_t = torch.as_tensor(host.kind, **i64)
    slide = config.in_children == "slide"
    # frozen: a container and its in children are one rigid body; slide: every object its own
    group = np.tile(np.arange(n_slot), (n_scene, 1)) if slide else host.body
    bounded = (kind_t == ON) | ((kind_t == IN) & slide)
    return TTOProblem(
        batch=batch,
        mask=torch.as_tensor(mask, device=dev),
        kind=kind_t,
        parent=torch.as_tensor(host.parent, **i64),
        depth_masks=[torch.as_tensor(depth == d, device=dev) for d in range(1, max_depth + 1)],
        xi0=torch.as_tensor(host.xi0, **f32),
        trainable=torch.as_tensor(mask & ~host.held, device=dev) & ((kind_t != IN) | slide),
        bounded=bounded,
        lift_max=torch.as_tensor(host.lift_max, **f32),
        zloc=torch.as_tensor(host.zloc, **f32),
        sizes=batch.sizes.to(**f32),
        raw_poses=batch.poses.to(**f32),
        parent_half=torch.as_tensor(host.parent_half, **f32),
        zone=torch.as_tensor(host.zone, **f32),
        restricted=torch.as_tensor(host.restricted, **f32),
        restricted_mask=torch.as_tensor(host.restricted_mask, device=dev),
        near=torch.as_tensor(host.near, **i64),
        near_axis=torch.as_tensor(host.near_axis, **i64),
        near_sign=torch.as_tensor(host.near_sign, **f32),
        near_margin=torch.as_tensor(host.near_margin, **f32),
        near_mask=torch.as_tensor(host.near_mask, device=dev),
        frozen_energy=_frozen_energy(engine, batch, group).to(**f32),
        contact=torch.zeros(n_scene, 1, 2, **i64),
        contact_mask=torch.zeros(n_scene, 1, dtype=torch.bool, device=dev),
        group=group,
        body=host.body,
        reattached=host.reattached,
    )


def build_problem(scenes: Sequence[Scene], engine, config: TTOConfig,
                  freeze: Sequence[set[str]] | None = None) -> TTOProblem:
    """Pack hierarchical, non-empty ``scenes`` (every object has a parent) for
    :func:`physcene.tto.optimise`.

    ``freeze``: per scene, ids whose ξ is held at its start (their subtrees still follow them).
    Steps: pack the engine batch, encode each scene (hierarchy and ξ0, zones, near relations),
    move the arrays to the device, seat sunk contents, find the contact pairs.
    """
    batch = engine.pack(list(scenes))
    n_scene, n_slot = batch.mask.shape
    for s, scene in enumerate(scenes):
        if list(batch.ids[s][: len(scene)]) != scene.ids():
            raise RuntimeError("engine.pack changed the object order; TTO relies on scene order")
    n_restricted = max([len(sc.restricted_zones) for sc in scenes] + [1])
    n_near = max([len(sc) for sc in scenes] + [1])
    host = _HostArrays(n_scene, n_slot, n_restricted, n_near)
    for s, scene in enumerate(scenes):
        objs = _encode_hierarchy(host, s, scene, freeze[s] if freeze else set(), config)
        _encode_zones(host, s, scene)
        _encode_near(host, s, scene, objs, config)
    problem = _to_device(host, batch, engine, config)
    _seat_contents(engine, problem)
    if config.separate_deep:
        separate_deep_pairs(engine, problem)
    problem.contact, problem.contact_mask = _contact_pairs(engine, problem)
    return problem


_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # rad: successive ranks never line up
_SEPARATION_GAP_CM = 0.1  # clearance left between the footprint boxes of a parted pair


def separate_deep_pairs(engine, problem: TTOProblem, rounds: int = 8) -> None:
    """Move apart, in ``problem.xi0``, penetrating table-level pairs where one object stands deep in
    the other's footprint.

    A pair is deep when the shortest sideways move that parts their footprint boxes is longer than
    half the narrower box along that axis (one's centre inside the other's box: coincident, or sunk
    into it). Each round: evaluate ξ0, and for every deep pair of two free table-level objects
    (different container bodies) move the later-written one (its stack follows) that shortest way
    out, away from the other's centre, or, coincident, along the golden angle of its rank among the
    coincident objects. Rounds repeat until no pair is deep (N coincident objects take up to N − 1).
    """
    slots = problem.batch.pair_slots()
    if len(slots) == 0:
        return
    kind = problem.kind.cpu().numpy()
    free = problem.trainable.cpu().numpy() & (kind == ROOT)
    sizes = problem.sizes.cpu().numpy().astype(np.float64)
    s_, i_, j_ = slots[:, 0], slots[:, 1], slots[:, 2]
    candidate = free[s_, i_] & free[s_, j_] & (problem.body[s_, i_] != problem.body[s_, j_])
    if not candidate.any():
        return
    for _ in range(rounds):
        poses = forward_kinematics(problem, problem.xi0)
        energy = engine.evaluate(problem.batch, poses)["pair_energy"].detach().cpu().numpy()
        pose = poses.detach().cpu().numpy().astype(np.float64)
        shift = np.zeros(pose.shape[:2] + (2,))
        moved = np.zeros(pose.shape[:2], bool)
        rank: dict[tuple[int, int], int] = {}
        for s, i, j in slots[candidate & (energy > 0)]:
            if moved[s, j]:
                continue
            lo_i, hi_i = _footprint_box(pose[s, i], sizes[s, i])
            lo_j, hi_j = _footprint_box(pose[s, j], sizes[s, j])
            push = np.minimum(hi_i - lo_j, hi_j - lo_i)  # per axis: the move that parts the boxes
            axis = int(np.argmin(push))
            if push[axis] <= 0.5 * min(hi_i[axis] - lo_i[axis], hi_j[axis] - lo_j[axis]):
                continue  # shallow: the gradient steps part it
            moved[s, j] = True
            delta = pose[s, j, :2] - pose[s, i, :2]
            if np.abs(delta).max() < 1e-3:  # coincident: no side is nearer, break the tie
                k = rank[(s, i)] = rank.get((s, i), 0) + 1
                u = np.array([math.cos(k * _GOLDEN_ANGLE), math.sin(k * _GOLDEN_ANGLE)])
                # the shortest move along u that clears the boxes on one axis
                need = (0.5 * (hi_i - lo_i + hi_j - lo_j) + _SEPARATION_GAP_CM) / np.maximum(np.abs(u), 1e-9)
                shift[s, j] = u * need.min()
            else:
                shift[s, j, axis] = math.copysign(push[axis] + _SEPARATION_GAP_CM,
                                                  delta[axis] if delta[axis] != 0 else 1.0)
        if not moved.any():
            return
        xi = problem.xi0.clone()
        xi[..., :2] += torch.as_tensor(shift / CM, dtype=xi.dtype, device=xi.device)
        problem.xi0 = xi


def _footprint_box(pose: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box (lo (2,), hi (2,)) cm of an object's yawed footprint."""
    half = footprint_half_extents(size[:2], pose[3])
    return pose[:2] - half, pose[:2] + half


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


def reattach(scene: Scene, config: TTOConfig) -> tuple[Scene, list[tuple[str, str]]]:
    """Put back on its support a table-level object that hovers over or is sunk into one.

    A table-level object whose bottom is off the table (|zmin| > 0.05 cm) but within
    ``reattach_gap_cm`` of the top of an object below it (lower centre, not in its own subtree)
    that covers more than the graph's on-overlap of its footprint is optimised as ``on`` the
    highest such support. Dropping it to the table instead would put it inside the support's
    footprint, where the SDF pushes only vertically (z is held) and the object is stuck.
    """
    if config.reattach_gap_cm <= 0:
        return scene, []
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

    They get the footprint proxy of :func:`physcene.tto.losses.footprint_overlap_depth`. Pairs
    inside one container body (a container and its contents, contents of one container) never do:
    the proxy would push a content out of its container's footprint, which the ``in`` edge forbids.
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
