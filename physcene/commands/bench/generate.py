"""``physcene bench generate``: batched greedy generation with each KV-cache mode.

    physcene bench generate --device cuda --config small --batch 128 --tokens 512 --json
    physcene bench generate --device cpu --config tiny --batch 2 --tokens 8
    physcene bench generate --device cuda --variants dynamic static     # a subset

A randomly initialised model of ``configs/train_<config>.yaml`` (speed does not depend on the
weights) and a tokenizer trained the way the train code does (:mod:`physcene.train.tokenizer`, on 32
synthetic records) generate ``--tokens`` new tokens for ``--batch`` CTRC prompts in one batch, with
``min_new_tokens`` so every variant decodes exactly the same number of steps. Timed with
:func:`physcene.commands.bench.timing.timed` (device synchronised, median of ``--repeat``, one warm-up call
that also compiles ``static_compile``): :func:`physcene.train.generate.generate_token_ids`, i.e.
``generate_with`` without the final text decode. Each variant's token ids are compared with the
first variant's (``dynamic`` by default): greedy decoding should give identical ids; in bf16 the
different attention reductions of a static cache can flip a near-tie, so the figure is the share of
equal rows and the first differing step.
"""

from __future__ import annotations

import time

import torch

from physcene.commands.bench.timing import BenchTarget, device_name, timed

__all__ = ["TARGET", "VARIANT_CACHE"]

VARIANT_CACHE = {"dynamic": "dynamic", "static": "static", "static+compile": "static_compile"}


def add_arguments(parser) -> None:
    parser.add_argument("--config", default="small",
                        help="training config whose model.arch is built (tiny, small)")
    parser.add_argument("--batch", type=int, default=128, help="prompts, generated in one batch")
    parser.add_argument("--tokens", type=int, default=512,
                        help="new tokens per prompt (forced: no early EOS)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANT_CACHE), choices=list(VARIANT_CACHE),
                        help="cache variants to time in this process (the first is the reference)")
    parser.add_argument("--dtype", default=None,
                        help="model dtype (default: bfloat16 on CUDA, float32 on CPU)")
    parser.add_argument("--seed", type=int, default=0)


def run(args) -> dict:
    # transformers is heavy: imported when this target runs, not when the bench registry is built
    from physcene.config import load_config
    from physcene.data import synthesize
    from physcene.train.generate import generate_token_ids
    from physcene.train.models import build_scratch_model, count_parameters
    from physcene.train.tokenizer import build_tokenizer

    if args.batch < 1 or args.tokens < 1:
        raise ValueError(f"--batch {args.batch} --tokens {args.tokens}: both must be >= 1")
    device = torch.device(args.device)
    dtype = args.dtype or ("bfloat16" if device.type == "cuda" else "float32")
    cfg = load_config(f"train_{args.config}", list(getattr(args, "overrides", [])))
    records = list(synthesize("train", n=max(32, args.batch), seed=args.seed))
    tokenizer = build_tokenizer([r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]],
                                vocab_size=int(cfg.model.tokenizer.vocab_size))
    model = build_scratch_model(cfg.model.arch, tokenizer, seed=args.seed, dtype=dtype).to(device).eval()
    prompts = [r["prompt"] for r in records[:args.batch]]
    prompt_tokens = [len(tokenizer(p, add_special_tokens=False)["input_ids"]) for p in prompts]
    result = {
        "target": "generate", "device": device_name(device), "config": args.config, "dtype": dtype,
        "parameters": count_parameters(model), "attention": model.config._attn_implementation,
        "batch": args.batch, "tokens": args.tokens, "prompt_tokens_max": max(prompt_tokens),
        "prompt_tokens_mean": sum(prompt_tokens) / len(prompt_tokens), "variants": {},
    }
    reference = None
    for name in args.variants:
        cache = VARIANT_CACHE[name]

        def call(tokens: int, cache=cache):
            return generate_token_ids(model, tokenizer, prompts, max_new_tokens=tokens, min_new_tokens=tokens,
                                      batch_size=args.batch, cache=cache)

        start = time.perf_counter()
        ids = call(args.tokens)  # the first call: cache allocation, compilation for static_compile
        first = time.perf_counter() - start
        timing = timed(lambda: call(args.tokens), device, args.repeat, warmup=0)
        seconds, cpu_seconds = timing.seconds, timing.cpu_seconds
        prefill = timed(lambda: call(1), device, args.repeat, warmup=1).seconds  # prompt pass + one token
        steps = max(args.tokens - 1, 1)
        row = result["variants"][name] = {
            "cache": cache, "seconds": seconds, "cpu_seconds": cpu_seconds, "first_call_seconds": first,
            "ms_per_step": 1e3 * seconds / args.tokens,
            "decode_ms_per_step": 1e3 * max(seconds - prefill, 0.0) / steps if args.tokens > 1 else None,
            "prefill_seconds": prefill, "tokens_per_s": args.batch * args.tokens / seconds,
        }
        if device.type == "cuda":
            row["max_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
            torch.cuda.reset_peak_memory_stats(device)
        if reference is None:
            reference, result["reference"] = ids, name
        row.update(_agreement(ids, reference))
    base = result["variants"][result["reference"]]["seconds"]
    for row in result["variants"].values():
        row["speedup"] = base / row["seconds"]
    return result


def _agreement(ids: list[list[int]], reference: list[list[int]]) -> dict:
    """Equal token ids with the reference: all rows, share of rows, first differing step (or None)."""
    equal = [a == b for a, b in zip(ids, reference)]
    first = [next((t for t, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
             for a, b, e in zip(ids, reference, equal) if not e]
    return {"equal": all(equal), "equal_rows": sum(equal) / max(len(equal), 1),
            "first_diff_step": min(first) if first else None}


def summary(r: dict) -> str:
    lines = [f"device {r['device']}: {r['config']} model ({r['parameters'] / 1e6:.2f} M parameters, "
             f"{r['dtype']}, "
             f"{r['attention']} attention), {r['batch']} prompts ({r['prompt_tokens_mean']:.0f} tokens mean, "
             f"{r['prompt_tokens_max']} max) x {r['tokens']} new tokens"]
    for name, v in r["variants"].items():
        decode = "" if v["decode_ms_per_step"] is None else f" ({v['decode_ms_per_step']:.2f} ms decode only)"
        same = "same ids" if v["equal"] else (f"{v['equal_rows']:.0%} rows equal, first diff at step "
                                              f"{v['first_diff_step']}")
        lines.append(f"{name:15s} {v['ms_per_step']:8.2f} ms/step{decode}  "
                     f"{v['tokens_per_s']:10.0f} tokens/s  "
                     f"{v['speedup']:5.2f}x  first call {v['first_call_seconds']:.1f} s  {same} as "
                     f"{r['reference']}")
    return "\n".join(lines)


TARGET = BenchTarget("Batched greedy generation: dynamic vs static vs static+compile KV cache",
                     add_arguments, run, summary, repeat=(3, 2))
