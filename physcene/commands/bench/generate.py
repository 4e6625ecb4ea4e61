"""``physcene bench generate``: batched greedy generation, HF ``generate`` (each KV-cache mode) beside
the fast decoder, against the KV-cache-read limit.

    physcene bench generate --device cuda --config small --batch 512 --tokens 2048 --json
    physcene bench generate --device cuda --config small --batch 512 --tokens 2048 --constrained
    physcene bench generate --device cpu --config tiny --batch 2 --tokens 8
    physcene bench generate --device cuda --variants static static_compile fast fast+fused fast+fused+flex
    physcene bench generate --device cuda --batch 128 --lora 16 --variants fast+fused+cudnn \
        fast+fused+cudnn@merged

A randomly initialised model of ``configs/train_<config>.yaml`` (speed does not depend on the
weights) and a tokenizer trained the way the train code does (:mod:`physcene.train.tokenizer`, on 32
synthetic records), or with ``--model`` a trained checkpoint (a folder or an artifact's name) and its
tokenizer, generate ``--tokens`` new tokens for ``--batch`` CTRC prompts in one batch, with
``min_new_tokens`` so every variant decodes exactly the same number of steps. Timed with
:func:`physcene.commands.bench.timing.timed` (device synchronised, median of ``--repeat``, after one
call that also compiles ``static+compile`` and captures ``fast``'s CUDA graphs):
:func:`physcene.train.generate.generate_token_ids`, i.e. ``generate_with`` without the final text
decode. ``--constrained``: every variant decodes under the CTRC constraint (HF: the logits
processor; fast: the host check beside the GPU).

Each variant's token ids are compared with the first variant's (``static`` by default): greedy
decoding should give identical ids; in bf16 a different reduction order can flip a near-tie, so the
figure is the share of equal rows and the first differing step. Random weights put a near-tie at almost
every step (any change of reduction order then flips most rows); a trained model's greedy choice is
rarely that close, which is what ``--model`` measures.

The limit: a decoding step must read every row's KV cache up to its current length at least once,
``kv_floor_seconds`` = those bytes summed over the steps / the GPU's memory bandwidth (from
:data:`BANDWIDTH_TB_S` by the GPU's name, else measured with a large device copy: ``bandwidth_source``
says which); ``floor_ratio`` = floor / measured time (1.0 = at the limit). The fast decoder reads
the cache up to a bucketed length (``kv_bytes_read``: what it actually read).

``--lora R``: the model decodes through random LoRA adapters of rank R on the config's ``pada.lora``
projections (what PADA's rollouts decode through; B drawn, not PEFT's zeros); a fast variant written
``<cache>@merged`` decodes with them merged (``pada.merge_adapters``: one matmul per projection).
"""

from __future__ import annotations

import json
import time

import torch

from physcene.commands.bench.timing import BenchTarget, device_name, timed
from physcene.files import write_atomic

__all__ = ["BANDWIDTH_TB_S", "TARGET", "VARIANT_ALIASES", "memory_bandwidth", "random_weight_model"]

# a variant is a generation cache setting (physcene.train.generate.CACHE_MODES: HF generate's caches and
# the fast decoder's settings, physcene.train.decode.FAST_CACHES); older spellings kept
VARIANT_ALIASES = {"static+compile": "static_compile"}
MERGED = "@merged"  # a fast variant decoding a --lora model with its adapters merged

# peak memory bandwidth, TB/s, by a substring of torch.cuda.get_device_name (the first match wins)
BANDWIDTH_TB_S = {"H200": 4.8, "H100 PCIe": 2.0, "H100 NVL": 3.9, "H100": 3.35, "A100-SXM4-80GB": 2.039,
                  "A100 80GB PCIe": 1.935, "A100": 1.555, "L40S": 0.864, "A10G": 0.6, "RTX 4090": 1.008}


def add_arguments(parser) -> None:
    parser.add_argument("--config", default="small",
                        help="training config whose model.arch is built (tiny, small)")
    parser.add_argument("--model", default=None,
                        help="a trained checkpoint folder or an artifact's name (physcene artifacts list) "
                             "instead of random weights of --config")
    parser.add_argument("--batch", type=int, default=128, help="prompts, generated in one batch")
    parser.add_argument("--tokens", type=int, default=512,
                        help="new tokens per prompt (forced: no early EOS)")
    parser.add_argument("--variants", nargs="+", default=["static", "fast"],
                        help="generation caches to time in this process, the first the reference: dynamic, "
                             "static, static_compile (HF generate) or a fast decoder setting: fast with "
                             "+fused and/or +cudnn, +matmul, +flex (physcene.train.generate.CACHE_MODES)")
    parser.add_argument("--until-eos", action="store_true",
                        help="let rows stop at their EOS (at most --tokens) instead of forcing --tokens: "
                             "the rows a trained model writes, compared up to their EOS (forced past it, "
                             "a model's greedy choice is a near-tie at many steps; the timing figures then "
                             "count --tokens steps per row as a bound only)")
    parser.add_argument("--constrained", action="store_true",
                        help="decode every variant under the CTRC constraint")
    parser.add_argument("--dtype", default=None,
                        help="model dtype (default: bfloat16 on CUDA, float32 on CPU)")
    parser.add_argument("--cudnn-attention", action="store_true",
                        help="allow torch's cuDNN attention (off by default, as in training: "
                             "physcene.train.models.set_attention_kernels)")
    parser.add_argument("--lora", type=int, default=0, metavar="R",
                        help="decode through random LoRA adapters of rank R on the config's pada.lora "
                             "projections, as PADA's rollouts do; a variant <cache>@merged merges them")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None,
                        help="also write the figures to this JSON file after each variant (a run stopped "
                             "by a time limit keeps the variants it finished)")


def memory_bandwidth(device: torch.device) -> tuple[float, str]:
    """(bytes/s, source): the GPU's peak from :data:`BANDWIDTH_TB_S` by name, else a measured device
    copy of 1 GiB (read + write) — on CPU, always measured."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        for key, tb_s in BANDWIDTH_TB_S.items():
            if key in name:
                return tb_s * 1e12, f"table: {key} {tb_s} TB/s"
    return measured_bandwidth(device), "measured: device copy"


def measured_bandwidth(device: torch.device, size: int = 1 << 30) -> float:
    """Bytes/s of a ``size``-byte device copy (read + write counted), best of 5."""
    size = size if device.type == "cuda" else size // 8
    src = torch.empty(size, dtype=torch.uint8, device=device)
    dst = torch.empty_like(src)
    best = float("inf")
    for _ in range(5):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        dst.copy_(src)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        best = min(best, time.perf_counter() - start)
    return 2 * size / best


def kv_floor_bytes(model, batch: int, prompt_tokens: int, tokens: int) -> int:
    """KV bytes the decoding steps must read at least: step t reads each row's ``prompt + t`` columns."""
    from physcene.train.decode import text_model

    config = text_model(model).config
    heads = int(config.num_attention_heads)
    kv_heads = int(getattr(config, "num_key_value_heads", None) or heads)
    head_dim = int(getattr(config, "head_dim", None) or config.hidden_size // heads)
    column = 2 * int(config.num_hidden_layers) * kv_heads * head_dim * next(model.parameters()).element_size()
    columns = sum(prompt_tokens + t for t in range(1, tokens))  # steps after the prompt pass
    return batch * columns * column


def random_weight_model(cfg, records: list[dict], *, seed: int = 0, dtype: str = "bfloat16"):
    """(model, tokenizer): the training config ``cfg``'s architecture with random weights (on the CPU) and
    a digit-level bpe tokenizer trained on the first 32 records, whatever the config's kind (the prompt
    lengths of the figures in docs/training.md)."""
    from physcene.train.models import build_scratch_model
    from physcene.train.tokenizer import build_tokenizer

    texts = [r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]]
    tokenizer = build_tokenizer(texts, vocab_size=int(cfg.model.tokenizer.vocab_size))
    return build_scratch_model(cfg.model.arch, tokenizer, seed=seed, dtype=dtype), tokenizer


def run(args) -> dict:
    # transformers is heavy: imported when this target runs, not when the bench registry is built
    from physcene.artifacts import resolve_model
    from physcene.config import load_config
    from physcene.data import synthesize
    from physcene.train.generate import check_cache, generate_token_ids, load_for_generation
    from physcene.train.models import count_parameters

    if args.batch < 1 or args.tokens < 1:
        raise ValueError(f"--batch {args.batch} --tokens {args.tokens}: both must be >= 1")
    caches = {name: check_cache(VARIANT_ALIASES.get(name, name).removesuffix(MERGED))
              for name in args.variants}
    if any(name.endswith(MERGED) and not caches[name].startswith("fast") for name in args.variants):
        raise ValueError(f"a variant ending {MERGED} merges adapters for the fast decoder: use a fast cache")
    if args.lora < 0:
        raise ValueError(f"--lora {args.lora}: a rank >= 1, or 0 for none")
    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cuda.enable_cudnn_sdp(bool(args.cudnn_attention))
    dtype = args.dtype or ("bfloat16" if device.type == "cuda" else "float32")
    records = list(synthesize("train", n=max(32, args.batch), seed=args.seed))
    cfg = load_config(f"train_{args.config}", list(getattr(args, "overrides", [])))
    if args.model:
        model, tokenizer, _ = load_for_generation(resolve_model(args.model), device=device, dtype=dtype)
    else:
        model, tokenizer = random_weight_model(cfg, records, seed=args.seed, dtype=dtype)
        model = model.to(device).eval()
    if args.lora:
        model = _with_random_adapters(model, cfg, args.lora, args.seed)
    prompts = [r["prompt"] for r in records[:args.batch]]
    prompt_tokens = [len(tokenizer(p, add_special_tokens=False)["input_ids"]) for p in prompts]
    bandwidth, source = memory_bandwidth(device)
    floor_bytes = kv_floor_bytes(model, args.batch, max(prompt_tokens), args.tokens)
    result = {
        "target": "generate", "device": device_name(device), "config": args.config, "dtype": dtype,
        "model": args.model or "random weights",
        "parameters": count_parameters(model), "attention": model.config._attn_implementation,
        "batch": args.batch, "tokens": args.tokens, "prompt_tokens_max": max(prompt_tokens),
        "prompt_tokens_mean": sum(prompt_tokens) / len(prompt_tokens), "constrained": bool(args.constrained),
        "until_eos": bool(args.until_eos),
        "cudnn_attention": bool(args.cudnn_attention) and device.type == "cuda",
        "bandwidth_bytes_per_s": bandwidth, "bandwidth_source": source,
        "kv_floor_bytes": floor_bytes, "kv_floor_seconds": floor_bytes / bandwidth,
        "kv_floor_ms_per_step": 1e3 * floor_bytes / bandwidth / max(args.tokens - 1, 1),
        "variants": {},
    }
    reference = None
    for name in args.variants:
        cache, merge = caches[name], name.endswith(MERGED)
        report: list = []

        def call(tokens: int, cache=cache, report=report, merge=merge):
            report.clear()
            return generate_token_ids(model, tokenizer, prompts, max_new_tokens=tokens,
                                      min_new_tokens=None if args.until_eos else tokens,
                                      batch_size=args.batch, cache=cache, constrained=args.constrained,
                                      report=report, merge_lora=merge)

        try:
            start = time.perf_counter()
            ids = call(args.tokens)  # the first call: cache allocation, compilation, graph capture
            first = time.perf_counter() - start
            timing = timed(lambda: call(args.tokens), device, args.repeat, warmup=0)
            details = _fast_details(report)
            prefill = timed(lambda: call(1), device, args.repeat, warmup=1).seconds  # prompt pass + one token
        except torch.cuda.OutOfMemoryError as error:  # one variant too large: the others still report
            result["variants"][name] = {"cache": cache, "error": f"out of memory: {error}"[:300]}
            torch.cuda.empty_cache()
            continue
        seconds, steps = timing.seconds, max(args.tokens - 1, 1)
        row = result["variants"][name] = {
            "cache": cache, "seconds": seconds, "cpu_seconds": timing.cpu_seconds,
            "first_call_seconds": first,
            "ms_per_step": 1e3 * seconds / args.tokens,
            "decode_ms_per_step": 1e3 * max(seconds - prefill, 0.0) / steps if args.tokens > 1 else None,
            "prefill_seconds": prefill, "tokens_per_s": args.batch * args.tokens / seconds,
            "floor_ratio": result["kv_floor_seconds"] / seconds, **details,
        }
        if device.type == "cuda":
            row["max_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
            torch.cuda.reset_peak_memory_stats(device)
        if reference is None:
            reference, result["reference"] = ids, name
        row.update(_agreement(ids, reference, tokenizer.eos_token_id if args.until_eos else None))
        if args.out:
            write_atomic(args.out, json.dumps(result, indent=1) + "\n")
    timed_rows = [r for r in result["variants"].values() if "seconds" in r]
    base = result["variants"].get(result.get("reference"), {}).get("seconds")
    for row in timed_rows:
        row["speedup"] = base / row["seconds"] if base else None
    if args.out:
        write_atomic(args.out, json.dumps(result, indent=1) + "\n")
    return result


def _with_random_adapters(model, cfg, rank: int, seed: int):
    """``model`` with LoRA adapters of ``rank`` on ``cfg.pada.lora``'s projections, B drawn at the scale
    of A (PEFT starts B at zero: the adapters would be a no-op a merge could not be told from)."""
    from peft import get_peft_model

    from physcene.train.sft import lora_config

    lora = lora_config(cfg.pada.lora)
    lora.r, lora.lora_alpha = int(rank), 2 * int(rank)
    model = get_peft_model(model, lora)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lora_B" in name:
                param.copy_((torch.randn(param.shape, generator=generator) * 0.02).to(param.dtype))
    return model.eval()


def _fast_details(report: list) -> dict:
    """The fast decoder's own figures of the last timed call (empty for HF variants)."""
    if not report:
        return {}
    r = report[-1]
    return {"path": "cuda_graphs" if r.graphs else "eager", "fallback_reason": r.fallback_reason,
            "decode_steps": r.steps, "repairs": r.repairs, "merged_projections": r.merged_projections,
            "kv_bytes_read": r.kv_bytes_read,
            "host_check_seconds": r.seconds.get("host_check", 0.0),
            "decode_seconds": r.seconds.get("decode", 0.0),
            "fast_prefill_seconds": r.seconds.get("prefill", 0.0)}


def _agreement(ids: list[list[int]], reference: list[list[int]], eos: int | None = None) -> dict:
    """Equal token ids with the reference (rows cut after their first ``eos`` when given): all rows,
    share of rows, the first differing step of any row and its median over the differing rows."""
    if eos is not None:
        from physcene.train.decode import cut_at_eos

        ids, reference = ([cut_at_eos(row, {eos}) for row in rows] for rows in (ids, reference))
    equal = [a == b for a, b in zip(ids, reference)]
    first = [next((t for t, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
             for a, b, e in zip(ids, reference, equal) if not e]
    return {"equal": all(equal), "equal_rows": sum(equal) / max(len(equal), 1),
            "first_diff_step": min(first) if first else None,
            "first_diff_step_median": sorted(first)[len(first) // 2] if first else None}


def summary(r: dict) -> str:
    which = r["config"] if r.get("model", "random weights") == "random weights" else r["model"]
    lines = [f"device {r['device']}: {which} model ({r['parameters'] / 1e6:.2f} M parameters, "
             f"{r['dtype']}, {r['attention']} attention), {r['batch']} prompts "
             f"({r['prompt_tokens_mean']:.0f} tokens mean, {r['prompt_tokens_max']} max) x {r['tokens']} new "
             f"tokens{', CTRC-constrained' if r['constrained'] else ''}",
             f"KV-read floor {r['kv_floor_seconds']:.2f} s ({r['kv_floor_ms_per_step']:.2f} ms/step; "
             f"bandwidth {r['bandwidth_bytes_per_s'] / 1e12:.2f} TB/s, {r['bandwidth_source']})"]
    for name, v in r["variants"].items():
        if "error" in v:
            lines.append(f"{name:15s} {v['error']}")
            continue
        decode = "" if v["decode_ms_per_step"] is None else f" ({v['decode_ms_per_step']:.2f} ms decode only)"
        same = "same ids" if v["equal"] else (f"{v['equal_rows']:.0%} rows equal, first diff at step "
                                              f"{v['first_diff_step']}")
        path = f"  [{v['path']}{': ' + v['fallback_reason'] if v.get('fallback_reason') else ''}]" \
            if "path" in v else ""
        lines.append(f"{name:15s} {v['seconds']:7.2f} s {v['ms_per_step']:8.2f} ms/step{decode}  "
                     f"{v['tokens_per_s']:10.0f} tokens/s  floor/time {v['floor_ratio']:.2f}  "
                     f"{v['speedup'] or 0:5.2f}x  first call {v['first_call_seconds']:.1f} s  {same} as "
                     f"{r['reference']}{path}")
    return "\n".join(lines)


TARGET = BenchTarget("Batched greedy generation: HF generate (dynamic/static/static+compile) vs the fast "
                     "decoder, against the KV-cache-read limit", add_arguments, run, summary, repeat=(3, 2))
