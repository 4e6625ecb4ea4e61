"""What turning torch's cuDNN attention off costs (``model.cudnn_attention: false``; CUDA only).

    python benchmarks/attention_kernel_timing.py runs/small/sft runs/small/anchors_l3.jsonl.gz [--out FILE]

Times, with the cuDNN SDPA kernel allowed and forbidden: (1) the forward + backward of a PADA anchor
micro-batch (8 rows of [left-padded prompt | anchor], bf16 autocast) at 2240 tokens (64 past a multiple
of 128: cuDNN's NaN case) and 2176 / 2304 (multiples of 128), with whether every gradient came out
finite; (2) sampled generation of 256 new tokens for 64 prompts (dynamic cache). Medians of repeats.
"""

from __future__ import annotations

import argparse
import gzip
import json
import statistics
import time

import torch

from physcene.train.models import load_model, load_tokenizer


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def timed(fn, repeats: int) -> tuple[float, object]:
    fn()  # warm-up (kernel selection, allocator)
    _sync()
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        _sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("anchors")
    parser.add_argument("--out")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--new-tokens", type=int, default=256)
    parser.add_argument("--lengths", default="2176,2240,2304")
    args = parser.parse_args()
    device = args.device
    model = load_model(args.model, dtype="bfloat16").to(device)
    tok = load_tokenizer(args.model)
    opener = gzip.open if args.anchors.endswith(".gz") else open
    with opener(args.anchors, "rt") as f:
        prompts = [json.loads(line)["prompt"] for _, line in zip(range(64), f)]
    for p in model.parameters():
        p.requires_grad_(True)
    gen = torch.Generator(device=device).manual_seed(0)
    vocab = model.config.vocab_size
    name = torch.cuda.get_device_name() if device.startswith("cuda") else device
    result = {"device": name, "torch": torch.__version__, "train_step": {}, "generate": {}}
    for length in (int(v) for v in args.lengths.split(",")):
        ids = torch.randint(0, vocab, (8, length), device=device, generator=gen)
        mask = torch.ones(8, length, dtype=torch.long, device=device)
        for b in range(8):
            mask[b, :4 * b] = 0  # rows 1-7 left-padded by 4-28 tokens

        def step(ids=ids, mask=mask):
            model.zero_grad(set_to_none=True)
            with torch.autocast(device.split(":")[0], dtype=torch.bfloat16):
                logits = model(input_ids=ids, attention_mask=mask).logits
            loss = torch.nn.functional.cross_entropy(logits[:, :-1].float().reshape(-1, logits.size(-1)),
                                                     ids[:, 1:].reshape(-1), reduction="none")
            (loss * mask[:, 1:].reshape(-1)).mean().backward()
            return all(bool(torch.isfinite(p.grad).all()) for p in model.parameters() if p.grad is not None)

        for cudnn in (True, False):
            torch.backends.cuda.enable_cudnn_sdp(cudnn)
            seconds, finite = timed(step, args.repeats)
            result["train_step"][f"{length}_cudnn_{'on' if cudnn else 'off'}"] = {
                "ms": round(1e3 * seconds, 2), "finite_grad": finite}
            print(length, "cudnn", cudnn, f"{1e3 * seconds:.2f} ms", "finite", finite, flush=True)
    model.zero_grad(set_to_none=True)
    tok.padding_side = "left"
    encoded = tok(prompts, return_tensors="pt", padding=True)
    batch = {k: encoded[k].to(device) for k in ("input_ids", "attention_mask")}
    for cudnn in (True, False):
        torch.backends.cuda.enable_cudnn_sdp(cudnn)

        def sample():
            with torch.no_grad():
                return model.generate(**batch, max_new_tokens=args.new_tokens, min_new_tokens=args.new_tokens,
                                      do_sample=True,
                                      pad_token_id=tok.pad_token_id)

        seconds, _ = timed(sample, max(1, args.repeats // 3))
        result["generate"][f"cudnn_{'on' if cudnn else 'off'}"] = {
            "s": round(seconds, 3), "ms_per_step": round(1e3 * seconds / args.new_tokens, 2)}
        print("generate cudnn", cudnn, f"{seconds:.3f} s", flush=True)
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
