"""PADA's groups sampled under the CTRC constraint (``pada.constrained``; not in the paper, off by
default), and the tokens the constraint chose left out of the loss (``pada.mask_overruled``).

The completions are sampled from the policy restricted to valid CTRC continuations
(:class:`~physcene.train.constrained.CTRCConstraint`, a transformers logits processor); their
log-probabilities are then taken under the unrestricted policy as usual (TRL's vLLM guided decoding,
``structured_outputs_regex``, does the same). TRL 1.16 calls ``generate(**inputs,
generation_config=...)`` and passes no logits processors, and transformers refuses a processor inside
a ``GenerationConfig``, so :func:`generate_with_processors` is TRL's HF generation call (text
prompts) with ``logits_processor=`` added; the trainer takes it only when an extension has a processor.

The positions where the constraint overruled the policy's draw (~1 % of tokens for ``small``) join
TRL's ``tool_mask``: there the unmasked log-probability is not the probability the token was sampled
with (it was forced or redrawn), and left in the loss a negative advantage pushes such a token down at
no cost to what is sampled, and its KL term to the reference grows without bound (docs/training.md,
"Tokens the constraint chose"). Logged: ``time/constraint_s`` (the constraint's host time; GPU:
``time/constraint_wait_s`` the forward's share, ``time/constraint_scan_s`` the vocabulary scans),
``constraint/refused_draws``, ``constraint/vocabulary_scans`` and ``constraint/overruled_frac``.
"""

from __future__ import annotations

import logging
from collections import deque

import torch
from transformers import LogitsProcessorList, TrainerCallback
from trl import GRPOTrainer
from trl.extras.profiling import profiling_context
from trl.models import unwrap_model_for_generation
from trl.trainer.utils import pad

from physcene.train.constrained import CTRCConstraint, sampling_warpers
from physcene.train.extension import PADAExtension

__all__ = ["ConstrainedRollouts", "OverruledStop", "fast_rollouts", "generate_with_processors",
           "mask_overruled"]

logger = logging.getLogger(__name__)


class ConstrainedRollouts(PADAExtension):
    """The CTRC constraint as the generation's logits processor; ``mask``: leave the tokens it chose
    out of the GRPO loss, the KL and the token count (:func:`mask_overruled`)."""

    def __init__(self, mask: bool = True):
        self.mask = bool(mask)
        self._processor: CTRCConstraint | None = None
        self._overruled: list[list[int]] | None = None

    def logits_processors(self, trainer, prompts: list) -> list:
        texts = [p if isinstance(p, str) else str(p[-1]["content"]) for p in prompts]  # chat: the user turn
        config = trainer.generation_config
        # sampling: each row's token drawn by rejection from the same warped distribution TRL samples
        self._processor = CTRCConstraint(trainer._tokenizer, texts, greedy=not config.do_sample,
                                         warpers=sampling_warpers(config))
        return [self._processor]

    def after_generation(self, trainer) -> None:
        processor = self._processor
        self._overruled = processor.stats.overruled  # row order = this round's prompts
        trainer.log_value("time/constraint_s", processor.stats.seconds)
        trainer.log_value("time/constraint_wait_s", processor.stats.wait_seconds)  # GPU: the forward's share
        # where that time goes: draws refused, and rows that fell back to scanning the vocabulary
        trainer.log_value("time/constraint_scan_s", processor.stats.scan_seconds)
        trainer.log_value("constraint/refused_draws", float(processor.stats.refused_draws))
        trainer.log_value("constraint/vocabulary_scans", float(processor.stats.vocabulary_scans))

    def after_scoring(self, trainer, inputs: list[dict], output: dict) -> None:
        overruled, self._overruled = self._overruled, None
        if self.mask and overruled is not None:
            mask_overruled(trainer, output, overruled)


def mask_overruled(trainer, output: dict, overruled: list[list[int]]) -> None:
    """Zero the loss mask where the constraint, not the policy, chose the token (``overruled[b]``: the
    completion positions of row b).

    TRL's ``tool_mask`` (tool output in a completion) already leaves tokens out of the loss, the KL
    and ``num_items_in_batch``; the overruled ones are added to it.
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
    loss_items, masked, total = trainer.accelerator.gather(local.reshape(1, 3)).sum(0)
    output["num_items_in_batch"] = loss_items
    trainer.log_value("constraint/overruled_frac", (masked / total.clamp(min=1)).item())


class OverruledStop(TrainerCallback):
    """Stop a run (saving a checkpoint) whose policy has left the grammar: once the constraint overrules
    more than ``share`` of the sampled tokens (``constraint/overruled_frac``, gathered over the
    processes, so every rank stops at the same step), averaged over the last ``steps`` logged steps
    (``pada.stop_overruled``, ``pada.stop_overruled_steps``).

    A policy that puts its mass on tokens the CTRC grammar refuses is still sampled valid text, by
    rejection, so nothing else in the logs breaks, but every refused draw costs host time: GRPO with
    per-object credit went from ~1 % overruled and 4 s a step to 31-45 % and 127 s a step within 20
    steps (docs/results.md, "Per-object credit"), where PADA's runs stay at ~1 %. ``stopped_at`` is
    the step it stopped at (None: it did not)."""

    def __init__(self, share: float, steps: int = 5):
        if not 0.0 < float(share) < 1.0:
            raise ValueError(f"pada.stop_overruled is a share of the sampled tokens in (0, 1), got {share!r}")
        if int(steps) < 1:
            raise ValueError(f"pada.stop_overruled_steps must be >= 1, got {steps!r}")
        self.share = float(share)
        self.recent: deque[float] = deque(maxlen=int(steps))
        self.stopped_at: int | None = None

    def on_log(self, args, state, control, logs=None, **kwargs):
        value = (logs or {}).get("constraint/overruled_frac")
        if value is None or self.stopped_at is not None:
            return control
        self.recent.append(float(value))
        mean = sum(self.recent) / len(self.recent)
        if len(self.recent) == self.recent.maxlen and mean > self.share:
            self.stopped_at = state.global_step
            logger.warning("step %d: the constraint overruled %.1f %% of the sampled tokens over the "
                           "last %d steps (pada.stop_overruled %.1f %%): the policy has left the grammar; "
                           "stopping, with a checkpoint",
                           state.global_step, 100 * mean, len(self.recent), 100 * self.share)
            control.should_training_stop = True
            control.should_save = True
        return control


def _generation_inputs(trainer: GRPOTrainer, prompt_ids: list[list[int]]) -> dict:
    """TRL's left-padded prompt batch on the trainer's device."""
    prompt_tensors = [torch.tensor(ids) for ids in prompt_ids]
    padded_ids = pad(prompt_tensors, padding_value=trainer._tokenizer.pad_token_id, padding_side="left",
                     pad_to_multiple_of=trainer.pad_to_multiple_of)
    attention_mask = pad([torch.ones_like(t) for t in prompt_tensors], padding_value=0, padding_side="left",
                         pad_to_multiple_of=trainer.pad_to_multiple_of)
    # Trainer's _prepare_inputs (device placement), as TRL's own call does
    return super(GRPOTrainer, trainer)._prepare_inputs(
        {"input_ids": padded_ids, "attention_mask": attention_mask})


def _unwrapped(trainer: GRPOTrainer):
    """TRL's context for a generation call: (profiling, the unwrapped model, no grad, full params)."""
    return (profiling_context(trainer, "transformers.generate"),
            unwrap_model_for_generation(
                trainer.model_wrapped, trainer.accelerator,
                gather_deepspeed3_params=trainer.args.ds3_gather_for_generation,
                generation_kwargs=trainer.generation_kwargs,
                gradient_checkpointing_kwargs=trainer.args.gradient_checkpointing_kwargs),
            torch.no_grad(),
            trainer._dist.summon_full_params(trainer.model_wrapped, recurse=False))


def fast_rollouts(trainer: GRPOTrainer, prompt_ids: list[list[int]],
                  processors: list) -> tuple[list[list[int]], None]:
    """TRL's generation call with the fast decoder (``pada.cache: fast``): (completion ids per row, cut
    after the first EOS; None), as :func:`generate_with_processors`. The CTRC constraint (the one
    processor it takes) is checked beside the GPU. Settings it does not rebuild (another logits
    processor, a repetition penalty, suppressed tokens, a warper outside temperature/top-k/top-p/
    min-p) go to HF generate instead, once logged."""
    from physcene.train.decode import FAST_CACHES, fast_generate
    from physcene.train.generate import longest_prompt_tokens

    config = trainer.generation_config
    constraint = next((p for p in processors if isinstance(p, CTRCConstraint)), None)
    warpers = sampling_warpers(config) if config.do_sample else None
    unsupported = [name for name, bad in (
        ("logits processors", len(processors) > (constraint is not None)),
        ("repetition_penalty", (config.repetition_penalty or 1.0) != 1.0),
        ("suppress_tokens", bool(config.suppress_tokens)),
        ("warpers", config.do_sample and warpers is None)) if bad]
    if unsupported:
        if not getattr(trainer, "_fast_decode_refused", False):
            logger.warning("pada.cache=fast: %s set, generating with HF generate", ", ".join(unsupported))
            trainer._fast_decode_refused = True
        return generate_with_processors(trainer, prompt_ids, processors)
    length = getattr(trainer, "_fast_decode_length", None)
    if length is None:  # one cache length for the run: one decoder and one set of CUDA graphs
        try:
            prompts = trainer.train_dataset["prompt"]
        except (TypeError, KeyError):  # no dataset, or an iterable one: this round's prompts only
            prompts = ()
        longest = max(longest_prompt_tokens(trainer._tokenizer, prompts), max(map(len, prompt_ids)))
        multiple = trainer.pad_to_multiple_of or 1
        length = trainer._fast_decode_length = -(-longest // multiple) * multiple + config.max_new_tokens
    attention, fuse = FAST_CACHES[trainer.args.fast_decode]
    inputs = _generation_inputs(trainer, prompt_ids)
    profiling, unwrapping, no_grad, full_params = _unwrapped(trainer)
    with profiling, unwrapping as unwrapped_model, no_grad, full_params:
        result = fast_generate(unwrapped_model, inputs["input_ids"], inputs["attention_mask"],
                               max_new_tokens=config.max_new_tokens,
                               min_new_tokens=config.min_new_tokens or 0, eos=list(trainer.eos_token_ids),
                               pad=trainer._tokenizer.pad_token_id, sampling=bool(config.do_sample),
                               warpers=warpers, constraint=constraint, length=length, attention=attention,
                               fuse=fuse, merge_lora=trainer.args.merge_adapters,
                               constraint_workers=trainer.args.constraint_workers)
    trainer.log_value("time/decode_graphs", float(result.graphs))
    trainer.log_value("time/decode_repairs", float(result.repairs))
    trainer.log_value("time/decode_host_check_s", result.seconds.get("host_check", 0.0))
    trainer.log_value("time/decode_merged_projections", float(result.merged_projections))
    return result.tokens, None


def generate_with_processors(trainer: GRPOTrainer, prompt_ids: list[list[int]],
                             processors: list) -> tuple[list[list[int]], None]:
    """TRL's HF-generate path of ``GRPOTrainer._generate_single_turn`` for text prompts, with
    ``processors`` passed to ``generate``: (completion ids per row, cut after the first EOS; None)."""
    device = trainer.accelerator.device
    generate_inputs = _generation_inputs(trainer, prompt_ids)
    profiling, unwrapping, no_grad, full_params = _unwrapped(trainer)
    with profiling, unwrapping as unwrapped_model, no_grad, full_params:
        prompt_completion_ids = unwrapped_model.generate(
            **generate_inputs, generation_config=trainer.generation_config,
            logits_processor=LogitsProcessorList(processors))
    completion_ids = prompt_completion_ids[:, generate_inputs["input_ids"].size(1):]
    # everything after the first EOS is cut, as in TRL
    is_eos = torch.isin(completion_ids, torch.tensor(trainer.eos_token_ids, device=device))
    eos_idx = torch.full((is_eos.size(0),), is_eos.size(1), dtype=torch.long, device=device)
    eos_idx[is_eos.any(dim=1)] = is_eos.int().argmax(dim=1)[is_eos.any(dim=1)]
    sequence_indices = torch.arange(is_eos.size(1), device=device).expand(is_eos.size(0), -1)
    completion_mask = (sequence_indices <= eos_idx.unsqueeze(1)).int()
    rows = zip(completion_ids.cpu(), completion_mask.bool().cpu(), strict=True)
    return [c[m].tolist() for c, m in rows], None
