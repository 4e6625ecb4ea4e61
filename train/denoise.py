"""On-policy denoising targets for PADA (``pada.denoise``; NOT in the paper, off by default).

The paper's anchor CE pulls the policy toward TTO repairs of the SFT model's outputs, made once before
RL. Here every rollout of a round that the reward blamed objects in (``object_credit``'s charges: the
later-written object of a penetrating pair, and per ``object_credit_terms`` a floating object or one
past the zone) gets a target: the blamed objects are moved — everything else held where the rollout
wrote it — and their numbers are rewritten in the rollout's own text. The cross-entropy of those
rewritten numbers given the rollout's own prefix answers "where should this object have gone, given
what was already on the table": the conditioning on earlier objects that likelihood training on whole
layouts barely teaches (docs/results.md, "Why dense scenes stay colliding"), where the per-object
credit only says where it should not have gone.

Blamed table-level objects go, in the order written, to the nearest spot where their footprint, grown
by ``margin_cm`` on every side, misses every other table-level footprint (:func:`free_spot`): exact,
and a clearance that a policy landing a few millimetres off the target does not lose. With TTO alone,
a pushed object stalls between held neighbours: 28 % of the targets were collision-free on the
``small`` SFT model's own outputs, 80 % with the free spot (docs/training.md). The blamed objects
left (``on`` / ``in`` children, table-level ones with no free spot) are repaired by TTO with every
other object held; an object left past the zone (further than the out-of-zone metric's tolerance)
keeps its text. TTO trades the zone term against penetration, so the configs weigh the zone ten times
the default for this repair (``pada.denoise_tto: [lambda_zone=100.0]``: a toaster written into its
neighbour lands 6 cm off the table at the default weight, inside and collision-free at 100).

In PADA (:class:`Denoise`, a :class:`~physcene.train.extension.PADAExtension`) the targets travel with
the rollouts as ``denoise_ids`` / ``denoise_attention_mask`` / ``denoise_loss_mask`` and add
``denoise`` × their NLL over TRL's token count to the loss. Logged: ``denoise/rows_frac``,
``denoise/token_frac``, ``denoise/depth_before_cm``, ``denoise/depth_after_cm``,
``denoise/collision_free_frac``, ``denoise/nll`` and ``time/denoise_s``.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from physcene.ctrc import encode, parse, usual_decimals
from physcene.scene import TABLE, ZONE_TOLERANCE_CM, Scene, SceneError, zone_overshoot
from physcene.train.extension import PADAExtension
from physcene.train.targets import object_line_spans, padded_targets, tokenize_target
from physcene.tto import TTOConfig, repair

__all__ = ["Denoise", "DenoiseTarget", "denoise_targets", "rewrite_boxes"]

_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_VALUE = {key: re.compile(rf'"{key}"\s*:\s*(\[[^\]]*\]|[-+0-9.eE]+)')
          for key in ("relative_bbox", "relative_rotation_deg")}
_MOVED_CM = 1e-3    # a blamed object moved less than this (and turned less than _MOVED_RAD) keeps its text
_MOVED_RAD = 1e-5
_CHUNK = 2048       # free_spot's candidates tested at once


@dataclass
class DenoiseTarget:
    """One rollout's target: its text with the blamed objects' numbers rewritten."""

    text: str
    spans: list[tuple[int, int]]
    """Character spans ``[start, end)`` in ``text`` of the numbers that changed (the supervised ones)."""
    moved: list[str]
    """Ids of the objects whose numbers changed."""
    depth_before: float
    """Summed pair depth (cm, the reward's E_pen / 10) of the rollout's layout ..."""
    depth_after: float
    """... and of the target's (before it is rounded to the text's decimals)."""


def rewrite_boxes(text: str, scene: Scene, ids: set[str], decimals: int) -> tuple[str, list[tuple[int, int]]]:
    """``text`` with the ``relative_bbox`` / ``relative_rotation_deg`` numbers of the objects ``ids``
    written from ``scene`` at ``decimals`` digits, and the spans of the numbers that changed.

    ``scene`` is the completion's parsed scene with new poses (objects in the order written). A number
    within half a unit of the last decimal of its new value is left as written. An object line whose
    values cannot be found is left as written. Returns ``(text, [])`` when nothing changed.
    """
    lines = object_line_spans(text)
    if len(lines) != len(scene.objects):
        raise ValueError(f"{len(lines)} object lines in the text, {len(scene.objects)} objects in the scene")
    entries = {e["instance_id"]: e for e in encode(scene, decimals=decimals)}
    unit = 0.5 * 10.0 ** -decimals
    pieces, spans, pos, length = [], [], 0, 0
    for (a, b), obj in zip(lines, scene.objects):
        if obj.instance_id not in ids:
            continue
        entry = entries[obj.instance_id]
        for key, values in (("relative_bbox", entry["relative_bbox"]),
                            ("relative_rotation_deg", [entry["relative_rotation_deg"]])):
            m = _VALUE[key].search(text, a, b)
            numbers = list(_NUMBER.finditer(text, m.start(1), m.end(1))) if m is not None else []
            if len(numbers) != len(values):
                continue
            for n, value in zip(numbers, values):
                if abs(float(n.group(0)) - value) < unit:
                    continue
                new = json.dumps(value)
                pieces.append(text[pos:n.start()])
                length += n.start() - pos
                spans.append((length, length + len(new)))
                pieces.append(new)
                length += len(new)
                pos = n.end()
    pieces.append(text[pos:])
    return "".join(pieces), spans


def _axes(yaw: np.ndarray) -> np.ndarray:
    """(..., 2, 2) unit axes (rows: the box's local x and y) of boxes yawed by ``yaw`` rad."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def free_spot(center: np.ndarray, half: np.ndarray, yaw: float, obstacles: np.ndarray, zone: np.ndarray, *,
              step_cm: float = 0.5, reach_cm: float = 60.0) -> np.ndarray | None:
    """The (x, y) nearest ``center`` where a box of half extents ``half`` (w/2, d/2) at ``yaw`` overlaps
    none of the ``obstacles`` (M, 5: x, y, w/2, d/2, yaw) and lies inside ``zone`` (xmin, xmax, ymin,
    ymax); None when no point of the grid (``step_cm``, within ``reach_cm``) is free.

    Footprints that do not overlap cannot penetrate (every shape lies inside its box) when both stand
    on the table: an exact answer for table-level objects, where TTO's gradient can stall between two
    held neighbours. Separating-axis test on the four box axes, all candidates at once.
    """
    n = int(reach_cm / step_cm)
    grid = np.arange(-n, n + 1) * step_cm
    offsets = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    offsets = offsets[np.argsort(np.einsum("kd,kd->k", offsets, offsets), kind="stable")]
    candidates = center[None, :2] + offsets  # nearest first
    own = _axes(np.asarray(yaw))  # (2, 2)
    ext = np.abs(own[0] * half[0]) + np.abs(own[1] * half[1])  # AABB half extents of the footprint
    inside = ((candidates[:, 0] - ext[0] >= zone[0]) & (candidates[:, 0] + ext[0] <= zone[1])
              & (candidates[:, 1] - ext[1] >= zone[2]) & (candidates[:, 1] + ext[1] <= zone[3]))
    candidates = candidates[inside]
    if not len(obstacles):
        return candidates[0] if len(candidates) else None
    other = _axes(obstacles[:, 4])  # (M, 2, 2)
    axes = np.concatenate([np.broadcast_to(own, other.shape), other], 1)  # (M, 4, 2)
    # projection radius of each box on each axis; the candidates differ by translation only
    reach = (np.abs(axes @ own[0]) * half[0] + np.abs(axes @ own[1]) * half[1]
             + np.abs(np.einsum("mad,md->ma", axes, other[:, 0])) * obstacles[:, None, 2]
             + np.abs(np.einsum("mad,md->ma", axes, other[:, 1])) * obstacles[:, None, 3])  # (M, 4)
    for start in range(0, len(candidates), _CHUNK):  # nearest first: most objects are free a few cm away
        chunk = candidates[start:start + _CHUNK]
        gap = np.abs(np.einsum("kmd,mad->kma", obstacles[None, :, :2] - chunk[:, None], axes))
        free = ~(gap < reach).all(-1).any(-1)  # (K,) every obstacle has a separating axis
        if free.any():
            return chunk[int(np.argmax(free))]
    return None


def _place_table_level(scene: Scene, blamed: set[str], margin_cm: float) -> tuple[Scene, set[str]]:
    """``scene`` with each blamed table-level object, in the order written, moved to its
    :func:`free_spot` (its footprint grown by ``margin_cm``, clear of every other table-level footprint
    and of the restricted zones; its subtree follows), and the ids it placed."""
    objects = list(scene.objects)
    zone = np.asarray(scene.zone.to_list())
    restricted = [(0.5 * (z.xmin + z.xmax), 0.5 * (z.ymin + z.ymax), 0.5 * (z.xmax - z.xmin),
                   0.5 * (z.ymax - z.ymin), 0.0) for z in scene.restricted_zones]
    placed = set()
    for oid in [o.instance_id for o in objects if o.instance_id in blamed and o.parent == TABLE]:
        o = next(p for p in objects if p.instance_id == oid)  # as placed so far
        others = [(p.center[0], p.center[1], 0.5 * p.size[0], 0.5 * p.size[1], p.yaw)
                  for p in objects if p.parent == TABLE and p.instance_id != o.instance_id]
        half = 0.5 * np.asarray(o.size[:2]) + margin_cm
        obstacles = np.asarray(others + restricted).reshape(-1, 5)
        spot = free_spot(np.asarray(o.center), half, o.yaw, obstacles, zone)
        if spot is None:
            continue
        shift = np.array([spot[0] - o.center[0], spot[1] - o.center[1], 0.0])
        subtree = _subtree(objects, o.instance_id)
        objects = [p.moved(center=tuple(np.asarray(p.center) + shift)) if p.instance_id in subtree else p
                   for p in objects]
        placed.add(o.instance_id)
    return scene.with_objects(objects), placed


def _subtree(objects, root: str) -> set[str]:
    """``root`` and every object whose parent chain reaches it."""
    out, frontier = {root}, {root}
    while frontier:
        frontier = {o.instance_id for o in objects if o.parent in frontier} - out
        out |= frontier
    return out


def _grown(scene: Scene, ids: set[str], margin_cm: float) -> Scene:
    """``scene`` with the table-level objects among ``ids`` grown by ``margin_cm`` on every side (x, y)."""
    if margin_cm <= 0:
        return scene
    return scene.with_objects(
        o.moved(size=(o.size[0] + 2 * margin_cm, o.size[1] + 2 * margin_cm, o.size[2]))
        if o.instance_id in ids and o.parent == TABLE else o for o in scene.objects)


def denoise_targets(texts: Sequence[str], charges: Sequence, *, config=None, engine=None,
                    margin_cm: float = 1.0, decimals: int | None = None) -> list[DenoiseTarget | None]:
    """Per completion text, its :class:`DenoiseTarget` or None (nothing blamed, not parsed, nothing moved).

    ``charges[k]``: the (n_objects,) cm the reward charged each object of ``texts[k]``
    (:attr:`physcene.reward.RewardBatch.placement_charges`), None when it did not parse. Blamed
    table-level objects go to their :func:`free_spot` (in the order written); the blamed objects left
    (``on`` / ``in`` children, table-level ones with no free spot) are repaired in one batched
    :func:`physcene.tto.repair` (``config``: a :class:`~physcene.tto.TTOConfig` on ``engine``'s device),
    every other object held. The rewritten numbers are written at ``decimals`` digits (the training
    data's ``record.decimals``); None: at each text's :func:`~physcene.ctrc.usual_decimals`. Never at
    the most any of its numbers has: targets that took a rollout's one stray eight-decimal number
    for its precision taught eight-decimal numbers, and the rollouts wrote more of them.
    """
    if len(texts) != len(charges):
        raise ValueError(f"{len(texts)} completions but {len(charges)} charges")
    if engine is None:
        from physcene.physics import PhysicsEngine

        engine = PhysicsEngine(device=config.device if config is not None else "cpu")
    jobs = []  # (row, parsed scene, blamed ids, scene with the table-level ones placed, the rest)
    for row, (text, charged) in enumerate(zip(texts, charges)):
        if charged is None or not np.any(np.asarray(charged) > 0):
            continue
        scene = parse(text)
        if not isinstance(scene, Scene) or len(scene.objects) != len(charged):
            continue
        blamed = {o.instance_id for o, c in zip(scene.objects, charged) if c > 0}
        placed_scene, placed = _place_table_level(scene, blamed, margin_cm)
        jobs.append((row, scene, blamed, placed_scene, blamed - placed))
    out: list[DenoiseTarget | None] = [None] * len(texts)
    if not jobs:
        return out
    finals = [placed for *_, placed, _ in jobs]
    rest = [k for k, job in enumerate(jobs) if job[4]]
    if rest:
        results = repair([_grown(jobs[k][3], jobs[k][4], margin_cm) for k in rest], config, engine=engine,
                         freeze=[set(jobs[k][3].ids()) - jobs[k][4] for k in rest])
        for k, result in zip(rest, results):
            finals[k] = jobs[k][3].with_poses(result.scene.poses())  # the margin shrunk back
    scores = engine.score([scene for _, scene, *_ in jobs] + finals)
    depth = [float(sum(d for *_, d in pairs)) for pairs in scores.pairs]
    for k, ((row, scene, blamed, *_), final) in enumerate(zip(jobs, finals)):
        before, after = scene.poses(), final.poses()
        shift = np.linalg.norm(after[:, :3] - before[:, :3], axis=1)
        turn = np.abs(after[:, 3] - before[:, 3])
        # a repair that pushed an object out of the table is no answer to where it should go
        zone = np.asarray(scene.zone.to_list())
        past = zone_overshoot(after[:, :2], scene.sizes()[:, :2], after[:, 3], zone)
        moved = {o.instance_id for o, d, t, p in zip(scene.objects, shift, turn, past)
                 if o.instance_id in blamed and (d > _MOVED_CM or t > _MOVED_RAD) and p <= ZONE_TOLERANCE_CM}
        if not moved:
            continue
        try:
            text, spans = rewrite_boxes(texts[row], final, moved,
                                        usual_decimals(texts[row]) if decimals is None else decimals)
        except (ValueError, KeyError, SceneError):  # model output the writer cannot re-encode: no target
            continue
        if spans:
            out[row] = DenoiseTarget(text, spans, sorted(moved), depth[k], depth[len(jobs) + k])
    return out


class Denoise(PADAExtension):
    """On-policy denoising targets and their cross-entropy (module docstring).

    ``reward``: the charged physics reward that scored the round
    (:func:`physcene.train.object_credit.credit_reward`); ``weight``: ``pada.denoise``; ``tto``: the
    repair's configuration (:meth:`tto_config` of ``pada.denoise_tto``); ``margin_cm`` /
    ``decimals``: ``pada.denoise_margin_cm`` / ``denoise_decimals``.
    """

    def __init__(self, reward, weight: float, tto: TTOConfig | None, margin_cm: float = 1.0,
                 decimals: int | None = None):
        self.reward, self.weight, self.tto = reward, float(weight), tto
        self.margin_cm, self.decimals = float(margin_cm), decimals

    @staticmethod
    def tto_config(overrides, reward) -> TTOConfig:
        """``configs/tto.yaml`` with ``overrides`` (key=value), on the device of ``reward``'s engine
        (``reward``: a :class:`~physcene.reward.PhysicsReward` or a charged one)."""
        engine = getattr(reward, "reward", reward).engine
        return replace(TTOConfig.load(list(overrides)), device=str(engine.device))

    def after_scoring(self, trainer, inputs: list[dict], output: dict) -> None:
        """Each rollout the reward blamed objects in, with those objects moved (free spot or TTO), as
        ``denoise_ids`` / ``denoise_attention_mask`` / ``denoise_loss_mask`` (right padded, like the
        anchor's), supervised on the numbers the repair rewrote. Rows without a target are all 0."""
        start = time.perf_counter()
        tokenizer = trainer._tokenizer
        completion_ids, completion_mask = output["completion_ids"], output["completion_mask"]
        lengths = completion_mask.sum(dim=1).tolist()
        texts = [tokenizer.decode(row[:int(n)], skip_special_tokens=True)
                 for row, n in zip(completion_ids.tolist(), lengths)]
        charges = self.reward.latest().placement_charges  # a target moves objects, it does not resize
        if len(charges) != len(texts):
            raise ValueError(f"object charges for {len(charges)} completions, {len(texts)} generated")
        targets = denoise_targets(texts, charges, config=self.tto, engine=self.reward.reward.engine,
                                  margin_cm=self.margin_cm, decimals=self.decimals)
        rows = [tokenize_target(tokenizer, t.text, t.spans, max_length=trainer.max_completion_length)
                if t is not None else ([], []) for t in targets]
        output.update(padded_targets("denoise", rows, tokenizer.pad_token_id, completion_ids.device))
        found = [t for t in targets if t is not None]
        trainer.log_value("denoise/rows_frac", len(found) / max(len(targets), 1))
        trainer.log_value("denoise/token_frac", sum(sum(m) for _, m in rows) / max(sum(lengths), 1))
        if found:
            trainer.log_value("denoise/depth_before_cm", float(np.mean([t.depth_before for t in found])))
            trainer.log_value("denoise/depth_after_cm", float(np.mean([t.depth_after for t in found])))
            free = float(np.mean([t.depth_after == 0 for t in found]))
            trainer.log_value("denoise/collision_free_frac", free)
        trainer.log_value("time/denoise_s", time.perf_counter() - start)

    def extra_loss(self, trainer, model, inputs: dict):
        if "denoise_ids" not in inputs or inputs["denoise_loss_mask"].sum() == 0:
            return None
        return self.weight * self.loss(trainer, model, inputs)

    def loss(self, trainer, model, inputs: dict) -> torch.Tensor:
        """The targets' summed NLL over TRL's dapo normaliser (the completion tokens of one
        accumulation window on this rank): a rewritten token pulls like a sampled token of advantage 1."""
        nll, count = trainer.target_nll(model, inputs, "denoise")
        normalizer = inputs["num_items_in_batch"].clamp(min=1.0) / trainer.accelerator.num_processes
        if trainer.model.training:
            normalizer = normalizer * trainer.current_gradient_accumulation_steps
            normalizer = normalizer / trainer.args.steps_per_generation
        trainer.log_value("denoise/nll", (nll.detach() / count.clamp(min=1.0)).item())
        return nll / normalizer
