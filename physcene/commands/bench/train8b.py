"""``physcene bench train8b --stage sft|pada|generate --out FIG.json``: the paper's backbone at its size.

A random-weight ``Qwen3VLForConditionalGeneration`` of Qwen3-VL-8B-Instruct's exact dimensions
(:data:`physcene.train.qwen3_vl.QWEN3_VL_8B_TEXT` / ``_VISION``, 8.77 B parameters) is built in bf16
directly on the GPU (``torch.device("cuda")`` context: the weights are created and initialised there,
no CPU init), with a ChatML tokenizer trained on CTRC records (``physcene.data.synthesize``). The
figures use real records through the chat template, concatenated and cut to a fixed length, so every
step computes the same number of tokens.

- ``sft``: full fine-tune, vision tower frozen, gradient checkpointing, AdamW (torch's, states in the
  parameters' dtype: bf16, as ``physcene train sft --config qwen3_vl_8b`` runs), per-device batch 2
  rows of ``--seq-len`` tokens. On N GPUs under ``accelerate launch`` with an FSDP config
  (``configs/accelerate/fsdp_shard_grad_op.yaml``: SHARD_GRAD_OP, ZeRO-2's sharding of gradients and
  optimizer states). An out-of-memory step is a figure (``fits: false`` and the memory it held).
- ``pada``: LoRA r 16 / α 32 on the language model (``configs/train/qwen3_vl_8b.yaml``'s ``pada.lora``),
  G = 4, per-device batch 4 completions of ``--completion-len`` tokens: generation
  (:func:`physcene.train.generate.generate_token_ids`, sampled, EOS held off to the fixed length), the
  SDF reward of the batch (:class:`physcene.reward.PhysicsReward` on the records' reference
  completions: a random model writes nothing that parses) and the update (policy forward/backward,
  reference forward without the adapter, anchor CE forward/backward: PADATrainer's passes, by a hand
  loop) are timed apart. N GPUs: DDP (``configs/accelerate/multi_gpu.yaml``).
- ``generate``: s/scene of batched generation of ``--completion-len`` tokens per scene.

Every stage reports s/step (median of ``--steps`` after one warm-up), peak memory
(``torch.cuda.max_memory_allocated``) and mean memory (sampled every 50 ms by a thread) per GPU.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path

import torch

from physcene.commands.bench.timing import BenchTarget

__all__ = ["TARGET", "MemorySampler"]

STAGES = ("sft", "pada", "generate")
GB = 1024 ** 3


class MemorySampler:
    """Mean and peak of ``torch.cuda.memory_allocated`` while the ``with`` block runs (a thread reads it
    every ``interval`` s; the peak is the allocator's own, reset on entry)."""

    def __init__(self, device: torch.device, interval: float = 0.05):
        self.device, self.interval = device, interval
        self.samples: list[int] = []
        self._stop = threading.Event()

    def _run(self):
        while not self._stop.is_set():
            self.samples.append(torch.cuda.memory_allocated(self.device))
            time.sleep(self.interval)

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            self._stop.set()
            self._thread.join()

    def figures(self) -> dict:
        if self.device.type != "cuda":
            return {"peak_gb": None, "mean_gb": None}
        return {"peak_gb": torch.cuda.max_memory_allocated(self.device) / GB,
                "mean_gb": statistics.fmean(self.samples) / GB if self.samples else None,
                "peak_reserved_gb": torch.cuda.max_memory_reserved(self.device) / GB}


def add_arguments(parser) -> None:
    parser.add_argument("--stage", choices=STAGES, required=True, help="what to measure")
    parser.add_argument("--out", required=True, help="write the figures to this JSON file")
    parser.add_argument("--size", choices=("8b", "tiny"), default="8b",
                        help="8b: Qwen3-VL-8B's dimensions (default); tiny: the CPU test size (a smoke run)")
    parser.add_argument("--steps", type=int, default=3, help="timed steps after one warm-up (default 3)")
    parser.add_argument("--seq-len", type=int, default=None,
                        help="sft: tokens per row (default: the qwen3_vl_8b config's sft.max_length, 8192)")
    parser.add_argument("--completion-len", type=int, default=None,
                        help="pada/generate: tokens per completion (default: pada.max_completion_length, "
                             "4096, for pada; 2048 for generate)")
    parser.add_argument("--batch", type=int, default=None,
                        help="per-device batch (default: sft.per_device_batch_size 2, "
                             "pada.per_device_batch_size 4, eval.batch_size 16)")
    parser.add_argument("--cache", default="dynamic", help="generation KV cache (physcene.train.generate)")


def _config():
    from physcene.commands.train import training_config

    return training_config("qwen3_vl_8b", ["model.path=unused"])


def _records(n: int) -> list[dict]:
    from physcene.data import synthesize

    return list(synthesize("train", n, seed=0))


def build_model(size: str, device: torch.device, records: list[dict]):
    """(model in bf16 on ``device`` with its vision tower frozen, ChatML tokenizer, build seconds)."""
    from transformers import Qwen3VLForConditionalGeneration

    from physcene.train.models import freeze_vision_tower
    from physcene.train.qwen3_vl import (
        QWEN3_VL_8B_TEXT,
        QWEN3_VL_8B_VISION,
        TINY_TEXT,
        TINY_VISION,
        chatml_tokenizer,
        qwen3_vl_config,
    )

    start = time.perf_counter()
    texts = [t for r in records for t in (r["prompt"], r["completion"])]
    tokenizer = chatml_tokenizer(texts, vocab_size=1024)
    text, vision = (QWEN3_VL_8B_TEXT, QWEN3_VL_8B_VISION) if size == "8b" else (TINY_TEXT, TINY_VISION)
    config = qwen3_vl_config(tokenizer, text, vision)
    torch.manual_seed(0)
    with torch.device(device):  # weights created and initialised where they train
        model = Qwen3VLForConditionalGeneration._from_config(config, dtype=torch.bfloat16)
    freeze_vision_tower(model)
    model.config.use_cache = False
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return model, tokenizer, time.perf_counter() - start


def fixed_rows(tokenizer, records: list[dict], rows: int, length: int, offset: int = 0) -> torch.Tensor:
    """``rows`` x ``length`` token ids: records' conversations through the chat template, end to end,
    cut to ``length`` (no padding: every position is computed)."""
    out = []
    k = offset
    for _ in range(rows):
        ids: list[int] = []
        while len(ids) < length:
            r = records[k % len(records)]
            ids += tokenizer.apply_chat_template(
                [{"role": "user", "content": r["prompt"]}, {"role": "assistant", "content": r["completion"]}],
                tokenize=True, return_dict=False)
            k += 1
        out.append(ids[:length])
    return torch.tensor(out)


def _timed_steps(step, steps: int, device: torch.device) -> tuple[list[dict], dict]:
    """One warm-up then ``steps`` calls of ``step() -> dict of seconds``; (per-step figures, memory)."""
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    step()
    sync()
    figures = []
    with MemorySampler(device) as memory:
        for _ in range(steps):
            sync()
            start = time.perf_counter()
            parts = step()
            sync()
            figures.append({"step_s": time.perf_counter() - start, **parts})
    return figures, memory.figures()


def _measured(step, info: dict, steps: int, device: torch.device) -> dict:
    """``info`` with :func:`_timed_steps`' figures and memory (``fits: true``), or with the error and
    the memory held when a step ran out of memory (``fits: false``): not fitting is a figure too."""
    try:
        figures, memory = _timed_steps(step, steps, device)
    except torch.cuda.OutOfMemoryError as exc:
        peak = torch.cuda.max_memory_allocated(device) / GB
        return {**info, "fits": False, "error": str(exc).splitlines()[0], "peak_gb_at_oom": peak}
    return {**info, "fits": True, "figures": figures, **memory}


def _sft(args, accelerator, model, tokenizer, records) -> dict:
    cfg = _config()
    batch = args.batch or int(cfg.sft.per_device_batch_size)
    length = args.seq_len or int(cfg.sft.max_length)
    model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})
    model.train()
    model = accelerator.prepare(model)
    trainable = [p for p in model.parameters() if p.requires_grad]
    betas = (float(cfg.sft.adam_beta1), float(cfg.sft.adam_beta2))
    optimizer = torch.optim.AdamW(trainable, lr=float(cfg.sft.learning_rate), betas=betas)
    optimizer = accelerator.prepare(optimizer)
    ids = fixed_rows(tokenizer, records, batch, length, offset=batch * accelerator.process_index)
    ids = ids.to(accelerator.device)

    def step():
        loss = model(input_ids=ids, labels=ids).loss
        accelerator.backward(loss)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        return {"loss": float(loss.detach())}

    info = {"per_device_batch": batch, "seq_len": length, "tokens_per_step_per_gpu": batch * length,
            "optimizer": "torch AdamW, states in the parameter dtype (bf16)",
            "gradient_checkpointing": True, "sharding": accelerator.distributed_type.value}
    return _measured(step, info, args.steps, accelerator.device)


def _lora_model(model):
    from peft import get_peft_model

    from physcene.train.sft import lora_config

    model = get_peft_model(model, lora_config(_config().pada.lora))
    return model


def _pada(args, accelerator, model, tokenizer, records) -> dict:
    from physcene.reward import PhysicsReward, RewardConfig
    from physcene.train.generate import generate_token_ids

    cfg = _config()
    batch = args.batch or int(cfg.pada.per_device_batch_size)
    group = int(cfg.pada.num_generations)
    length = args.completion_len or int(cfg.pada.max_completion_length)
    if batch % group:
        raise ValueError(f"--batch {batch} is not a multiple of G = {group}")
    alpha, beta = float(cfg.pada.alpha), float(cfg.pada.beta)
    model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})
    model.enable_input_require_grads()
    model = accelerator.prepare(_lora_model(model))
    policy = accelerator.unwrap_model(model)
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad],
                                  lr=float(cfg.pada.learning_rate))
    reward = PhysicsReward(RewardConfig(device=str(accelerator.device)))
    rank, counter = accelerator.process_index, [0]
    tokenizer.padding_side = "left"

    def logps(m, ids, mask, n):
        logits = m(input_ids=ids, attention_mask=mask, logits_to_keep=n + 1).logits[:, :-1].float()
        return torch.log_softmax(logits, -1).gather(-1, ids[:, -n:, None]).squeeze(-1)

    def step():
        k = (rank * 1000 + counter[0] * batch // group) % len(records)
        counter[0] += 1
        chosen = [records[(k + i) % len(records)] for i in range(batch // group)]
        prompts = [r["prompt"] for r in chosen for _ in range(group)]
        cuda = accelerator.device.type == "cuda"
        sync = (lambda: torch.cuda.synchronize(accelerator.device)) if cuda else (lambda: None)
        start = time.perf_counter()
        policy.eval()
        completion = generate_token_ids(policy, tokenizer, prompts, chat_format=True, max_new_tokens=length,
                                        min_new_tokens=length, batch_size=batch, do_sample=True,
                                        cache=args.cache, seed=counter[0])
        sync()
        generate_s = time.perf_counter() - start
        start = time.perf_counter()
        scores = reward.score([r["completion"] for r in chosen for _ in range(group)]).rewards
        sync()
        reward_s = time.perf_counter() - start
        start = time.perf_counter()
        policy.train()
        chat = [tokenizer.apply_chat_template([{"role": "user", "content": p}], tokenize=False,
                                              add_generation_prompt=True) for p in prompts]
        enc = tokenizer(chat, return_tensors="pt", padding=True, add_special_tokens=False)
        enc = enc.to(accelerator.device)
        comp = torch.tensor(completion, device=accelerator.device)
        ids = torch.cat([enc["input_ids"], comp], 1)
        mask = torch.cat([enc["attention_mask"], torch.ones_like(comp)], 1)
        anchor = fixed_rows(tokenizer, chosen, batch // group, length).repeat_interleave(group, 0)
        anchor_ids = torch.cat([enc["input_ids"], anchor.to(accelerator.device)], 1)
        new = logps(model, ids, mask, length)
        with torch.no_grad(), policy.disable_adapter():
            ref = logps(model, ids, mask, length)
        rewards = torch.as_tensor(scores, dtype=torch.float32, device=accelerator.device).view(-1, group)
        advantage = (rewards - rewards.mean(1, keepdim=True)) / (rewards.std(1, keepdim=True) + 1e-4)
        advantage = advantage.view(-1, 1)
        kl = torch.exp(ref - new) - (ref - new) - 1
        grpo = (-(torch.exp(new - new.detach()) * advantage) + beta * kl).mean()
        ce = -logps(model, anchor_ids, torch.ones_like(anchor_ids), length).mean()
        accelerator.backward(grpo + alpha * ce)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        sync()
        return {"generate_s": generate_s, "reward_s": reward_s, "update_s": time.perf_counter() - start,
                "prompt_tokens": int(enc["input_ids"].shape[1])}

    info = {"per_device_batch": batch, "G": group, "completion_len": length, "cache": args.cache,
            "lora": {"r": int(cfg.pada.lora.r), "alpha": int(cfg.pada.lora.alpha)},
            "trainable_params": sum(p.numel() for p in model.parameters() if p.requires_grad)}
    return _measured(step, info, args.steps, accelerator.device)


def _generate(args, accelerator, model, tokenizer, records) -> dict:
    from physcene.train.generate import generate_token_ids

    cfg = _config()
    batch = args.batch or int(cfg.eval.batch_size)
    length = args.completion_len or 2048
    model.config.use_cache = True
    model.eval()
    rank, counter = accelerator.process_index, [0]

    def step():
        k = rank * 1000 + counter[0] * batch
        counter[0] += 1
        prompts = [records[(k + i) % len(records)]["prompt"] for i in range(batch)]
        generate_token_ids(model, tokenizer, prompts, chat_format=True, max_new_tokens=length,
                           min_new_tokens=length, batch_size=batch, cache=args.cache)
        return {}

    figures, memory = _timed_steps(step, args.steps, accelerator.device)
    for f in figures:
        f["s_per_scene"] = f["step_s"] / batch
    return {"per_device_batch": batch, "completion_len": length, "cache": args.cache, "fits": True,
            "figures": figures, **memory}


def run(args) -> dict:
    from accelerate import Accelerator
    from accelerate.utils import gather_object

    accelerator = Accelerator()
    device = accelerator.device
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    records = _records(64)
    start = time.perf_counter()
    model, tokenizer, build_s = build_model(args.size, device, records)
    params = sum(p.numel() for p in model.parameters())
    frozen = sum(p.numel() for p in model.parameters() if not p.requires_grad)
    measure = {"sft": _sft, "pada": _pada, "generate": _generate}[args.stage]
    result = measure(args, accelerator, model, tokenizer, records)
    result.update(rank=accelerator.process_index, build_s=build_s, wall_s=time.perf_counter() - start,
                  device=torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu")
    per_gpu = gather_object([result])
    summary = {"stage": args.stage, "size": args.size, "gpus": accelerator.num_processes,
               "distributed": accelerator.distributed_type.value, "params": params, "vision_frozen": frozen,
               "torch": torch.__version__, "per_gpu": per_gpu,
               "argv": sys.argv[1:], "world_size_env": int(os.environ.get("WORLD_SIZE", "1"))}
    fitted = [r for r in per_gpu if r.get("fits")]
    if len(fitted) == len(per_gpu):
        for key in ("step_s", "generate_s", "reward_s", "update_s", "s_per_scene"):
            values = [f[key] for r in per_gpu for f in r["figures"] if key in f]
            if values:
                summary[f"median_{key}"] = statistics.median(values)
        summary["peak_gb_max"] = max((r["peak_gb"] or 0) for r in per_gpu)
        summary["mean_gb_max"] = max((r["mean_gb"] or 0) for r in per_gpu)
    if accelerator.is_main_process:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(summary, indent=1))
    accelerator.wait_for_everyone()
    return summary


def summary(result: dict) -> str:
    lines = [f"train8b {result['stage']} ({result['size']}, {result['gpus']} process(es), "
             f"{result['distributed']}): {result['params'] / 1e9:.2f} B parameters"]
    for key in ("median_step_s", "median_generate_s", "median_reward_s", "median_update_s",
                "median_s_per_scene"):
        if key in result:
            lines.append(f"  {key[7:]}: {result[key]:.3f} s")
    if "peak_gb_max" in result:
        lines.append(f"  peak {result['peak_gb_max']:.1f} GB, mean {result['mean_gb_max']:.1f} GB per GPU")
    for r in result["per_gpu"]:
        if not r.get("fits"):
            lines.append(f"  rank {r['rank']}: does not fit ({r['error']}; "
                         f"{r['peak_gb_at_oom']:.1f} GB held)")
    return "\n".join(lines)


TARGET = BenchTarget("Qwen3-VL-8B's dimensions, random bf16 weights on the GPU: SFT, PADA or generation "
                     "steps (s/step, peak and mean memory per GPU; --out JSON)",
                     add_arguments, run, summary, repeat=(1, 1))
