"""``physcene bench pada``: whole PADA optimiser steps (generation, reward, update) with the real
trainer, on a randomly initialised model of a training config.

    physcene bench pada --device cuda --config small --tokens 2304 --steps 3 --json
    physcene bench pada --device cuda --config small --caches fast dynamic --constrained
    physcene bench pada --device cuda --config small --caches fast+fused+cudnn --merge-adapters off on
    physcene bench pada --device cuda --config small --caches fast+fused+cudnn --joint-anchor-pass off on
    physcene bench pada --device cuda --config small --caches fast+fused+cudnn --adapter-input-cast on off
    physcene bench pada --device cpu --config tiny --tokens 16 --set pada.global_batch_size=4 \\
        pada.per_device_batch_size=2 pada.num_generations=2

The settings are ``configs/train_<config>.yaml``'s ``pada`` section (global batch, G, LoRA, precision;
``--set key=value`` overrides), with ``pada.max_completion_length = --tokens`` and every
rollout forced to that length (``min_new_tokens``: a random model would stop anywhere). The anchors
are the synthetic records' reference completions. Each ``--caches`` entry trains ``1 + --steps``
optimiser steps (the first, which captures graphs and allocates, is not counted) and reports the
median seconds per step split into generation (``time/generate_s``; of it, the constraint's host check
``host_check_s``, with the counters of where it went: ``constraint_scan_s``, ``vocabulary_scans``,
``refused_draws``), reward (the reward function's calls) and the rest (log-probabilities, loss, backward,
optimiser: ``update``). ``--merge-adapters off
on`` times each fast cache also with the LoRA adapters merged for decoding (``pada.merge_adapters``;
row ``<cache> merged``), and ``--joint-anchor-pass off on`` each with the anchors scored in the policy's
forward (``pada.joint_anchor_pass``; row ``... joint``), and ``--adapter-input-cast on off`` each with
the LoRA adapters reading their bf16 inputs uncast (``pada.adapter_input_cast=false``; row ``...
uncast``), and ``--compile-update off on`` each with the update's forwards compiled
(``pada.compile_update``; row ``... compiled``), one after the other in the same process.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from physcene.commands.bench.timing import BenchTarget, device_name

__all__ = ["TARGET"]

# the pada switches timed in turn (--merge-adapters ..., each "on" / "off"): pada key -> (the word a row's
# name gets, the value that gets it); merge_adapters first (a row of a cache other than fast skips "on")
SWITCHES = {"merge_adapters": ("merged", "on"), "joint_anchor_pass": ("joint", "on"),
            "adapter_input_cast": ("uncast", "off"), "compile_update": ("compiled", "on")}


# the constraint's counters of a round (train.constrained_rollouts logs them), medians of the timed steps
CONSTRAINT_LOGS = {"constraint_scan_s": "time/constraint_scan_s",
                   "vocabulary_scans": "constraint/vocabulary_scans",
                   "refused_draws": "constraint/refused_draws"}


def add_arguments(parser) -> None:
    parser.add_argument("--config", default="small", help="training config (tiny, small)")
    parser.add_argument("--tokens", type=int, default=2304,
                        help="rollout length (pada.max_completion_length), forced unless --until-eos")
    parser.add_argument("--model", default=None,
                        help="the policy's base: a trained checkpoint folder or an artifact's name "
                             "(physcene artifacts list) instead of random weights of --config")
    parser.add_argument("--until-eos", action="store_true",
                        help="rollouts stop at their EOS (at most --tokens): the lengths a trained policy "
                             "writes (with random weights every rollout runs to --tokens anyway)")
    parser.add_argument("--steps", type=int, default=3, help="timed optimiser steps (after one warm-up step)")
    parser.add_argument("--caches", nargs="+", default=["fast"],
                        help="pada.cache values timed one after the other (dynamic, static, static_compile, "
                             "fast, fast+fused, fast+fused+flex, ...: physcene.train.generate.CACHE_MODES)")
    parser.add_argument("--constrained", action="store_true", help="sample under the CTRC constraint")
    parser.add_argument("--merge-adapters", nargs="+", choices=["off", "on"], default=["off"],
                        help="decode each fast cache's groups with the LoRA adapters as they are (off) "
                             "and/or merged into a copy of the weights (on: pada.merge_adapters, row "
                             "'<cache> merged')")
    parser.add_argument("--joint-anchor-pass", nargs="+", choices=["off", "on"], default=["off"],
                        help="score each micro-batch's anchors in their own forward (off) and/or in the "
                             "policy's (on: pada.joint_anchor_pass, row '<cache> joint'), in turn")
    parser.add_argument("--adapter-input-cast", nargs="+", choices=["on", "off"], default=["on"],
                        help="the LoRA adapters' inputs cast to their float32 weights as PEFT does (on) "
                             "and/or read as bf16 autocast gives them (off: pada.adapter_input_cast=false, "
                             "row '<cache> uncast'), in turn")
    parser.add_argument("--compile-update", nargs="+", choices=["off", "on"], default=["off"],
                        help="the update's forwards eager (off) and/or through torch.compile with dynamic "
                             "shapes (on: pada.compile_update, row '<cache> compiled'; the warm-up step "
                             "pays the compile), in turn")
    parser.add_argument("--variant", default="pada", choices=["pada", "pada_star", "grpo"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", default=None, metavar="DIR",
                        help="profile the last timed step (torch.profiler, CPU and CUDA) and write its "
                             "tables to DIR/pada_<cache>.txt: the trainer's parts (generation, the "
                             "log-probabilities, the anchor CE, backward) and the operators with the most "
                             "GPU and host time")
    parser.add_argument("--set", dest="config_set", nargs="+", default=[], metavar="KEY=VALUE",
                        help="overrides of the training config (pada.global_batch_size=4 ...)")


def run(args) -> dict:
    from physcene.config import load_config
    from physcene.train.generate import check_cache

    if args.tokens < 1 or args.steps < 1:
        raise ValueError(f"--tokens {args.tokens} --steps {args.steps}: both must be >= 1")
    for cache in args.caches:  # a misspelt one fails here, not after the others' minutes
        check_cache(cache)
    device = torch.device(args.device)
    if device.type == "cpu" and torch.cuda.is_available():
        raise ValueError("--device cpu: the trainer takes the GPU of this machine; run on a CPU-only one")
    result = {"target": "pada", "device": device_name(device), "config": args.config, "variant": args.variant,
              "model": args.model or "random weights", "tokens": args.tokens,
              "until_eos": bool(args.until_eos), "constrained": bool(args.constrained), "caches": {}}
    runs = [(cache, dict(zip(SWITCHES, values))) for cache in args.caches
            for values in itertools.product(*(dict.fromkeys(getattr(args, key)) for key in SWITCHES))
            if values[0] == "off" or cache.startswith("fast")]  # merge_adapters: the fast decoder's
    if not runs:
        raise ValueError("--merge-adapters on merges for the fast decoder: give a fast cache in --caches")
    for cache, settings in runs:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = load_config(f"train_{args.config}", [
                f"output_dir={tmp}", f"pada.max_completion_length={args.tokens}", f"pada.cache={cache}",
                f"pada.constrained={str(bool(args.constrained)).lower()}", "pada.save_steps=1000000",
                *(f"pada.{key}={str(value == 'on').lower()}" for key, value in settings.items()),
                "pada.logging_steps=1", *args.config_set, *getattr(args, "overrides", [])])
            name = cache + "".join(f" {word}" for key, (word, marked) in SWITCHES.items()
                                   if settings[key] == marked)
            row = result["caches"][name] = _time_steps(cfg, args, device, name)
        result.update({k: row.pop(k) for k in ("global_batch", "num_generations", "parameters")})
    return result


def _time_steps(cfg, args, device: torch.device, name: str) -> dict:
    """The timed steps of one row (``name``: its name in the result, which names its profile files too)."""
    from transformers import TrainerCallback

    from physcene.artifacts import resolve_model
    from physcene.commands.bench.generate import random_weight_model
    from physcene.data import synthesize
    from physcene.reward.trl import PhysicsRewardFunction
    from physcene.train.config import pada_arguments
    from physcene.train.models import count_parameters, load_model, load_tokenizer, set_attention_kernels
    from physcene.train.pada import PADATrainer
    from physcene.train.records import training_dataset
    from physcene.train.sft import lora_config

    steps = 1 + args.steps
    pada_args = pada_arguments(cfg, args.variant)
    pada_args.max_steps = steps
    if not args.until_eos:
        pada_args.generation_kwargs = {**(pada_args.generation_kwargs or {}), "min_new_tokens": args.tokens}
    records = list(synthesize("train", n=max(64, pada_args.per_device_train_batch_size * 4), seed=args.seed))
    for r in records:
        r["anchor"] = r["anchor_raw"] = r["completion"]
    dtype = str(cfg.model.dtype) if device.type == "cuda" else "float32"
    set_attention_kernels(cfg.model)
    if args.model:
        path = resolve_model(args.model)
        model, tokenizer = load_model(path, dtype=dtype), load_tokenizer(path)
    else:
        model, tokenizer = random_weight_model(cfg, records, seed=args.seed, dtype=dtype)
    reward = PhysicsRewardFunction(device)
    reward_seconds: list[float] = []

    def timed_reward(*a, **kw):
        start = time.perf_counter()
        try:
            return reward(*a, **kw)
        finally:
            reward_seconds.append(time.perf_counter() - start)

    timed_reward.__name__ = getattr(reward, "__name__", "physics_reward")
    step_seconds: list[float] = []
    profiler = None

    class StepClock(TrainerCallback):
        def on_step_begin(self, *_, **__):
            nonlocal profiler
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            if args.profile and len(step_seconds) == steps - 1:  # the last step
                activities = [torch.profiler.ProfilerActivity.CPU]
                if device.type == "cuda":
                    activities.append(torch.profiler.ProfilerActivity.CUDA)
                profiler = torch.profiler.profile(activities=activities)
                profiler.__enter__()
            self.start = time.perf_counter()

        def on_step_end(self, *_, **__):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            step_seconds.append(time.perf_counter() - self.start)
            if profiler is not None:
                profiler.__exit__(None, None, None)

    trainer = PADATrainer(model=model, reward_funcs=[timed_reward], args=pada_args,
                          train_dataset=training_dataset(records, chat_format=False,
                                                         columns=("anchor", "anchor_raw")),
                          processing_class=tokenizer, peft_config=lora_config(cfg.pada.lora),
                          callbacks=[StepClock()])
    if args.profile:
        _label_parts(trainer)
    with contextlib.redirect_stdout(sys.stderr):  # the trainer's log lines: stdout is the figures' (--json)
        trainer.train()
    history = trainer.state.log_history
    generate = [h["time/generate_s"] for h in history if "time/generate_s" in h]
    lengths = [(h["completions/mean_length"], h["completions/max_length"]) for h in history
               if "completions/mean_length" in h]
    graphs = [h["time/decode_graphs"] for h in history if "time/decode_graphs" in h]
    merged = [h["time/decode_merged_projections"] for h in history if "time/decode_merged_projections" in h]
    host_check = [h["time/decode_host_check_s"] for h in history if "time/decode_host_check_s" in h]
    # where the constraint's check went: rows that fell back to the vocabulary, and the draws it refused
    constraint = {key: [h[log] for h in history if log in h] for key, log in CONSTRAINT_LOGS.items()}
    rounds = max(len(reward_seconds) // max(len(step_seconds), 1), 1)  # reward calls per step
    per_step_reward = [sum(reward_seconds[i * rounds:(i + 1) * rounds]) for i in range(len(step_seconds))]
    timed = slice(1, None)  # the first step captures graphs and allocates
    total = statistics.median(step_seconds[timed])
    gen = statistics.median(generate[timed]) if len(generate) > 1 else None
    rew = statistics.median(per_step_reward[timed])
    row = {"seconds_per_step": total, "generate_s": gen, "reward_s": rew,
           # the fast decoder's constraint check on the host, of generate_s (0: no constraint; None: HF)
           "host_check_s": statistics.median(host_check[timed]) if len(host_check) > 1 else None,
           **{key: statistics.median(values[timed]) for key, values in constraint.items() if len(values) > 1},
           "update_s": total - (gen or 0.0) - rew, "steps_timed": len(step_seconds) - 1,
           "first_step_s": step_seconds[0], "all_steps_s": step_seconds,
           "completion_tokens_mean": statistics.mean(m for m, _ in lengths) if lengths else None,
           "completion_tokens_max": max(x for _, x in lengths) if lengths else None,
           "merged_projections": int(max(merged, default=0)),
           "path": ("cuda_graphs" if graphs and min(graphs) == 1.0 else "eager") if graphs else "hf_generate",
           "global_batch": pada_args.per_device_train_batch_size * pada_args.gradient_accumulation_steps,
           "num_generations": pada_args.num_generations, "parameters": count_parameters(model),
           # the adapters read their inputs uncast only under mixed precision (a GPU's bf16)
           "adapter_inputs_uncast": pada_args.adapter_inputs_uncast,
           "compile_update": pada_args.compile_update}
    if device.type == "cuda":
        row["max_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
        torch.cuda.reset_peak_memory_stats(device)
    if profiler is not None:
        # the timings first: reading a long step's events back takes minutes, and a command's time
        # limit that cuts it still leaves the step's figures
        stem = "pada_" + name.replace(" ", "_")
        timing = Path(args.profile) / f"{stem}.json"
        timing.parent.mkdir(parents=True, exist_ok=True)
        timing.write_text(json.dumps(row, indent=1) + "\n")
        row["profile"] = _write_profile(profiler, Path(args.profile) / f"{stem}.txt", device)
    return row


# the trainer's methods a profiled step labels (record_function ranges named "pada/<method>")
PROFILED_PARTS = ("_generate", "_generate_and_score_completions", "_get_per_token_logps_and_entropies",
                  "_compute_loss", "anchor_cross_entropy", "training_step")


def _label_parts(trainer) -> None:
    """Wrap :data:`PROFILED_PARTS` of ``trainer`` (instance attributes: this trainer only) and its
    accelerator's ``backward`` and optimiser step in ``record_function`` ranges."""
    import functools

    def labelled(name, method):
        @functools.wraps(method)
        def call(*a, **kw):
            with torch.profiler.record_function(f"pada/{name}"):
                return method(*a, **kw)
        return call

    for name in PROFILED_PARTS:
        setattr(trainer, name, labelled(name, getattr(trainer, name)))
    trainer.accelerator.backward = labelled("backward", trainer.accelerator.backward)


def _write_profile(profiler, path: Path, device: torch.device) -> dict:
    """The profiled step's tables to ``path``; returns the labelled parts' host and GPU seconds."""
    events = profiler.key_averages()
    gpu = "cuda" if device.type == "cuda" else "cpu"
    parts = {e.key.removeprefix("pada/"): {"cpu_s": e.cpu_time_total / 1e6,
                                           "gpu_s": getattr(e, "device_time_total", 0.0) / 1e6,
                                           "calls": e.count}
             for e in events if e.key.startswith("pada/")}
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        f.write("The trainer's parts (host time includes what they wait for):\n")
        for name, v in sorted(parts.items(), key=lambda kv: -kv[1]["cpu_s"]):
            f.write(f"  {name:40s} {v['calls']:5d} calls  host {v['cpu_s']:8.3f} s  "
                    f"gpu {v['gpu_s']:8.3f} s\n")
        for title, key in ((f"Operators by {gpu} self time", f"self_{gpu}_time_total"),
                           ("Operators by host self time", "self_cpu_time_total")):
            f.write(f"\n{title}:\n")
            f.write(events.table(sort_by=key, row_limit=40, max_name_column_width=70) + "\n")
    return {"file": str(path), "parts": parts}


def summary(r: dict) -> str:
    lines = [f"device {r['device']}: {r['config']} ({r['parameters'] / 1e6:.2f} M parameters), "
             f"{r['variant']}, "
             f"global batch {r['global_batch']}, G = {r['num_generations']}, rollouts of "
             f"{'at most ' if r.get('until_eos') else ''}{r['tokens']} tokens"
             f"{'' if r.get('model', 'random weights') == 'random weights' else ', policy ' + r['model']}"
             f"{', CTRC-constrained' if r['constrained'] else ''}"]
    for cache, v in r["caches"].items():
        gen = "-" if v["generate_s"] is None else f"{v['generate_s']:.2f}"
        mean = v.get("completion_tokens_mean")
        lengths = ("" if mean is None
                   else f"; rollouts {mean:.0f} tokens mean, {v['completion_tokens_max']:.0f} max")
        lines.append(f"{cache:22s} {v['seconds_per_step']:7.2f} s/step (generation {gen} s, reward "
                     f"{v['reward_s']:.2f} s, update {v['update_s']:.2f} s; median of {v['steps_timed']}; "
                     f"first step {v['first_step_s']:.1f} s{lengths}) [{v['path']}]")
    return "\n".join(lines)


TARGET = BenchTarget("Whole PADA optimiser steps (generation, reward, update) with the real trainer",
                     add_arguments, run, summary, repeat=(1, 1))
