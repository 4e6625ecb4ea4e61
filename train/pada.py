"""Stage 2: PADA — GRPO with a cross-entropy pull toward physically-projected semantic anchors.

The paper's objective (Sec. 3.3, appendix "Stage 2")::

    J(θ) = E[ 1/K Σ_k A_k π_θ(S_k)/π_old(S_k) ]  +  α · L_CE(π_θ, S*_anchor)        (α = 0.1)

is TRL's GRPO loss plus one term. Following TRL's extension pattern (``trl/experimental/gmpo``), the
subclass :class:`PADATrainer` overrides only

- ``_generate_and_score_completions``: after TRL has generated and scored the group, tokenise each
  prompt's anchor (the ``anchor`` column written by :mod:`physcene.train.anchors`) into
  ``anchor_ids``/``anchor_attention_mask``/``anchor_loss_mask`` so TRL shuffles and splits them with
  the rest of the batch;
- ``_compute_loss``: ``loss = GRPO loss + α · CE(anchor)``, with the same gradient-accumulation scaling
  TRL applies to its own loss, and the CE logged as ``anchor_ce``.

Under CTRC-constrained sampling (``pada.constrained``) the tokens the constraint chose instead of the
policy's draw join TRL's ``tool_mask`` (``pada.mask_overruled``): they are the grammar's, not the
policy's, and left in the loss they drift without bound (docs/training.md, "Tokens the constraint chose").

Variants (``pada.variant``): ``pada`` (TTO-repaired anchors), ``pada_star`` (raw SFT output as the
anchor, CE masked to non-numeric tokens: the box and rotation values are left to GRPO, as the
paper's PADA*), ``grpo`` (α = 0: plain GRPO, no anchor forward pass). Rows whose anchor is empty (the
SFT output did not parse) contribute no CE.

β (KL to the SFT model) starts at 0.04 and is adapted by :class:`AdaptiveKLCallback`.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from physcene.train.sft import nonfinite_gradients
from transformers import PreTrainedTokenizerBase, TrainerCallback
from trl import GRPOConfig, GRPOTrainer

from physcene.ctrc import MAX_DECIMALS
from physcene.ctrc.spans import (
    GEOMETRY_KEYS,
    numeric_spans,
    object_line_spans,  # noqa: F401  (train/denoise.py imports it from here)
    object_text_spans,
)

__all__ = [
    "VARIANTS",
    "NoAnchorsError",
    "AdaptiveKLCallback",
    "PADAConfig",
    "PADATrainer",
    "PhysicsRewardFunction",
    "numeric_spans",
    "pada_arguments",
    "padded_targets",
    "run_pada",
    "tokenize_anchor",
    "tokenize_target",
]

logger = logging.getLogger(__name__)

# variant -> (anchor column, numeric tokens masked out of the CE); grpo has no anchor (α = 0)
VARIANTS = {"pada": ("anchor", False), "pada_star": ("anchor_raw", True), "grpo": (None, False)}



class NoAnchorsError(ValueError):
    """An anchor file in which no SFT output parsed: PADA and PADA* have nothing to pull toward."""


@dataclass
class PADAConfig(GRPOConfig):
    """``GRPOConfig`` plus the anchor term. Defaults are the paper's (α = 0.1, β = 0.04, G = 4)."""

    anchor_alpha: float = field(default=0.1, metadata={"help": "Weight α of the anchor CE; 0 = GRPO."})
    anchor_column: str = field(default="anchor", metadata={"help": "Dataset column holding the anchor text."})
    anchor_numeric_mask: bool = field(
        default=False, metadata={"help": "PADA*: leave geometry numbers out of the anchor CE."})
    anchor_geometry_keys: list[str] = field(
        default_factory=lambda: list(GEOMETRY_KEYS),
        metadata={"help": "JSON keys whose numeric values the PADA* mask removes from the CE."})
    beta: float = field(default=0.04, metadata={"help": "Initial KL coefficient (AdaptiveKLCallback)."})
    num_generations: int | None = field(default=4, metadata={"help": "Group size G."})
    generation_compile: bool = field(
        default=False, metadata={"help": "Compile the decoding forward of a static-cache generation "
                                         "(pada.cache=static_compile); TRL itself always disables it."})
    constrained_decoding: bool = field(
        default=False, metadata={"help": "Sample the groups under the CTRC constraint "
                                         "(physcene.train.constrained; HF generate only, not vLLM)."})
    mask_overruled: bool = field(
        default=True, metadata={"help": "Leave the tokens the CTRC constraint chose instead of the "
                                        "policy's draw out of the GRPO loss and KL (like tool output)."})
    nonfinite_probe: int = field(
        default=0, metadata={"help": "Micro-batches whose backward leaves a non-finite gradient to take "
                                     "apart (PADATrainer.probe_nonfinite): which loss term, which rows, "
                                     "which attention kernel; 0 = off."})
    object_credit: float = field(
        default=0.0, metadata={"help": "Not in the paper (0 = off): lower the advantage of the tokens of "
                                       "each object's plan step and layout line by this much per cm of "
                                       "penetration charged to it (object_token_depths); per-token "
                                       "advantages."})
    object_credit_terms: list[str] = field(
        default_factory=lambda: ["penetration"],
        metadata={"help": "What object_credit charges each object with (cm), of "
                          "physcene.reward.OBJECT_TERMS: penetration (the paper's reward term), "
                          "floating (its support gap), out_of_zone (how far its footprint leaves the zone), "
                          "size (how far its size lies outside its category's band; reward.size_tolerance)."})
    object_credit_penetration: str = field(
        default="depth", metadata={"help": "How a penetrating pair charges its later-written object: depth "
                                           "(its depth, cm) or pairs (1 per pair: does not fall when the "
                                           "objects are written thinner)."})
    object_credit_scope: str = field(
        default="line", metadata={"help": "Which tokens of a charged object object_credit lowers: line (its "
                                          "plan step and layout line) or numbers (only the numbers of its "
                                          "relative_bbox and relative_rotation_deg)."})
    denoise: float = field(
        default=0.0, metadata={"help": "Not in the paper (0 = off): weight of the cross-entropy toward each "
                                       "rollout's on-policy repair (physcene.train.denoise: the objects the "
                                       "reward blamed moved to a free spot or by TTO, the rest held, their "
                                       "numbers rewritten in the rollout's text); a rewritten token weighs "
                                       "like a GRPO token of advantage `denoise`."})
    denoise_margin_cm: float = field(
        default=1.0, metadata={"help": "Clearance (cm) the denoising repair keeps around a blamed "
                                       "table-level object."})
    denoise_decimals: int | None = field(
        default=None, metadata={"help": "Digits after the point of the denoising targets' rewritten numbers "
                                        "(the training data's record.decimals); None: each rollout's usual "
                                        "precision (physcene.ctrc.usual_decimals)."})
    denoise_tto: list[str] = field(
        default_factory=lambda: ["lambda_zone=100.0"],
        metadata={"help": "configs/tto.yaml overrides for the denoising repair (key=value; the zone "
                          "weighed 10x, train/denoise.py); its device is the reward engine's."})


def tokenize_anchor(tokenizer: PreTrainedTokenizerBase, text: str, *, max_length: int,
                    numeric_mask: bool = False, keys=GEOMETRY_KEYS) -> tuple[list[int], list[int]]:
    """(token ids, loss mask) of an anchor completion, EOS appended, at most ``max_length`` tokens.

    The EOS is supervised like the generated completions' EOS (the model must learn to stop). With
    ``numeric_mask`` every token overlapping a geometry number gets loss mask 0. Empty text -> ``([], [])``.
    """
    if not text:
        return [], []
    enc = tokenizer(text, add_special_tokens=False, return_offsets_mapping=numeric_mask)
    ids = list(enc["input_ids"]) + [tokenizer.eos_token_id]
    mask = [1] * len(ids)
    if numeric_mask:
        for t in _tokens_over(enc["offset_mapping"], numeric_spans(text, keys)):
            mask[t] = 0
    return ids[:max_length], mask[:max_length]


def tokenize_target(tokenizer: PreTrainedTokenizerBase, text: str, spans: list[tuple[int, int]], *,
                    max_length: int) -> tuple[list[int], list[int]]:
    """(token ids, loss mask) of a completion, EOS appended, supervised only where a token overlaps one
    of the character ``spans`` (:mod:`physcene.train.denoise`'s rewritten numbers); at most
    ``max_length`` tokens. Empty text -> ``([], [])``."""
    if not text:
        return [], []
    enc = tokenizer(text, add_special_tokens=False, return_offsets_mapping=True)
    ids = list(enc["input_ids"]) + [tokenizer.eos_token_id]
    mask = [0] * len(ids)
    for t in _tokens_over(enc["offset_mapping"], spans):
        mask[t] = 1
    return ids[:max_length], mask[:max_length]


def padded_targets(name: str, rows: list[tuple[list[int], list[int]]], pad: int, device) -> dict:
    """``<name>_ids`` / ``<name>_attention_mask`` / ``<name>_loss_mask`` (B, T) of per-row (ids, loss
    mask), right padded like TRL's completion_ids so that [prompt | target] reads as prompt +
    completion; an empty row is all padding."""
    width = max(1, max((len(ids) for ids, _ in rows), default=0))
    return {
        f"{name}_ids": torch.tensor([ids + [pad] * (width - len(ids)) for ids, _ in rows], device=device),
        f"{name}_attention_mask": torch.tensor([[1] * len(ids) + [0] * (width - len(ids)) for ids, _ in rows],
                                               device=device),
        f"{name}_loss_mask": torch.tensor([m + [0] * (width - len(m)) for _, m in rows], device=device),
    }


def _tokens_over(offsets, spans: list[tuple[int, int]]) -> list[int]:
    """Indices of the tokens (character ``offsets``) that overlap any of the sorted ``spans``."""
    if not spans:
        return []
    starts = np.array([s for s, _ in spans])
    ends = np.maximum.accumulate(np.array([e for _, e in spans]))
    out = []
    for t, (a, b) in enumerate(offsets):
        k = int(np.searchsorted(starts, b, side="left")) - 1  # the last span starting before b
        if k >= 0 and ends[k] > a:
            out.append(t)
    return out


OBJECT_CREDIT_SCOPES = ("line", "numbers")


def object_credit_scope_checked(scope: str) -> str:
    """``scope`` if it is one of :data:`OBJECT_CREDIT_SCOPES`, else a ValueError naming them."""
    if scope not in OBJECT_CREDIT_SCOPES:
        raise ValueError(f"object credit scope must be one of {list(OBJECT_CREDIT_SCOPES)}, got {scope!r}")
    return scope


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


def longest_prompt_tokens(tokenizer: PreTrainedTokenizerBase, prompts) -> int:
    """Tokens of the longest prompt as TRL feeds it (a conversational prompt through the chat template)."""
    texts = [p if isinstance(p, str) else
             tokenizer.apply_chat_template(p, tokenize=False, add_generation_prompt=True) for p in prompts]
    return max((len(ids) for ids in tokenizer(texts, add_special_tokens=False)["input_ids"]), default=0)


class PADATrainer(GRPOTrainer):
    """GRPO + α·CE(anchor) (see the module docstring). ``args`` is a :class:`PADAConfig`."""

    _tag_names = ["trl", "grpo", "pada"]

    def __init__(self, model, reward_funcs, args: PADAConfig | None = None, **kwargs):
        if args is None:
            args = PADAConfig("pada")
        super().__init__(model, reward_funcs, args=args, **kwargs)
        self.anchor_alpha = float(args.anchor_alpha)
        self._probes_left = int(args.nonfinite_probe)
        if self._probes_left and self.is_deepspeed_enabled:  # its gradients are not in p.grad
            logger.warning("pada.nonfinite_probe needs gradients in p.grad: off under DeepSpeed")
            self._probes_left = 0
        self._probed_step = -1
        self._micro_batch_inputs = None
        self.object_credit = float(args.object_credit)
        self.object_credit_scope = str(args.object_credit_scope)
        self.denoise = float(args.denoise)
        self._credit_reward = None
        if self.object_credit or self.denoise:
            from physcene.reward import PhysicsReward, object_terms_checked, penetration_charge_checked

            rewards = (getattr(f, "reward", f) for f in self.reward_funcs)
            found = [r for r in rewards if isinstance(r, PhysicsReward)]
            if not found:
                raise ValueError("pada.object_credit and pada.denoise need the physics reward (physcene."
                                 "reward.PhysicsReward) among the reward functions: it charges each "
                                 "object its penetration")
            self._credit_reward = found[0]
            self._credit_reward.object_depths = True
            self._credit_reward.object_terms = object_terms_checked(args.object_credit_terms)
            charge = penetration_charge_checked(args.object_credit_penetration)
            self._credit_reward.penetration_charge = charge
        self._denoise_tto = None
        if self.denoise:
            from dataclasses import replace

            from physcene.tto import TTOConfig

            self._denoise_tto = replace(TTOConfig.from_config(list(args.denoise_tto)),
                                        device=str(self._credit_reward.engine.device))
        if args.cache_implementation == "static" and getattr(self, "generation_config", None) is not None:
            # One static cache size for the whole run (longest prompt + completion): HF sizes it per
            # call otherwise, and each longer batch would recompile the compiled decoding forward.
            longest = longest_prompt_tokens(self._tokenizer, self.train_dataset["prompt"])
            self.generation_config.max_cache_len = longest + self.max_completion_length
        if args.generation_compile and getattr(self, "generation_config", None) is not None:
            # TRL builds its GenerationConfig with disable_compile=True; pada.cache=static_compile turns
            # HF's compiled static-cache decoding back on (same CompileConfig as physcene.train.generate).
            from physcene.train.generate import cache_generate_kwargs

            compiled = cache_generate_kwargs("static_compile", self.accelerator.device)
            self.generation_config.disable_compile = False
            self.generation_config.compile_config = compiled["compile_config"]

    def _generate(self, prompts: list):
        # The prompts of this generation round, in row order, for the CTRC constraint (below).
        self._round_prompts = prompts
        start = time.perf_counter()
        output = super()._generate(prompts)
        # this rank's generation round, with the constraint's host time (also logged apart as
        # time/constraint_s): where a step's time goes, next to time/reward_s and step_time
        self._log_value("time/generate_s", time.perf_counter() - start)
        return output

    def _log_value(self, name: str, value: float) -> None:
        self._metrics["train" if self.model.training else "eval"][name].append(value)

    def _generate_single_turn(self, prompt_ids, images, multimodal_fields, num_generations,
                              has_tool_images=False):
        """TRL's HF-generate path, with :class:`~physcene.train.constrained.CTRCConstraint` passed to
        ``generate`` when ``constrained_decoding`` is on (TRL passes no logits processors itself).

        The completions are sampled from the policy restricted to valid CTRC continuations; their
        log-probabilities are then taken under the unrestricted policy as usual (TRL's vLLM guided
        decoding, ``structured_outputs_regex``, does the same). The positions where the constraint
        overruled the policy's draw (~1 % of tokens for ``small``) are kept per row for
        ``pada.mask_overruled`` (:meth:`_mask_overruled`): left in the loss, a negative advantage
        pushes such a token down at no cost to what is sampled (it is forced anyway), and its KL
        term to the reference grows without bound.
        """
        prompts = getattr(self, "_round_prompts", None)
        usable = prompts is not None and len(prompts) == len(prompt_ids) and not self.use_vllm
        if not (self.args.constrained_decoding and usable):
            return super()._generate_single_turn(prompt_ids, images, multimodal_fields, num_generations,
                                                 has_tool_images)
        from physcene.train.constrained import CTRCConstraint, sampling_warpers
        from transformers import LogitsProcessorList

        texts = [p if isinstance(p, str) else str(p[-1]["content"]) for p in prompts]  # chat: the user turn
        model = self.accelerator.unwrap_model(self.model_wrapped)
        plain_generate = model.generate

        def generate(*args, **kwargs):
            config = self.generation_config
            # sampling: each row's token drawn by rejection from the same warped distribution TRL samples
            processor = CTRCConstraint(self._tokenizer, texts, greedy=not config.do_sample,
                                       warpers=sampling_warpers(config))
            kwargs["logits_processor"] = LogitsProcessorList([processor])
            output = plain_generate(*args, **kwargs)
            self._round_overruled = processor.stats.overruled  # row order = this round's prompts
            self._log_value("time/constraint_s", processor.stats.seconds)
            self._log_value("time/constraint_wait_s", processor.stats.wait_seconds)  # GPU: forward's share
            # where that time goes: draws refused, and rows that fell back to scanning the vocabulary
            self._log_value("time/constraint_scan_s", processor.stats.scan_seconds)
            self._log_value("constraint/refused_draws", float(processor.stats.refused_draws))
            self._log_value("constraint/vocabulary_scans", float(processor.stats.vocabulary_scans))
            return output

        model.generate = generate  # an instance attribute shadows the method for this round only
        try:
            return super()._generate_single_turn(prompt_ids, images, multimodal_fields, num_generations,
                                                 has_tool_images)
        finally:
            del model.generate

    def _set_signature_columns_if_needed(self):
        super()._set_signature_columns_if_needed()
        # Keep the anchor column through Trainer's column pruning.
        if self.args.anchor_column not in self._signature_columns:
            self._signature_columns.append(self.args.anchor_column)

    def _generate_and_score_completions(self, inputs):
        self._round_overruled = None
        output = super()._generate_and_score_completions(inputs)
        if self.args.mask_overruled and self._round_overruled is not None:
            self._mask_overruled(output, self._round_overruled)
        if self.object_credit:
            self._credit_objects(output)
        if self.denoise:
            self._denoise_rollouts(output)
        if self.anchor_alpha == 0.0:
            return output
        device = self.accelerator.device
        rows = [tokenize_anchor(self._tokenizer, x.get(self.args.anchor_column) or "",
                                max_length=self.max_completion_length,
                                numeric_mask=self.args.anchor_numeric_mask,
                                keys=tuple(self.args.anchor_geometry_keys)) for x in inputs]
        output.update(padded_targets("anchor", rows, self._tokenizer.pad_token_id, device))
        return output

    def _credit_objects(self, output: dict) -> None:
        """Per-token advantages (``pada.object_credit``, not in the paper): each token of an object's
        plan step and layout line (``pada.object_credit_scope: line``; ``numbers``: only its geometry
        numbers) loses ``object_credit`` × the cm charged to it (its penetration,
        and per ``pada.object_credit_terms`` its floating gap and how far it leaves the zone).

        The sequence reward says a layout collides, not which placement did it; this points the
        gradient at the objects written into occupied space. TRL's loss takes (B, T) advantages
        from a subclass. The reward's last call scored this rank's completions in this order.
        """
        depths = self._credit_reward.last_object_depths
        completion_ids = output["completion_ids"]
        if len(depths) != completion_ids.size(0):
            raise ValueError(f"object depths for {len(depths)} completions, "
                             f"{completion_ids.size(0)} generated")
        charged, skipped = object_token_depths(self._tokenizer, completion_ids.cpu(),
                                               output["completion_mask"].cpu(), depths,
                                               self.object_credit_scope)
        charged = charged.to(completion_ids.device)
        advantages = output["advantages"]
        if advantages.dim() == 1:
            advantages = advantages.unsqueeze(1)
        output["advantages"] = advantages - self.object_credit * charged.to(advantages.dtype)
        mask = output["completion_mask"]
        self._log_value("object_credit/charged_token_frac",
                        ((charged > 0) & mask.bool()).sum().item() / max(mask.sum().item(), 1))
        self._log_value("object_credit/rows_left_out", float(skipped))

    def _denoise_rollouts(self, output: dict) -> None:
        """On-policy denoising targets (``pada.denoise``, not in the paper; :mod:`physcene.train.denoise`):
        each rollout the reward blamed objects in, with those objects moved (free spot or TTO), as
        ``denoise_ids`` / ``denoise_attention_mask`` / ``denoise_loss_mask`` (right padded, like the
        anchor's), supervised on the numbers the repair rewrote. Rows without a target are all 0.
        """
        from physcene.train.denoise import denoise_targets

        start = time.perf_counter()
        completion_ids, completion_mask = output["completion_ids"], output["completion_mask"]
        lengths = completion_mask.sum(dim=1).tolist()
        texts = [self._tokenizer.decode(row[:int(n)], skip_special_tokens=True)
                 for row, n in zip(completion_ids.tolist(), lengths)]
        charges = self._credit_reward.last_placement_depths  # a target moves objects, it does not resize
        if len(charges) != len(texts):
            raise ValueError(f"object charges for {len(charges)} completions, {len(texts)} generated")
        targets = denoise_targets(texts, charges, config=self._denoise_tto, engine=self._credit_reward.engine,
                                  margin_cm=self.args.denoise_margin_cm, decimals=self.args.denoise_decimals)
        rows = [tokenize_target(self._tokenizer, t.text, t.spans, max_length=self.max_completion_length)
                if t is not None else ([], []) for t in targets]
        output.update(padded_targets("denoise", rows, self._tokenizer.pad_token_id, completion_ids.device))
        found = [t for t in targets if t is not None]
        self._log_value("denoise/rows_frac", len(found) / max(len(targets), 1))
        self._log_value("denoise/token_frac", sum(sum(m) for _, m in rows) / max(sum(lengths), 1))
        if found:
            self._log_value("denoise/depth_before_cm", float(np.mean([t.depth_before for t in found])))
            self._log_value("denoise/depth_after_cm", float(np.mean([t.depth_after for t in found])))
            free = float(np.mean([t.depth_after == 0 for t in found]))
            self._log_value("denoise/collision_free_frac", free)
        self._log_value("time/denoise_s", time.perf_counter() - start)

    def _mask_overruled(self, output: dict, overruled: list[list[int]]) -> None:
        """Zero the loss mask where the constraint, not the policy, chose the token.

        There the unmasked log-probability is not the probability the token was sampled with (it
        was forced or redrawn), and the policy gradient would push it anywhere at no cost to what
        is sampled: with a negative advantage, down without bound, which shows as KL spikes against
        the reference. TRL's ``tool_mask`` (tool output in a completion) already leaves tokens out of
        the loss, the KL and ``num_items_in_batch``; the overruled ones are added to it.
        """
        completion_ids = output["completion_ids"]
        if len(overruled) != completion_ids.size(0):
            raise ValueError(f"constraint rows {len(overruled)} != completions {completion_ids.size(0)}")
        completion_mask = output["completion_mask"]
        keep = torch.ones_like(completion_ids, dtype=completion_mask.dtype)
        pairs = [(b, p) for b, positions in enumerate(overruled) for p in positions if p < keep.size(1)]
        if pairs:
            keep[tuple(torch.tensor(pairs, device=keep.device).T)] = 0
        tool_mask = output.get("tool_mask")
        output["tool_mask"] = keep if tool_mask is None else tool_mask * keep
        # one gather for the loss's token count and the logged share of overruled tokens
        local = torch.stack([(completion_mask * output["tool_mask"]).sum(),
                             (completion_mask * (1 - keep)).sum(), completion_mask.sum()])
        loss_items, masked, total = self.accelerator.gather(local.reshape(1, 3)).sum(0)
        output["num_items_in_batch"] = loss_items
        self._log_value("constraint/overruled_frac", (masked / total.clamp(min=1)).item())

    def anchor_cross_entropy(self, model, inputs) -> torch.Tensor:
        """Mean token NLL of the anchors given their prompts, over the supervised anchor tokens (scalar)."""
        nll, count = self._target_nll(model, inputs, "anchor")
        return nll / count.clamp(min=1.0)

    def _target_nll(self, model, inputs, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(summed NLL, supervised token count) of the completions ``<name>_ids`` given their prompts,
        over ``<name>_loss_mask``."""
        target_ids = inputs[f"{name}_ids"]
        input_ids = torch.cat([inputs["prompt_ids"], target_ids], dim=1)
        attention_mask = torch.cat([inputs["prompt_mask"], inputs[f"{name}_attention_mask"]], dim=1)
        logps, _, _ = self._get_per_token_logps_and_entropies(model, input_ids, attention_mask,
                                                              target_ids.size(1))
        mask = inputs[f"{name}_loss_mask"].to(logps.dtype)
        return -(logps * mask).sum(), mask.sum()

    def denoise_loss(self, model, inputs) -> torch.Tensor:
        """The denoising targets' summed NLL over TRL's dapo normaliser (the completion tokens of one
        accumulation window on this rank): a rewritten token pulls like a sampled token of advantage 1."""
        nll, count = self._target_nll(model, inputs, "denoise")
        normalizer = inputs["num_items_in_batch"].clamp(min=1.0) / self.accelerator.num_processes
        if self.model.training:
            normalizer = normalizer * self.current_gradient_accumulation_steps
            normalizer = normalizer / self.args.steps_per_generation
        self._log_value("denoise/nll", (nll.detach() / count.clamp(min=1.0)).item())
        return nll / normalizer

    def training_step(self, model, inputs, num_items_in_batch=None):
        loss = super().training_step(model, inputs, num_items_in_batch)
        if self._probes_left > 0 and self._probed_step != self.state.global_step:
            if nonfinite_gradients(model)[0]:
                self._probes_left -= 1
                self._probed_step = self.state.global_step  # later micro-batches carry the same NaN
                self.probe_nonfinite(model, self._micro_batch_inputs)
        return loss

    def probe_nonfinite(self, model, inputs) -> dict:
        """Take apart a micro-batch whose backward left a non-finite gradient (``pada.nonfinite_probe``).

        Runs each loss term's backward alone (the GRPO loss; the anchor CE under the model's own
        attention and under eager attention) and the anchor CE of each row alone, and notes which
        leave every gradient finite, with each row's prompt padding and anchor length. The report
        goes to the log and ``<output_dir>/nonfinite_probe.jsonl``, the micro-batch's tensors to
        ``<output_dir>/nonfinite_step<N>.pt`` for a replay. The gradients are put back as they were,
        so :class:`~physcene.train.sft.SkipNonFiniteSteps` still drops the step. (The probe's GRPO
        forward logs its metrics, KL and entropy, a second time for that step.)
        """
        params = [q for q in model.parameters() if q.requires_grad]
        saved = [q.grad for q in params]

        def finite_backward(term) -> tuple[float, bool]:
            for q in params:
                q.grad = None
            with self.compute_loss_context_manager():
                value = term()
            with self.accelerator.no_sync(model):  # this rank's own diagnosis: no gradient all-reduce
                value.backward()
            return float(value.detach()), not nonfinite_gradients(model)[0]

        step = self.state.global_step + 1

        def anchor_ce(batch=inputs):
            return self.anchor_cross_entropy(model, batch)

        report: dict = {"step": step,
                        "grpo_loss": finite_backward(lambda: GRPOTrainer._compute_loss(self, model, inputs))}
        if "anchor_ids" in inputs and inputs["anchor_loss_mask"].sum() > 0:
            report["anchor_ce"] = finite_backward(anchor_ce)
            base = self.accelerator.unwrap_model(model)
            attention = base.config._attn_implementation
            if attention != "eager":
                base.set_attn_implementation("eager")
                try:
                    report["anchor_ce_eager"] = finite_backward(anchor_ce)
                finally:
                    base.set_attn_implementation(attention)
            rows = []
            row_keys = ("prompt_ids", "prompt_mask", "anchor_ids", "anchor_attention_mask",
                        "anchor_loss_mask")
            for b in range(inputs["anchor_ids"].size(0)):
                if inputs["anchor_loss_mask"][b].sum() == 0:
                    continue
                one = {k: inputs[k][b:b + 1] for k in row_keys}
                value, finite = finite_backward(lambda one=one: anchor_ce(one))
                rows.append({"row": b, "ce": value, "finite": finite,
                             "prompt_tokens": int(one["prompt_mask"].sum()),
                             "prompt_width": one["prompt_ids"].size(1),
                             "anchor_tokens": int(one["anchor_attention_mask"].sum()),
                             "anchor_width": one["anchor_ids"].size(1)})
            report["anchor_rows"] = rows
        for q, g in zip(params, saved):
            q.grad = g
        broken = [r["row"] for r in report.get("anchor_rows", ()) if not r["finite"]]
        logger.warning("step %d: non-finite gradient probe (value, finite backward): %s", step,
                       {k: v for k, v in report.items() if k != "anchor_rows"}
                       | {"rows_with_nonfinite_ce": broken})
        if self.is_world_process_zero():
            out = Path(self.args.output_dir)
            out.mkdir(parents=True, exist_ok=True)
            with open(out / "nonfinite_probe.jsonl", "a") as f:
                f.write(json.dumps(report) + "\n")
            torch.save({k: v.detach().cpu() for k, v in inputs.items() if isinstance(v, torch.Tensor)},
                       out / f"nonfinite_step{step}.pt")
        return report

    def _compute_loss(self, model, inputs):
        if self._probes_left > 0:
            self._micro_batch_inputs = inputs
        loss = super()._compute_loss(model, inputs)
        if self.denoise and "denoise_ids" in inputs and inputs["denoise_loss_mask"].sum() > 0:
            loss = loss + self.denoise * self.denoise_loss(model, inputs)
        if self.anchor_alpha == 0.0 or "anchor_ids" not in inputs:
            return loss
        mode = "train" if self.model.training else "eval"
        has_anchor = inputs["anchor_loss_mask"].sum() > 0
        ce = self.anchor_cross_entropy(model, inputs) if has_anchor else loss.new_zeros(())
        # TRL divides its own loss by the accumulation steps (HF auto-scaling is off): do the same.
        normalizer = self.current_gradient_accumulation_steps if mode == "train" else 1.0
        stats = torch.stack([ce.detach() * has_anchor, has_anchor.float(), loss.detach()])
        stats = self.accelerator.reduce(stats, reduction="sum")
        if not bool(torch.isfinite(stats).all()):  # say which term broke (SkipNonFiniteSteps drops the step)
            logger.warning("step %d: non-finite loss term (anchor CE sum %s over %d ranks with anchors, "
                           "GRPO loss sum %s)", self.state.global_step + 1, stats[0].item(), int(stats[1]),
                           stats[2].item())
        if stats[1] > 0:
            self._metrics[mode]["anchor_ce"].append((stats[0] / stats[1]).item())
        return loss + self.anchor_alpha * ce / normalizer


class AdaptiveKLCallback(TrainerCallback):
    """Adaptive KL coefficient (Ziegler et al. 2019): β ← β · (1 + clip(KL/target − 1, ±0.2) · n/horizon).

    Reads the ``kl`` that GRPOTrainer logs (mean per-token KL to the reference), ``n`` = optimizer
    steps since the last update; β stays in ``[min_beta, max_beta]`` (it must stay > 0: TRL only
    computes reference log-probs when β ≠ 0). The new β goes into the log entry that carried the KL
    (``beta`` in ``train_log.json`` and the checkpoints' ``trainer_state.json``), and a run resumed
    from a checkpoint goes on from the last β logged there instead of the configured one.
    """

    def __init__(self, trainer: GRPOTrainer, target: float = 0.05, horizon: int = 100,
                 min_beta: float = 1e-3, max_beta: float = 1.0):
        if trainer.beta <= 0:
            raise ValueError(f"adaptive KL needs an initial beta > 0, got {trainer.beta}")
        if target <= 0 or horizon <= 0:
            raise ValueError(f"adaptive KL needs target > 0 and horizon > 0, got {target}, {horizon}")
        self.trainer, self.target, self.horizon = trainer, target, horizon
        self.min_beta, self.max_beta = min_beta, max_beta
        self._last_step = 0

    def update(self, kl: float, global_step: int) -> float:
        """Apply one update for the measured ``kl`` at ``global_step``; returns the new β."""
        error = min(max(kl / self.target - 1.0, -0.2), 0.2)
        steps = max(global_step - self._last_step, 1)
        self._last_step = global_step
        beta = self.trainer.beta * (1.0 + error * steps / self.horizon)
        self.trainer.beta = min(max(beta, self.min_beta), self.max_beta)
        return self.trainer.beta

    def on_train_begin(self, args, state, control, **kwargs):
        logged = [entry for entry in state.log_history if "beta" in entry]
        if state.global_step > 0 and logged:  # resumed: the history is the checkpoint's
            self.trainer.beta = float(logged[-1]["beta"])
            self._last_step = int(logged[-1].get("step", state.global_step))

    def on_log(self, args, state, control, logs=None, **kwargs):
        if logs and "kl" in logs and state.global_step > self._last_step:
            self.update(float(logs["kl"]), state.global_step)
            # GRPOTrainer empties its metric buffers once a log is written, so β goes straight into
            # the entry the Trainer has just appended for these logs
            if state.log_history and state.log_history[-1].get("step") == state.global_step:
                state.log_history[-1]["beta"] = self.trainer.beta


class PhysicsRewardFunction:
    """TRL reward function: ``physcene.reward.PhysicsReward`` with its engine on this rank's device.

    Each rank scores only its own completions (TRL gathers the rewards afterwards), so on N GPUs the
    engine runs N-way parallel. After each batch it logs, through the trainer's ``log_metric``:
    ``time/reward_s`` (this rank's seconds), ``parse_rate``, and over the parsed layouts
    ``penetration_mm`` (mean E_pen, mm), ``max_depth_mm`` and ``collision_free_rate``; with the
    reward's size guard ``size_outside_cm``, with its ``valid_terms`` ``invalid_rate`` and
    ``floating_objects`` / ``shrunk_objects`` (mean per layout).
    """

    __name__ = "physics"

    def __init__(self, device: str | torch.device = "cpu", reward=None, overrides=()):
        if reward is None:
            from dataclasses import replace

            from physcene.reward import PhysicsReward, RewardConfig

            reward = PhysicsReward(replace(RewardConfig.load(list(overrides)), device=str(device)))
        self.reward = reward

    def __call__(self, prompts, completions, log_metric=None, **columns) -> list[float]:
        start = time.perf_counter()
        rewards = self.reward(prompts, completions)
        seconds = time.perf_counter() - start
        m = self.reward.last_metrics
        if log_metric is not None:
            log_metric("time/reward_s", seconds)
            log_metric("parse_rate", 1.0 - m["parse_failure_rate"])
            if m["parse_failure_rate"] < 1.0:  # energy figures exist only for parsed layouts
                log_metric("penetration_mm", m["mean_energy_mm"])
                log_metric("max_depth_mm", m["mean_max_depth_mm"])
                log_metric("collision_free_rate", m["collision_free_rate"])
                if "mean_size_outside_cm" in m:
                    log_metric("size_outside_cm", m["mean_size_outside_cm"])
                if "invalid_rate" in m:  # reward.valid_terms: the share paid `invalid`, objects per term
                    log_metric("invalid_rate", m["invalid_rate"])
                    for term in self.reward.config.valid_terms:
                        log_metric(f"{term}_objects", m[f"mean_{term}_objects"])
        return rewards


def pada_arguments(cfg, variant: str) -> PADAConfig:
    """The :class:`PADAConfig` of ``cfg.pada`` for ``variant`` (paper stage 2 defaults in the configs)."""
    from omegaconf import OmegaConf
    from physcene.train.sft import _precision, accumulation_steps, world_size

    from physcene.reward import object_terms_checked, penetration_charge_checked

    if variant not in VARIANTS:
        raise ValueError(f"unknown PADA variant {variant!r}; use one of {sorted(VARIANTS)}")
    from physcene.train.generate import check_cache

    p = cfg.pada
    column, numeric_mask = VARIANTS[variant]
    cache = check_cache(str(p.get("cache", "dynamic")))
    deepspeed = OmegaConf.to_container(p.deepspeed, resolve=True) if p.deepspeed is not None else None
    accumulation = accumulation_steps(int(p.global_batch_size), int(p.per_device_batch_size), world_size())
    generation_batches = int(p.get("generation_batches", 1))
    num_iterations = int(p.get("num_iterations", 1))
    for key, value in (("generation_batches", generation_batches), ("num_iterations", num_iterations)):
        if value < 1:
            raise ValueError(f"pada.{key} must be a positive integer, got {value}")
    object_credit = float(p.get("object_credit", 0.0) or 0.0)
    if object_credit < 0:
        raise ValueError(f"pada.object_credit must be >= 0 (advantage per cm of penetration), "
                         f"got {object_credit}")
    denoise = float(p.get("denoise", 0.0) or 0.0)
    denoise_margin_cm = float(p.get("denoise_margin_cm", 1.0))
    if denoise < 0 or denoise_margin_cm < 0:
        raise ValueError(f"pada.denoise and pada.denoise_margin_cm must be >= 0, got {denoise}, "
                         f"{denoise_margin_cm}")
    denoise_decimals = p.get("denoise_decimals")
    whole = isinstance(denoise_decimals, int) and not isinstance(denoise_decimals, bool)
    if denoise_decimals is not None and not (whole and 0 <= denoise_decimals <= MAX_DECIMALS):
        raise ValueError(f"pada.denoise_decimals must be null or an integer from 0 to {MAX_DECIMALS}, "
                         f"got {denoise_decimals!r}")
    denoise_tto = p.get("denoise_tto", ["lambda_zone=100.0"])
    denoise_tto = [str(x) for x in (OmegaConf.to_container(denoise_tto) if OmegaConf.is_config(denoise_tto)
                                    else denoise_tto or [])]
    scope = str(p.get("object_credit_scope", "line"))
    try:
        object_credit_scope_checked(scope)
    except ValueError as exc:
        raise ValueError(f"pada.object_credit_scope: {exc}") from None
    penetration = str(p.get("object_credit_penetration", "depth"))
    try:
        penetration_charge_checked(penetration)
    except ValueError as exc:
        raise ValueError(f"pada.object_credit_penetration: {exc}") from None
    terms = p.get("object_credit_terms", ["penetration"])
    try:
        terms = OmegaConf.to_container(terms) if OmegaConf.is_config(terms) else terms
        terms = list(object_terms_checked(terms))
    except ValueError as exc:
        raise ValueError(f"pada.object_credit_terms: {exc}") from None
    return PADAConfig(
        output_dir=str(p.output_dir),
        anchor_alpha=0.0 if column is None else float(p.alpha),
        anchor_column=column or "anchor",
        anchor_numeric_mask=numeric_mask,
        beta=float(p.beta),
        num_generations=int(p.num_generations),
        max_completion_length=int(p.max_completion_length),
        temperature=float(p.temperature),
        # TRL passes it to GenerationConfig (HF generate, use_vllm=False); None = HF's dynamic cache
        cache_implementation=None if cache == "dynamic" else "static",
        generation_compile=cache == "static_compile",
        constrained_decoding=bool(p.get("constrained", False)),
        mask_overruled=bool(p.get("mask_overruled", True)),
        nonfinite_probe=int(p.get("nonfinite_probe", 0) or 0),
        object_credit=object_credit,
        object_credit_terms=terms,
        object_credit_scope=scope,
        object_credit_penetration=penetration,
        denoise=denoise,
        denoise_margin_cm=denoise_margin_cm,
        denoise_tto=denoise_tto,
        denoise_decimals=denoise_decimals,
        learning_rate=float(p.learning_rate),
        lr_scheduler_type=str(p.lr_scheduler_type),
        num_train_epochs=float(p.epochs),
        max_steps=int(p.max_steps),
        per_device_train_batch_size=int(p.per_device_batch_size),
        gradient_accumulation_steps=accumulation,
        # TRL counts steps_per_generation in micro-batches: one generation round feeds
        # `generation_batches` optimizer steps of global_batch_size completions each.
        steps_per_generation=accumulation * generation_batches,
        num_iterations=num_iterations,
        save_steps=int(p.save_steps),
        save_total_limit=None if p.get("save_total_limit", 2) is None else int(p.save_total_limit),
        logging_steps=int(p.logging_steps),
        report_to="none",
        seed=int(cfg.seed),
        deepspeed=deepspeed,
        dataloader_num_workers=0,
        # TRL turns it on by default; the tiny/small models have memory to spare and run faster without.
        gradient_checkpointing=bool(p.get("gradient_checkpointing", False)),
        # Two forwards (GRPO, anchor) feed one backward; every trainable (LoRA) weight is used by
        # both, so DDP needs no unused-parameter search, which would trip over the second forward.
        ddp_find_unused_parameters=False,
        **_precision(cfg),
    )


def run_pada(cfg, variant: str | None = None, reward=None, callbacks=()) -> Path:
    """Train stage 2 (``variant`` or ``cfg.pada.variant``) from ``cfg.pada.model`` on ``cfg.pada.anchors``.

    Saves the LoRA adapter, tokenizer and run info to ``cfg.pada.output_dir``; resumes from its last
    checkpoint. ``reward`` (a ``physcene.reward.PhysicsReward``) replaces the default one on this rank's
    device, e.g. to share an engine.
    """
    from accelerate import PartialState
    from omegaconf import OmegaConf
    from physcene.train.models import (
        load_model,
        load_tokenizer,
        read_run_info,
        set_attention_kernels,
        write_run_info,
    )
    from physcene.train.records import load_records, training_dataset
    from physcene.train.sft import SkipNonFiniteSteps, lora_config, skipped_steps, time_budget_callbacks
    from transformers.trainer_utils import get_last_checkpoint

    if variant is not None and variant != cfg.pada.variant:
        # pada.output_dir interpolates ${pada.variant}: set it, don't just pass it along.
        cfg = OmegaConf.merge(cfg, {"pada": {"variant": variant}})
    variant = str(cfg.pada.variant)
    args = pada_arguments(cfg, variant)
    model_dir = Path(str(cfg.pada.model))
    info = read_run_info(model_dir)
    chat = bool(info.get("chat_format", cfg.model.chat_format))
    records = load_records(str(cfg.pada.anchors), max_level=cfg.pada.get("max_level"))
    if not records:
        raise ValueError(f"no records in anchor file {cfg.pada.anchors!r}")
    if args.anchor_alpha > 0 and not any(r.get(args.anchor_column) for r in records):
        raise NoAnchorsError(f"{cfg.pada.anchors}: no record has a non-empty {args.anchor_column!r} "
                         f"(variant {variant})")
    dataset = training_dataset(records, chat_format=chat, columns=("anchor", "anchor_raw"))
    dtype = str(cfg.model.dtype) if __import__("torch").cuda.is_available() else "float32"
    # Absolute path: PEFT records it as the adapter's base model, read back by generate().
    set_attention_kernels(cfg.model)  # cuDNN attention's backward NaNs on left-padded rows (torch 2.11)
    model = load_model(model_dir.resolve(), dtype=dtype, freeze_vision=bool(cfg.model.freeze_vision))
    tokenizer = load_tokenizer(model_dir)
    state = PartialState()
    reward_fn = PhysicsRewardFunction(state.device, reward=reward, overrides=list(cfg.pada.get("reward", [])))
    trainer = PADATrainer(
        model=model,
        reward_funcs=[reward_fn],
        args=args,
        train_dataset=dataset,
        processing_class=tokenizer,
        peft_config=lora_config(cfg.pada.lora),
        callbacks=[*callbacks, *time_budget_callbacks(cfg.pada), SkipNonFiniteSteps()],
    )
    kl = cfg.pada.adaptive_kl
    if kl is not None and args.beta > 0:
        trainer.add_callback(AdaptiveKLCallback(trainer, target=float(kl.target), horizon=int(kl.horizon),
                                                min_beta=float(kl.min_beta), max_beta=float(kl.max_beta)))
    out = Path(args.output_dir)
    trainer.train(resume_from_checkpoint=get_last_checkpoint(str(out)) if out.is_dir() else None)
    trainer.save_model(str(out))
    if trainer.is_world_process_zero():
        tokenizer.save_pretrained(str(out))
        (out / "train_log.json").write_text(json.dumps(trainer.state.log_history, indent=1))
        write_run_info(out, stage="pada", variant=variant, chat_format=chat, alpha=args.anchor_alpha,
                       eval_batch_size=int(cfg.eval.batch_size), steps=trainer.state.global_step,
                       stopped_by_budget=any(getattr(c, "stopped_early", False)
                                             for c in trainer.callback_handler.callbacks),
                       nonfinite_steps_dropped=skipped_steps(trainer),
                       base_model=str(model_dir.resolve()), n_records=len(records))
    return out
