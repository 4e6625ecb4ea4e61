"""Stage 1: supervised fine-tuning on CTRC prompt/completion pairs with TRL's ``SFTTrainer``.

The loss covers the completion only (``completion_only_loss=True``: TRL masks the prompt tokens of
prompt/completion datasets). Full fine-tuning by default; ``sft.lora`` switches to LoRA adapters.
The global batch is ``per_device_batch_size x world_size x gradient_accumulation_steps``; the
accumulation steps are derived from ``global_batch_size`` for the world size the run sees, so one
config serves 1 GPU, N GPUs and the CPU test. A run resumes from the newest complete
``checkpoint-*`` in its output directory (:func:`~physcene.train.checkpoints.last_complete_checkpoint`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from pathlib import Path

import torch
import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf
from peft import LoraConfig
from transformers import TrainerCallback
from trl import SFTConfig, SFTTrainer

from physcene.train.checkpoints import last_complete_checkpoint
from physcene.train.models import (
    TrainingSetupError,
    begin_final_save,
    language_model_targets,
    prepare_model_and_tokenizer,
    save_train_log,
    set_attention_kernels,
    torch_dtype,
    write_run_info,
)
from physcene.train.records import load_records, model_prompt, training_dataset

__all__ = ["SHARD_BYTES", "SkipNonFiniteSteps", "accumulation_steps", "lora_config", "run_sft",
           "shard_weights", "skipped_steps"]

logger = logging.getLogger(__name__)

SHARD_BYTES = 48 * 2**20
"""The largest weights file of a saved SFT model. A bigger checkpoint (``medium``: 118 MiB in bf16) is
written in shards, so each shard travels to a GPU machine in a call of its own (64 MiB per call, the
working tree included) and stays under a git host's file limit (``physcene.artifacts.MAX_FILE_BYTES``)."""


def shard_weights(model, out: str | Path, max_bytes: int = SHARD_BYTES) -> list[str]:
    """Rewrite ``out/model.safetensors`` as ``model-0000k-of-0000n.safetensors`` shards of at most
    ``max_bytes`` (+ ``model.safetensors.index.json``, which ``from_pretrained`` reads) when it is
    bigger; a smaller file stays as it is. Returns the weights files' names."""
    out = Path(out)
    single = out / "model.safetensors"
    if not single.is_file():
        raise FileNotFoundError(f"{single}: no weights to shard")
    if single.stat().st_size <= max_bytes:
        return [single.name]
    single.unlink()  # save_pretrained keeps a single file beside new shards; the loader would prefer it
    model.save_pretrained(str(out), max_shard_size=int(max_bytes))
    return sorted(p.name for p in out.glob("model-*-of-*.safetensors"))


class TimeBudget(TrainerCallback):
    """Stop training ``seconds`` of wall clock after ``on_train_begin``, or at the Unix time
    ``stop_at`` (whichever comes first), saving a checkpoint.

    The run then ends like a finished one (final model written); running the same command again
    resumes from that checkpoint and goes on toward ``max_steps``/the epochs. This is how a long
    run fits into jobs with a wall-clock limit (``sft.max_minutes``, ``pada.max_minutes``). ``stop_at``
    (``sft.stop_at``, ``pada.stop_at``) also counts what comes before training (data synthesis,
    tokenisation, a model's load), which ``seconds`` does not: a job killed at its limit would lose
    the steps since the last checkpoint and the final save.
    """

    def __init__(self, seconds: float | None = None, *, stop_at: float | None = None):
        if seconds is None and stop_at is None:
            raise ValueError("TimeBudget needs seconds or stop_at")
        self.seconds = None if seconds is None else float(seconds)
        self.stop_at = None if stop_at is None else float(stop_at)
        self.start = None
        self.stopped_early = False

    def on_train_begin(self, args, state, control, **kwargs):
        self.start = time.monotonic()

    def on_step_end(self, args, state, control, **kwargs):
        running = None if self.start is None else time.monotonic() - self.start
        spent = self.seconds is not None and running is not None and running > self.seconds
        late = self.stop_at is not None and time.time() > self.stop_at
        if self._agreed(spent or late, args):
            self.stopped_early = True
            control.should_training_stop = True
            control.should_save = True
        return control

    @staticmethod
    def _agreed(stop: bool, args) -> bool:
        """Under DDP every rank must stop at the same step (a rank that goes on would wait forever
        in the next all-reduce), so the ranks' clocks are OR-ed: one small all-reduce per step."""
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return stop
        flag = torch.tensor([1.0 if stop else 0.0], device=args.device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        return bool(flag.item())


def nonfinite_gradients(model) -> tuple[list[str], int]:
    """(names of the parameters whose gradient holds a NaN or an inf, how many gradients there are);
    one device sync for all of them."""
    named = [(n, p.grad) for n, p in model.named_parameters() if p.grad is not None]
    if not named:
        return [], 0
    finite = torch.stack([torch.isfinite(g).all() for _, g in named]).tolist()
    return [n for (n, _), ok in zip(named, finite) if not ok], len(named)


class SkipNonFiniteSteps(TrainerCallback):
    """Drop an optimizer step whose (all-reduced, clipped) gradients hold a NaN or an inf.

    Clipping by a NaN norm turns every gradient into NaN, and one such AdamW step writes NaN into
    every trained weight: the run goes on, logging losses, while the model it saves generates
    nothing parsable (a ``small`` PADA* run did this at its last step, 15). Here every gradient is set
    to None before ``optimizer.step()``, which AdamW then skips parameter by parameter; the LR
    schedule still advances. Under DDP all ranks see the same reduced gradients and drop the same
    step. The dropped steps are in ``self.steps`` (and the run's ``physcene_run.json``). DeepSpeed
    keeps gradients in its own buffers (``p.grad`` is None), so there this check sees nothing.
    """

    def __init__(self):
        self.steps: list[int] = []

    def on_pre_optimizer_step(self, args, state, control, model=None, **kwargs):
        if model is None:
            return control
        bad, total = nonfinite_gradients(model)
        if bad:
            for p in model.parameters():
                p.grad = None
            self.steps.append(state.global_step + 1)
            logger.warning("step %d: non-finite gradient in %d of %d tensors (first: %s), optimizer step "
                           "dropped", state.global_step + 1, len(bad), total, ", ".join(bad[:3]))
        return control


def skipped_steps(trainer) -> list[int]:
    """The optimizer steps a trainer's :class:`SkipNonFiniteSteps` dropped."""
    guards = [c for c in trainer.callback_handler.callbacks if isinstance(c, SkipNonFiniteSteps)]
    return [s for c in guards for s in c.steps]


def time_budget_callbacks(stage_cfg) -> list[TimeBudget]:
    """``[TimeBudget]`` when the stage config sets ``max_minutes`` or ``stop_at`` (a Unix time), else
    ``[]``."""
    minutes, stop_at = stage_cfg.get("max_minutes"), stage_cfg.get("stop_at")
    if not minutes and stop_at is None:
        return []
    return [TimeBudget(60.0 * float(minutes) if minutes else None,
                       stop_at=None if stop_at is None else float(stop_at))]


def world_size() -> int:
    """Processes of this run (accelerate/torchrun set WORLD_SIZE; 1 otherwise)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def accumulation_steps(global_batch: int, per_device: int, world: int) -> int:
    """Gradient accumulation steps that make ``per_device x world x steps == global_batch``."""
    per_step = per_device * world
    steps = max(1, math.ceil(global_batch / per_step))
    if steps * per_step != global_batch:
        raise TrainingSetupError(
            f"global_batch_size={global_batch} is not a multiple of per_device_batch_size={per_device} x "
            f"world_size={world}")
    return steps


def lora_config(lora: DictConfig | None) -> LoraConfig | None:
    """A peft ``LoraConfig`` from ``{r, alpha, dropout, target_modules}``, or None for full fine-tuning;
    the adapters go on the language model's modules of those names only (never a vision tower's)."""
    if lora is None:
        return None
    return LoraConfig(r=int(lora.r), lora_alpha=int(lora.alpha), lora_dropout=float(lora.get("dropout", 0.0)),
                      target_modules=language_model_targets(lora.target_modules), task_type="CAUSAL_LM")


def _precision(cfg: DictConfig) -> dict:
    # Mixed precision only where the hardware does it; CPU tests train in fp32.
    if not torch.cuda.is_available():
        return {"bf16": False, "fp16": False, "use_cpu": True}
    return {"bf16": torch.cuda.is_bf16_supported(), "fp16": not torch.cuda.is_bf16_supported()}


def sft_arguments(cfg: DictConfig) -> SFTConfig:
    """The ``SFTConfig`` of ``cfg.sft`` (paper stage 1 for ``qwen3_vl_8b``)."""
    s = cfg.sft
    deepspeed = OmegaConf.to_container(s.deepspeed, resolve=True) if s.deepspeed is not None else None
    return SFTConfig(
        output_dir=str(s.output_dir),
        num_train_epochs=float(s.epochs),
        max_steps=int(s.max_steps),
        learning_rate=float(s.learning_rate),
        lr_scheduler_type=str(s.lr_scheduler_type),
        warmup_steps=float(s.warmup_steps),
        adam_beta1=float(s.adam_beta1),
        adam_beta2=float(s.adam_beta2),
        weight_decay=float(s.weight_decay),
        per_device_train_batch_size=int(s.per_device_batch_size),
        gradient_accumulation_steps=accumulation_steps(int(s.global_batch_size), int(s.per_device_batch_size),
                                                       world_size()),
        max_length=int(s.max_length),
        completion_only_loss=True,
        packing=False,
        save_steps=int(s.save_steps),
        save_total_limit=2,
        logging_steps=int(s.logging_steps),
        report_to="none",
        seed=int(cfg.seed),
        deepspeed=deepspeed,
        dataloader_num_workers=0,
        # processes for TRL's tokenizing/labelling map over the records (None: one process)
        dataset_num_proc=int(s.dataset_num_proc) if s.get("dataset_num_proc") else None,
        # every trainable weight takes part in every forward (the 8B vision tower is frozen, so DDP
        # skips it): the unused-parameter search would only add a graph traversal per step
        ddp_find_unused_parameters=False,
        gradient_checkpointing=bool(s.get("gradient_checkpointing", False)),
        **_length_grouping(bool(s.get("group_by_length", False))),
        **_precision(cfg),
    )


def _length_grouping(enabled: bool) -> dict:
    """Batches of similar length (``sft.group_by_length``): completions run from ~500 to ~3,700 tokens,
    so random batches pad to their longest row; grouping cuts the padded tokens a step computes.

    transformers 5 spells it ``train_sampling_strategy="group_by_length"``, 4.x ``group_by_length=True``.
    """
    if not enabled:
        return {}
    fields = {f.name for f in dataclasses.fields(SFTConfig)}
    if "train_sampling_strategy" in fields:
        return {"train_sampling_strategy": "group_by_length"}
    return {"group_by_length": True}


def run_sft(cfg: DictConfig, callbacks=()) -> Path:
    """Train stage 1 per ``cfg`` and save the model, tokenizer and run info to ``cfg.sft.output_dir``."""
    out = Path(cfg.sft.output_dir)
    records = load_records(str(cfg.data.train), seed=int(cfg.seed), max_level=cfg.data.get("max_level"))
    if not records:
        raise TrainingSetupError(f"no training records in {cfg.data.train!r} "
                                 f"(max_level={cfg.data.get('max_level')})")
    physics = "reference" if cfg.model.get("physics_conditioned", False) else None
    texts = [t for r in records for t in (model_prompt(r, physics), r["completion"])]
    set_attention_kernels(cfg.model)
    model, tokenizer = prepare_model_and_tokenizer(cfg, texts=texts, out_dir=out)
    chat = bool(cfg.model.chat_format)
    trainer = SFTTrainer(
        model=model,
        args=sft_arguments(cfg),
        train_dataset=training_dataset(records, chat_format=chat, physics=physics),
        processing_class=tokenizer,
        peft_config=lora_config(cfg.sft.lora),
        callbacks=[*callbacks, *time_budget_callbacks(cfg.sft), SkipNonFiniteSteps()],
    )
    trainer.train(resume_from_checkpoint=last_complete_checkpoint(out))
    if cfg.sft.lora is not None:
        # Later stages load one plain checkpoint: fold the adapters into the weights.
        trainer.model = trainer.model.merge_and_unload()
    if cfg.model.source == "scratch":
        trainer.model.to(torch_dtype(str(cfg.model.dtype)))  # small: a 52 MiB bf16 checkpoint
    begin_final_save(trainer, out)
    trainer.save_model(str(out))
    if trainer.is_world_process_zero():
        if cfg.model.source == "scratch" and (out / "model.safetensors").is_file():
            shard_weights(trainer.model, out)  # medium: 118 MiB -> 3 shards (a pretrained model keeps HF's)
        tokenizer.save_pretrained(str(out))
        save_train_log(trainer, out)
        write_run_info(out, stage="sft", chat_format=chat, physics_conditioned=physics is not None,
                       config=str(cfg.name), n_records=len(records),
                       eval_batch_size=int(cfg.eval.batch_size), steps=trainer.state.global_step,
                       stopped_by_budget=any(getattr(c, "stopped_early", False)
                                             for c in trainer.callback_handler.callbacks),
                       nonfinite_steps_dropped=skipped_steps(trainer),
                       base_model=str(cfg.model.path) if cfg.model.source == "pretrained" else "scratch",
                       **({"init_from": str(cfg.model.init_from)} if cfg.model.get("init_from") else {}))
    return out
