"""Stage 2: PADA — GRPO with a cross-entropy pull toward physically-projected semantic anchors.

The paper's objective (Sec. 3.3, appendix "Stage 2")::

    J(θ) = E[ 1/K Σ_k A_k π_θ(S_k)/π_old(S_k) ]  +  α · L_CE(π_θ, S*_anchor)        (α = 0.1)

is TRL's GRPO loss plus one term. Following TRL's extension pattern (``trl/experimental/gmpo``), the
subclass :class:`PADATrainer` changes two of TRL's methods:

- ``_generate_and_score_completions``: after TRL has generated and scored the group, tokenise each
  prompt's anchor (the ``anchor`` column written by :mod:`physcene.train.anchors`) into
  ``anchor_ids``/``anchor_attention_mask``/``anchor_loss_mask`` so TRL shuffles and splits them with
  the rest of the batch (``_set_signature_columns_if_needed`` keeps the column);
- ``_compute_loss``: ``loss = GRPO loss + α · CE(anchor)``, with the same gradient-accumulation scaling
  TRL applies to its own loss, and the CE logged as ``anchor_ce``.

Variants (``pada.variant``, :data:`~physcene.train.config.VARIANTS`): ``pada`` (TTO-repaired anchors),
``pada_star`` (raw SFT output as the anchor, CE masked to non-numeric tokens: the box and rotation
values are left to GRPO, as the paper's PADA*), ``grpo`` (α = 0: plain GRPO, no anchor forward pass).
Rows whose anchor is empty (the SFT output did not parse) contribute no CE.

Everything not in the paper reaches the trainer through one hook,
:class:`~physcene.train.extension.PADAExtension` (sampling under the CTRC constraint, per-object
credit, denoising targets, the non-finite gradient probe; each off by default, configured by
:class:`~physcene.train.config.PADAConfig`). ``_generate``, ``_generate_single_turn`` and
``training_step`` only call those hooks (and log ``time/generate_s``). β (KL to the SFT model) starts
at 0.04 and is adapted by :class:`~physcene.train.kl.AdaptiveKLCallback`.
"""

from __future__ import annotations

import contextlib
import logging
import time
from contextlib import ExitStack
from pathlib import Path

import torch
from accelerate import PartialState
from omegaconf import OmegaConf
from peft.helpers import disable_input_dtype_casting
from trl import GRPOTrainer

from physcene.reward.trl import PhysicsRewardFunction
from physcene.train.checkpoints import last_complete_checkpoint
from physcene.train.config import VARIANTS, PADAConfig, pada_arguments, reward_overrides
from physcene.train.constrained_rollouts import (
    ConstrainedRollouts,
    OverruledStop,
    fast_rollouts,
    generate_with_processors,
)
from physcene.train.decode import compiled_layers, text_model
from physcene.train.denoise import Denoise
from physcene.train.diagnostics import NonfiniteProbe
from physcene.train.extension import PADAExtension
from physcene.train.generate import set_trainer_cache
from physcene.train.kl import AdaptiveKLCallback
from physcene.train.micro_batches import grouped_by_length, trimmed
from physcene.train.models import (
    base_checked,
    begin_final_save,
    load_model,
    load_tokenizer,
    read_run_info,
    save_train_log,
    set_attention_kernels,
    write_run_info,
)
from physcene.train.object_credit import ObjectCredit, credit_reward
from physcene.train.records import load_records, training_dataset
from physcene.train.sft import SkipNonFiniteSteps, lora_config, skipped_steps, time_budget_callbacks
from physcene.train.targets import (
    ANCHOR_ROW_KEYS,
    numeric_spans,
    padded_targets,
    tokenize_anchor,
    tokenize_target,
)

__all__ = [
    "VARIANTS",
    "anchor_owners",
    "anchor_rows",
    "NoAnchorsError",
    "AdaptiveKLCallback",
    "PADAConfig",
    "PADATrainer",
    "numeric_spans",
    "pada_arguments",
    "pada_extensions",
    "padded_targets",
    "run_pada",
    "tokenize_anchor",
    "tokenize_target",
]

logger = logging.getLogger(__name__)


def anchor_owners(inputs: list[dict], column: str) -> list[bool]:
    """For each row of a generation round, whether it is the first with its (prompt, anchor): the row
    whose anchor the CE supervises (TRL repeats each prompt, with its anchor, for its G completions)."""
    seen, owners = set(), []
    for x in inputs:
        key = (str(x.get("prompt")), x.get(column) or "")
        owners.append(bool(key[1]) and key not in seen)
        seen.add(key)
    return owners


GROUPING_LOSSES = ("dapo", "dr_grpo", "grpo", "cispo")
"""TRL loss types whose gradient over an optimizer step does not depend on which micro-batch a row is
in (global token normaliser, a constant, or per-row means over micro-batches of equal row counts)."""


class NoAnchorsError(ValueError):
    """An anchor file in which no SFT output parsed: PADA and PADA* have nothing to pull toward."""


def anchor_rows(inputs: dict) -> dict:
    """The anchor CE's rows of a micro-batch (:data:`ANCHOR_ROW_KEYS`): those with a supervised anchor
    token (:func:`anchor_owners`); ``inputs`` itself when every row has one."""
    supervised = inputs["anchor_loss_mask"].any(dim=1)
    if bool(supervised.all()):
        return inputs
    keep = supervised.nonzero().squeeze(1)
    return {k: inputs[k].index_select(0, keep) for k in ANCHOR_ROW_KEYS}


def pada_extensions(trainer: GRPOTrainer, args: PADAConfig) -> list[PADAExtension]:
    """The extensions ``args`` turns on, in the order they act on a round: the constraint's mask, the
    per-object credit, the denoising targets, the probe."""
    extensions: list[PADAExtension] = []
    if args.constrained_decoding:
        extensions.append(ConstrainedRollouts(mask=args.mask_overruled))
    reward = credit_reward(trainer.reward_funcs, args) if args.object_credit or args.denoise else None
    if args.object_credit:
        extensions.append(ObjectCredit(reward, args.object_credit, args.object_credit_scope))
    if args.denoise:
        extensions.append(Denoise(reward, args.denoise, tto=Denoise.tto_config(args.denoise_tto, reward),
                                  margin_cm=args.denoise_margin_cm, decimals=args.denoise_decimals))
    if args.nonfinite_probe:
        if trainer.is_deepspeed_enabled:  # its gradients are not in p.grad
            logger.warning("pada.nonfinite_probe needs gradients in p.grad: off under DeepSpeed")
        else:
            extensions.append(NonfiniteProbe(args.nonfinite_probe))
    return extensions


class PADATrainer(GRPOTrainer):
    """GRPO + α·CE(anchor) (see the module docstring). ``args`` is a :class:`PADAConfig`;
    ``extensions`` replaces the ones its extension fields turn on (:func:`pada_extensions`)."""

    _tag_names = ["trl", "grpo", "pada"]

    def __init__(self, model, reward_funcs, args: PADAConfig | None = None,
                 extensions: list[PADAExtension] | None = None, **kwargs):
        if args is None:
            args = PADAConfig("pada")
        super().__init__(model, reward_funcs, args=args, **kwargs)
        self.anchor_alpha = float(args.anchor_alpha)
        self.extensions = pada_extensions(self, args) if extensions is None else list(extensions)
        self._joint_anchor: dict | None = None  # joint_anchor_pass: the anchors the next policy pass scores
        # inside training_step: the contexts _compute_loss holds through the backward
        self._backward_scope: ExitStack | None = None
        self._round_prompts = None
        self._compiled: dict[int, torch.nn.Module] = {}  # compile_update: each model's compiled forward
        if getattr(self, "generation_config", None) is not None:  # HF generate (not vLLM)
            static = args.cache_implementation == "static"
            prompts = self.train_dataset["prompt"] if static else ()
            set_trainer_cache(self.generation_config, static=static, compiled=args.generation_compile,
                              tokenizer=self._tokenizer, prompts=prompts,
                              max_new_tokens=self.max_completion_length, device=self.accelerator.device)

    def log_value(self, name: str, value: float) -> None:
        """Append ``value`` to the metric ``name``, logged with TRL's metrics at the next logging step."""
        self._metrics["train" if self.model.training else "eval"][name].append(value)

    def _set_signature_columns_if_needed(self):
        super()._set_signature_columns_if_needed()
        # Keep the anchor column through Trainer's column pruning.
        if self.args.anchor_column not in self._signature_columns:
            self._signature_columns.append(self.args.anchor_column)

    def _generate(self, prompts: list):
        self._round_prompts = prompts  # in row order, for the extensions' logits processors
        start = time.perf_counter()
        output = super()._generate(prompts)
        # this rank's generation round, with the constraint's host time (also logged apart as
        # time/constraint_s): where a step's time goes, next to time/reward_s and step_time
        self.log_value("time/generate_s", time.perf_counter() - start)
        return output

    def _generate_single_turn(self, prompt_ids, images, multimodal_fields, num_generations,
                              has_tool_images=False):
        """TRL's generation call, with the extensions' logits processors passed to ``generate`` when
        there are any (:func:`~physcene.train.constrained_rollouts.generate_with_processors`), or the
        fast decoder for text prompts under ``pada.cache: fast``
        (:func:`~physcene.train.constrained_rollouts.fast_rollouts`)."""
        prompts = self._round_prompts
        usable = prompts is not None and len(prompts) == len(prompt_ids) and not self.use_vllm
        used = [(e, e.logits_processors(self, prompts)) for e in self.extensions] if usable else []
        processors = [p for _, ps in used for p in ps]
        fast = self.args.fast_decode is not None and not self.use_vllm and not multimodal_fields
        if not processors and not fast:
            return super()._generate_single_turn(prompt_ids, images, multimodal_fields, num_generations,
                                                 has_tool_images)
        if multimodal_fields:
            raise ValueError("logits processors (pada.constrained) need text prompts, got image fields "
                             f"{sorted(multimodal_fields)}")
        output = (fast_rollouts if fast else generate_with_processors)(self, prompt_ids, processors)
        for extension, ps in used:
            if ps:
                extension.after_generation(self)
        return output

    def _prepare_inputs(self, generation_batch):
        """TRL's micro-batch of this step; with ``length_grouping`` the round's micro-batches regrouped
        by completion length within each optimizer step and each cut to the columns it uses
        (:mod:`physcene.train.micro_batches`; the loss must not depend on the grouping: ``dapo``)."""
        buffered = self._buffered_inputs
        inputs = super()._prepare_inputs(generation_batch)
        if not (self.model.training and self.args.length_grouping and self.loss_type in GROUPING_LOSSES):
            return inputs
        if self._buffered_inputs is not buffered:  # TRL generated a new round
            self._buffered_inputs = grouped_by_length(self._buffered_inputs,
                                                      self.current_gradient_accumulation_steps)
        return trimmed(self._buffered_inputs[self._step % self.args.steps_per_generation])

    def update_forward(self, model):
        """``model``, or with ``compile_update`` its forward through ``torch.compile`` (dynamic shapes: the
        micro-batches' lengths vary; one compiled module per model, sharing its parameters). The
        update's passes (the policy's, the reference model's under ``disable_adapter``, the anchors')
        call it; sampling and saving see ``model`` as it is. With ``compile_scope: layers`` the model
        stays as it is here and :meth:`update_layers` compiles its decoder layers instead."""
        if (not self.args.compile_update or self.args.compile_scope != "model"
                or isinstance(model, torch._dynamo.eval_frame.OptimizedModule)):
            return model
        compiled = self._compiled.get(id(model))
        if compiled is None or compiled._orig_mod is not model:
            compiled = self._compiled[id(model)] = torch.compile(model, dynamic=True,
                                                                 backend=self.args.compile_backend)
        return compiled

    def update_layers(self, model):
        """With ``compile_update`` and ``compile_scope: layers``, a context in which ``model``'s decoder
        layers run their compiled forward (:func:`~physcene.train.decode.fuse.compiled_layers`: dynamic
        shapes, ``compile_backend``); else no change. The update's passes run in it; sampling, the fast
        decoder's own fused layers and saving run outside it."""
        if not (self.args.compile_update and self.args.compile_scope == "layers"):
            return contextlib.nullcontext()
        return compiled_layers(text_model(model), dynamic=True, backend=self.args.compile_backend)

    def _get_per_token_logps_and_entropies(self, model, input_ids, attention_mask, logits_to_keep,
                                           batch_size=None, compute_entropy=False, **kwargs):
        with self.update_layers(model):
            return self._update_pass(self.update_forward(model), input_ids, attention_mask, logits_to_keep,
                                     batch_size, compute_entropy, **kwargs)

    def _update_pass(self, model, input_ids, attention_mask, logits_to_keep, batch_size=None,
                     compute_entropy=False, **kwargs):
        """TRL's, with ``length_grouping`` over chunks of rows of similar length (a round's rows sorted
        by their last used column first: the reference model's pass), each chunk cut to the columns its
        rows use; the results padded back and returned in the rows' order. Image inputs go to TRL's. The
        policy's pass of a micro-batch under ``joint_anchor_pass`` takes its anchor rows along
        (:meth:`_joint_pass`). With ``compile_update`` the forwards are compiled (:meth:`update_forward`,
        :meth:`update_layers`)."""
        text_only = not any(v is not None for k, v in kwargs.items() if k != "compute_aux_loss")
        pending, self._joint_anchor = self._joint_anchor, None
        if pending is not None and text_only:
            return self._joint_pass(pending, model, input_ids, attention_mask, logits_to_keep,
                                    compute_entropy, kwargs)
        rows = input_ids.size(0)
        size = batch_size or rows
        if not self.args.length_grouping or not text_only:
            return super()._get_per_token_logps_and_entropies(
                model, input_ids, attention_mask, logits_to_keep, batch_size, compute_entropy, **kwargs)
        columns = torch.arange(1, input_ids.size(1) + 1, device=input_ids.device)
        used = (attention_mask.bool() * columns).amax(dim=1)  # each row's last used column, 1-based
        order = torch.argsort(used, descending=True, stable=True) if rows > size else None
        logps, entropies, aux = [], [], []
        for start in range(0, rows, size):
            index = order[start:start + size] if order is not None else slice(start, start + size)
            width = int(used[index].max())
            cut = min(input_ids.size(1) - width, logits_to_keep - 1)  # keep one completion column
            keep = input_ids.size(1) - cut
            lp, ent, ax = super()._get_per_token_logps_and_entropies(
                model, input_ids[index, :keep], attention_mask[index, :keep], logits_to_keep - cut,
                batch_size=size, compute_entropy=compute_entropy, **kwargs)
            logps.append(torch.nn.functional.pad(lp, (0, cut)))
            if ent is not None:
                entropies.append(torch.nn.functional.pad(ent, (0, cut)))
            if ax is not None:
                aux.append(ax)
        logps = torch.cat(logps)
        entropies = torch.cat(entropies) if entropies else None
        if order is not None:
            back = torch.argsort(order)
            logps = logps[back]
            entropies = entropies[back] if entropies is not None else None
        return logps, entropies, (torch.stack(aux).mean() if aux else None)

    def _joint_pass(self, pending: dict, model, input_ids, attention_mask, logits_to_keep: int,
                    compute_entropy: bool, kwargs: dict):
        """The policy's pass of a micro-batch with its anchor rows (``pending["rows"]``, the same prompts'
        columns) appended: each part right-padded to the wider of completion and anchor, one forward;
        the anchors' log-probabilities go to ``pending["logps"]``, the completions' are returned."""
        anchors = pending["rows"]
        anchor_width = anchors["anchor_ids"].size(1)
        width = max(logits_to_keep, anchor_width)
        pad = self._tokenizer.pad_token_id

        def widened(ids, mask, keep):
            return (torch.nn.functional.pad(ids, (0, width - keep), value=pad),
                    torch.nn.functional.pad(mask, (0, width - keep), value=0))

        ids, mask = widened(input_ids, attention_mask, logits_to_keep)
        anchor_ids, anchor_mask = widened(
            torch.cat([anchors["prompt_ids"], anchors["anchor_ids"]], dim=1),
            torch.cat([anchors["prompt_mask"], anchors["anchor_attention_mask"]], dim=1), anchor_width)
        logps, entropies, aux = self._get_per_token_logps_and_entropies(
            model, torch.cat([ids, anchor_ids]), torch.cat([mask, anchor_mask]), width,
            compute_entropy=compute_entropy, **kwargs)
        rows = input_ids.size(0)
        pending["logps"] = logps[rows:, :anchor_width]
        return (logps[:rows, :logits_to_keep],
                entropies[:rows, :logits_to_keep] if entropies is not None else None, aux)

    def _generate_and_score_completions(self, inputs):
        output = super()._generate_and_score_completions(inputs)
        for extension in self.extensions:
            extension.after_scoring(self, inputs, output)
        if self.anchor_alpha == 0.0:
            return output
        column = self.args.anchor_column
        rows = [tokenize_anchor(self._tokenizer, x.get(column) or "",
                                max_length=self.max_completion_length,
                                numeric_mask=self.args.anchor_numeric_mask,
                                keys=tuple(self.args.anchor_geometry_keys)) for x in inputs]
        device = self.accelerator.device
        output.update(padded_targets("anchor", rows, self._tokenizer.pad_token_id, device))
        # The G completions of a prompt carry the same anchor: one row per distinct (prompt, anchor) is
        # supervised (the others' loss mask is zero and they skip the CE's forward), and the round's
        # supervised tokens are kept so the micro-batches' terms add up to the mean over them.
        owner = torch.tensor(anchor_owners(inputs, column), dtype=torch.bool, device=device)
        output["anchor_loss_mask"] = output["anchor_loss_mask"] * owner[:, None]
        output["anchor_tokens"] = output["anchor_loss_mask"].sum().float()  # 0-d: not split with the rows
        return output

    def anchor_cross_entropy(self, model, inputs, logps: torch.Tensor | None = None) -> torch.Tensor:
        """Mean token NLL of the anchors given their prompts, over the supervised anchor tokens (scalar):
        the forward runs on the rows with a supervised token only (a prompt's other completions repeat
        its anchor with a zero loss mask, :func:`anchor_owners`). ``logps``: those rows' anchor
        log-probabilities, already computed (``joint_anchor_pass``, which passes those rows as ``inputs``):
        no forward of its own."""
        inputs = anchor_rows(inputs)
        if logps is None:
            nll, count = self.target_nll(model, inputs, "anchor")
        else:
            mask = inputs["anchor_loss_mask"].to(logps.dtype)
            nll, count = -(logps * mask).sum(), mask.sum()
        return nll / count.clamp(min=1.0)

    def target_nll(self, model, inputs, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(summed NLL, supervised token count) of the completions ``<name>_ids`` given their prompts,
        over ``<name>_loss_mask``."""
        target_ids = inputs[f"{name}_ids"]
        input_ids = torch.cat([inputs["prompt_ids"], target_ids], dim=1)
        attention_mask = torch.cat([inputs["prompt_mask"], inputs[f"{name}_attention_mask"]], dim=1)
        logps, _, _ = self._get_per_token_logps_and_entropies(model, input_ids, attention_mask,
                                                              target_ids.size(1))
        mask = inputs[f"{name}_loss_mask"].to(logps.dtype)
        return -(logps * mask).sum(), mask.sum()

    def training_step(self, model, inputs, num_items_in_batch=None):
        with ExitStack() as self._backward_scope:  # what _compute_loss sets for its backward too
            try:
                loss = super().training_step(model, inputs, num_items_in_batch)
            finally:
                self._backward_scope = None
        for extension in self.extensions:
            extension.after_backward(self, model)
        return loss

    def _compute_loss(self, model, inputs):
        # adapter_input_cast=False under mixed precision: each LoRA adapter reads its input as autocast
        # gives it (bf16) in the policy's and the anchors' forwards, instead of PEFT's cast to the
        # adapter's float32 weights that autocast undoes for the matmul; inside training_step the switch
        # lasts through the backward (a forward recomputed by gradient checkpointing reads them so too)
        uncast = self.args.adapter_inputs_uncast
        if uncast and self._backward_scope is not None:
            self._backward_scope.enter_context(disable_input_dtype_casting(model))
            return self._objective(model, inputs)
        with disable_input_dtype_casting(model, active=uncast):
            return self._objective(model, inputs)

    def _objective(self, model, inputs):
        """GRPO loss + α · CE(anchor) of a micro-batch, with the extensions' extra terms."""
        joint = None
        if self.args.joint_anchor_pass and self.anchor_alpha != 0.0 and "anchor_ids" in inputs \
                and bool(inputs["anchor_loss_mask"].any()):
            joint = self._joint_anchor = {"rows": anchor_rows(inputs), "logps": None}
        try:
            loss = super()._compute_loss(model, inputs)
        finally:
            self._joint_anchor = None
        for extension in self.extensions:
            extra = extension.extra_loss(self, model, inputs)
            if extra is not None:
                loss = loss + extra
        if self.anchor_alpha == 0.0 or "anchor_ids" not in inputs:
            return loss
        mode = "train" if self.model.training else "eval"
        count = inputs["anchor_loss_mask"].sum()
        has_anchor = count > 0
        if not has_anchor:
            ce = loss.new_zeros(())
        elif joint is not None and joint["logps"] is not None:
            ce = self.anchor_cross_entropy(model, joint["rows"], logps=joint["logps"])  # rows chosen once
        else:
            ce = self.anchor_cross_entropy(model, inputs)
        total = inputs.get("anchor_tokens")
        if mode == "train" and total is not None:
            # this micro-batch's share of the round's anchor tokens, per optimizer step of the round: the
            # steps' terms are the mean NLL over the round's distinct anchors, duplicates counted once
            steps_per_round = self.args.steps_per_generation / self.current_gradient_accumulation_steps
            weight = count / total.clamp(min=1.0) * steps_per_round
        else:
            # TRL divides its own loss by the accumulation steps (HF auto-scaling is off): do the same.
            weight = 1.0 / (self.current_gradient_accumulation_steps if mode == "train" else 1.0)
        stats = torch.stack([ce.detach() * has_anchor, has_anchor.float(), loss.detach()])
        stats = self.accelerator.reduce(stats, reduction="sum")
        if not bool(torch.isfinite(stats).all()):  # say which term broke (SkipNonFiniteSteps drops the step)
            logger.warning("step %d: non-finite loss term (anchor CE sum %s over %d ranks with anchors, "
                           "GRPO loss sum %s)", self.state.global_step + 1, stats[0].item(), int(stats[1]),
                           stats[2].item())
        if stats[1] > 0:
            self._metrics[mode]["anchor_ce"].append((stats[0] / stats[1]).item())
        return loss + self.anchor_alpha * ce * weight


def overruled_stop(pada_cfg) -> list[OverruledStop]:
    """``[OverruledStop]`` when ``pada.stop_overruled`` is set and groups are sampled under the
    constraint (else ``[]``)."""
    share = pada_cfg.get("stop_overruled")
    if share is None or not pada_cfg.get("constrained", False):
        return []
    return [OverruledStop(float(share), int(pada_cfg.get("stop_overruled_steps", 5)))]


def run_pada(cfg, variant: str | None = None, reward=None, callbacks=()) -> Path:
    """Train stage 2 (``variant`` or ``cfg.pada.variant``) from ``cfg.pada.model`` on ``cfg.pada.anchors``.

    Saves the LoRA adapter, tokenizer and run info to ``cfg.pada.output_dir``; resumes from its last
    checkpoint. ``reward`` (a ``physcene.reward.PhysicsReward``) replaces the default one on this rank's
    device, e.g. to share an engine.
    """
    if variant is not None and variant != cfg.pada.variant:
        # pada.output_dir interpolates ${pada.variant}: set it, don't just pass it along.
        cfg = OmegaConf.merge(cfg, {"pada": {"variant": variant}})
    variant = str(cfg.pada.variant)
    args = pada_arguments(cfg, variant)
    model_dir = Path(str(cfg.pada.model))
    info = read_run_info(model_dir)
    chat = bool(info.get("chat_format", cfg.model.chat_format))
    physics = bool(info.get("physics_conditioned", False))  # rollouts: asked for collision-free layouts
    state = PartialState()
    # refuse to resume an adapter on a base other than the one it was trained from (its weights' sha256)
    base_sha256 = base_checked(args.output_dir, model_dir, stage="pada", variant=variant, chat_format=chat,
                               physics_conditioned=physics,
                               base_model=str(model_dir.resolve())) if state.is_main_process else None
    records = load_records(str(cfg.pada.anchors), max_level=cfg.pada.get("max_level"))
    if not records:
        raise ValueError(f"no records in anchor file {cfg.pada.anchors!r}")
    if args.anchor_alpha > 0 and not any(r.get(args.anchor_column) for r in records):
        raise NoAnchorsError(f"{cfg.pada.anchors}: no record has a non-empty {args.anchor_column!r} "
                         f"(variant {variant})")
    dataset = training_dataset(records, chat_format=chat, columns=("anchor", "anchor_raw"),
                               physics="requested" if physics else None)
    dtype = str(cfg.model.dtype) if torch.cuda.is_available() else "float32"
    # Absolute path: PEFT records it as the adapter's base model, read back by generate().
    set_attention_kernels(cfg.model)  # cuDNN attention's backward NaNs on left-padded rows (torch 2.11)
    model = load_model(model_dir.resolve(), dtype=dtype, freeze_vision=bool(cfg.model.freeze_vision))
    tokenizer = load_tokenizer(model_dir)
    reward_fn = PhysicsRewardFunction(state.device, reward=reward, overrides=reward_overrides(cfg, variant))
    trainer = PADATrainer(
        model=model,
        reward_funcs=[reward_fn],
        args=args,
        train_dataset=dataset,
        processing_class=tokenizer,
        peft_config=lora_config(cfg.pada.lora),
        callbacks=[*callbacks, *time_budget_callbacks(cfg.pada), SkipNonFiniteSteps(),
                   *overruled_stop(cfg.pada)],
    )
    kl = cfg.pada.adaptive_kl
    if kl is not None and args.beta > 0:
        trainer.add_callback(AdaptiveKLCallback(trainer, target=float(kl.target), horizon=int(kl.horizon),
                                                min_beta=float(kl.min_beta), max_beta=float(kl.max_beta)))
    out = Path(args.output_dir)
    trainer.train(resume_from_checkpoint=last_complete_checkpoint(out))
    begin_final_save(trainer, out)
    trainer.save_model(str(out))
    if trainer.is_world_process_zero():
        tokenizer.save_pretrained(str(out))
        save_train_log(trainer, out)
        write_run_info(out, stage="pada", variant=variant, chat_format=chat, physics_conditioned=physics,
                       alpha=args.anchor_alpha,
                       eval_batch_size=int(cfg.eval.batch_size), steps=trainer.state.global_step,
                       stopped_by_budget=any(getattr(c, "stopped_early", False)
                                             for c in trainer.callback_handler.callbacks),
                       nonfinite_steps_dropped=skipped_steps(trainer),
                       stopped_off_grammar=next((c.stopped_at for c in trainer.callback_handler.callbacks
                                                 if isinstance(c, OverruledStop)), None),
                       base_model=str(model_dir.resolve()), base_sha256=base_sha256, n_records=len(records),
                       complete=True)
    return out
