"""Per-object credit (``pada.object_credit``; not in the paper, off by default).

The sequence reward says a layout collides, not which placement did it. Here the physics reward also
charges each object of a rollout (the later-written object of a penetrating pair its depth, or 1 per
pair with ``object_credit_penetration: pairs``; per ``object_credit_terms`` its floating gap, how far
it leaves the zone, how far its size lies outside its category's band), and every token of the text
placing a charged object (``object_credit_scope``: its plan step and layout line, or only its geometry
numbers) loses ``object_credit`` × the cm charged to it from its advantage: the gradient points at
the objects written into occupied space. TRL's loss takes (B, T) advantages from a subclass. Logged:
``object_credit/charged_token_frac`` and ``object_credit/rows_left_out``.

:func:`credit_reward` binds the charges to the trainer's physics reward and keeps the
:class:`~physcene.reward.RewardBatch` of each of its calls (also read by :mod:`physcene.train.denoise`).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from transformers import PreTrainedTokenizerBase

from physcene.reward import ChargeConfig, PhysicsReward, RewardBatch
from physcene.train.extension import PADAExtension
from physcene.train.targets import object_text_spans

__all__ = ["ChargedReward", "ObjectCredit", "credit_reward", "object_token_depths"]


class ChargedReward:
    """The physics reward as PADA's extensions see it: the reward, the charges it is called with and
    the :class:`~physcene.reward.RewardBatch` of its latest call (this rank's rollouts, in order)."""

    def __init__(self, reward: PhysicsReward, charges: ChargeConfig):
        self.reward, self.charges = reward, charges
        self.batch: RewardBatch | None = None

    def keep(self, batch: RewardBatch) -> None:
        self.batch = batch

    def latest(self) -> RewardBatch:
        if self.batch is None:
            raise RuntimeError("the physics reward has not scored a round yet")
        return self.batch


def credit_reward(reward_funcs: list, args) -> ChargedReward:
    """The :class:`~physcene.reward.PhysicsReward` among ``reward_funcs`` (or their ``reward``), bound
    in place to charge each object per ``args.object_credit_terms`` / ``object_credit_penetration``:
    TRL calls it with its own arguments, the charges and the keeping of the call's batch are added."""
    found = [k for k, f in enumerate(reward_funcs) if isinstance(getattr(f, "reward", f), PhysicsReward)]
    if not found:
        raise ValueError("pada.object_credit and pada.denoise need the physics reward (physcene."
                         "reward.PhysicsReward) among the reward functions: it charges each "
                         "object its penetration")
    k = found[0]
    charged = ChargedReward(getattr(reward_funcs[k], "reward", reward_funcs[k]),
                            ChargeConfig(terms=tuple(args.object_credit_terms),
                                         penetration=args.object_credit_penetration))
    reward_funcs[k] = functools.partial(reward_funcs[k], charges=charged.charges, on_batch=charged.keep)
    return charged


class ObjectCredit(PADAExtension):
    """Lowers the advantage of the tokens placing each charged object (module docstring).

    ``reward``: the charged physics reward that scored the round (:func:`credit_reward`); ``weight``:
    ``pada.object_credit``, advantage per cm; ``scope``: ``pada.object_credit_scope``.
    """

    def __init__(self, reward: ChargedReward, weight: float, scope: str = "line"):
        self.reward, self.weight, self.scope = reward, float(weight), str(scope)

    def after_scoring(self, trainer, inputs: list[dict], output: dict) -> None:
        # the reward's latest call scored this rank's completions in this order
        depths = self.reward.latest().object_charges
        completion_ids = output["completion_ids"]
        if len(depths) != completion_ids.size(0):
            raise ValueError(f"object depths for {len(depths)} completions, "
                             f"{completion_ids.size(0)} generated")
        charged, skipped = object_token_depths(trainer._tokenizer, completion_ids.cpu(),
                                               output["completion_mask"].cpu(), depths, self.scope)
        charged = charged.to(completion_ids.device)
        advantages = output["advantages"]
        if advantages.dim() == 1:
            advantages = advantages.unsqueeze(1)
        output["advantages"] = advantages - self.weight * charged.to(advantages.dtype)
        mask = output["completion_mask"]
        trainer.log_value("object_credit/charged_token_frac",
                          ((charged > 0) & mask.bool()).sum().item() / max(mask.sum().item(), 1))
        trainer.log_value("object_credit/rows_left_out", float(skipped))


def object_token_depths(tokenizer: PreTrainedTokenizerBase, completion_ids: torch.Tensor,
                        completion_mask: torch.Tensor, depths: list,
                        scope: str = "line") -> tuple[torch.Tensor, int]:
    """((B, T) cm charged to each completion token, rows left out).

    ``depths[b]``: the (n_objects,) penetration charged to each object of completion b
    (:attr:`physcene.reward.PhysicsReward.last_object_depths`), None when it did not parse. Every
    token that overlaps the text placing object k (per ``scope``: its plan step and layout line, or
    its geometry numbers; :func:`object_text_spans`) carries ``depths[b][k]`` (a token across two
    objects' text: the larger). A row is left out (all 0) when its tokens decoded one by one do not
    give the completion's text (a multi-byte character split across tokens) or its object lines do
    not match its objects.
    """
    out = torch.zeros(completion_ids.shape, dtype=torch.float32)
    skipped = 0
    lengths = completion_mask.sum(dim=1).tolist()
    for b, (row, charged) in enumerate(zip(completion_ids.tolist(), depths)):
        if charged is None or not np.any(charged):
            continue
        ids = row[:int(lengths[b])]
        pieces = [tokenizer.decode([t]) for t in ids]
        text = "".join(pieces)
        spans = object_text_spans(text, scope)
        if text != tokenizer.decode(ids) or len(spans) != len(charged):
            skipped += 1
            continue
        ends = np.cumsum([len(p) for p in pieces])
        starts = ends - np.array([len(p) for p in pieces])
        for object_spans, d in zip(spans, charged):
            if d <= 0:
                continue
            for a, e in object_spans:
                first = np.searchsorted(ends, a, side="right")  # the first token ending past a
                last = np.searchsorted(starts, e, side="left")  # the first token starting at e or later
                out[b, first:last] = torch.clamp(out[b, first:last], min=float(d))
    return out, skipped
