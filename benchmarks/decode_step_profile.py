"""Where a fast-decoder step's time goes (CUDA): kernels per step and the GPU time of each.

    python benchmarks/decode_step_profile.py [--config small] [--batch 512] [--read 1024] [--out FILE]

Builds a random-weight model of ``--config`` (bf16), prefills ``--batch`` CTRC prompts into a
:class:`~physcene.train.decode.FastDecoder`, moves every row to ``--read`` cache columns and then,
for each setting (``fast``, ``fast+fused``, ``fast+fused+flex``, ...):

- the median of 50 replayed CUDA-graph steps (the path rollouts take), milliseconds;
- 5 eager steps under ``torch.profiler``: kernels launched per step, the summed GPU time of those
  kernels per step, and the 15 kernels with the most GPU time.

The summed kernel time against the replayed step's time says whether the step is bound by what the
kernels do (equal) or by the gaps between them (the replayed step longer).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import time

import torch


def _model(config: str, batch: int):
    from physcene.commands.bench.generate import random_weight_model
    from physcene.config import load_config
    from physcene.data import synthesize

    records = list(synthesize("train", n=max(32, batch), seed=0))
    model, tokenizer = random_weight_model(load_config(f"train_{config}"), records, seed=0, dtype="bfloat16")
    model = model.cuda().eval()
    prompts = [records[b % len(records)]["prompt"] for b in range(batch)]
    tokenizer.padding_side = "left"
    enc = tokenizer(prompts, return_tensors="pt", padding=True, add_special_tokens=False)
    return model, tokenizer, enc


def profile(cache: str, model, tokenizer, enc, read: int) -> dict:
    from physcene.train.decode import FAST_CACHES, FastDecoder, fused_layers, sampling_mode, text_model

    attention, fuse = FAST_CACHES[cache]
    batch, prompt = enc["input_ids"].shape
    decoder = FastDecoder(model, batch=batch, length=max(read, prompt) + 64, attention=attention, fuse=fuse)
    with sampling_mode(model, attention), torch.no_grad():
        decoder.configure(max_new_tokens=64, min_new_tokens=64, eos=[tokenizer.eos_token_id],
                          pad=tokenizer.pad_token_id, sampling=False, warpers=None, keep_output=True)
        decoder.prefill(enc["input_ids"].cuda(), enc["attention_mask"].cuda())
        decoder.positions.fill_(read - 1)
        decoder._furthest = read - 2  # every step reads the bucket holding column `read`
        with fused_layers(text_model(model)) if fuse else contextlib.nullcontext():
            replayed = []
            for _ in range(53):
                decoder.positions.fill_(read - 1)
                decoder._furthest = read - 2
                torch.cuda.synchronize()
                start = time.perf_counter()
                decoder.run_step()
                torch.cuda.synchronize()
                replayed.append(time.perf_counter() - start)
            decoder.want_graphs = False
            for _ in range(2):
                decoder.positions.fill_(read - 1)
                decoder.run_step()
            torch.cuda.synchronize()
            steps = 5
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
                for _ in range(steps):
                    decoder.positions.fill_(read - 1)
                    decoder._furthest = read - 2
                    decoder.run_step()
                torch.cuda.synchronize()
    kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    by_name: dict[str, list[float]] = {}
    for e in kernels:
        by_name.setdefault(e.name, []).append(e.device_time)
    top = sorted(by_name.items(), key=lambda kv: -sum(kv[1]))[:15]
    return {
        "cache": cache, "batch": batch, "read_columns": read,
        "graph_step_ms": 1e3 * statistics.median(replayed[3:]),
        "kernels_per_step": len(kernels) / steps,
        "kernel_ms_per_step": sum(e.device_time for e in kernels) / steps / 1e3,
        "top": [{"kernel": name[:90], "calls_per_step": len(t) / steps, "ms_per_step": sum(t) / steps / 1e3}
                for name, t in top],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="small")
    parser.add_argument("--batch", type=int, nargs="+", default=[512])
    parser.add_argument("--read", type=int, default=1024)
    parser.add_argument("--caches", nargs="+", default=["fast", "fast+fused", "fast+fused+cudnn"])
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    torch.backends.cuda.enable_cudnn_sdp(False)  # as training and bench generate set it
    rows = []
    for batch in args.batch:
        model, tokenizer, enc = _model(args.config, batch)
        for cache in args.caches:
            row = profile(cache, model, tokenizer, enc, args.read)
            rows.append(row)
            print(f"{cache:18s} batch {batch:4d} read {args.read}: graph step {row['graph_step_ms']:.3f} ms, "
                  f"{row['kernels_per_step']:.0f} kernels/step, "
                  f"kernel time {row['kernel_ms_per_step']:.3f} ms")
            for k in row["top"][:10]:
                print(f"    {k['ms_per_step']:.3f} ms  x{k['calls_per_step']:.0f}  {k['kernel']}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"device": torch.cuda.get_device_name(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
