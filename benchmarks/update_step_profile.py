"""Where a PADA update's GPU time goes: one micro-batch's policy pass (forward, loss, backward) and the
reference model's pass, as TRL's GRPO trainer runs them, with the settings that could make them cheaper.

    python benchmarks/update_step_profile.py [--config small] [--rows 32] [--prompt 180] [--completion 512]
        [--variants trl no-dropout bf16-adapters uncast-inputs compile compile-layers] [--out FILE]

Builds a random-weight model of ``--config`` (bf16, its tokenizer's vocabulary) with TRL's fused LM
head (``add_fused_lm_head``: per-token log-probabilities and entropies without the full logits, as
``GRPOTrainer`` patches it) and
the config's LoRA adapters (``pada.lora``), then for ``--rows`` rows of ``--prompt`` left-padded prompt
tokens (the padding of each row drawn up to 40 % of the prompt) and ``--completion`` completion tokens:

- ``policy_ms``: the policy's pass of a micro-batch, as ``GRPOTrainer._compute_loss`` runs it: forward
  under the accelerator's bf16 autocast with ``fused_lm_head=True`` (log-probabilities and entropies of
  the completion tokens), a token-level policy-gradient loss, backward; the median of ``--repeat``;
- ``ref_ms``: the reference model's pass of the same rows (the adapters disabled, no gradient, the
  log-probabilities only), as the trainer computes the KL's reference;
- under ``torch.profiler`` (one policy pass): the kernels it launched, their summed GPU time and the 12
  kernels with the most.

Variants: ``trl`` (the trainer's settings: LoRA dropout of the config, adapters in float32, PEFT's
default), ``no-dropout`` (LoRA dropout 0), ``bf16-adapters`` (the adapters' weights in bf16 too),
``uncast-inputs`` (``trl`` with the adapters reading their inputs as autocast gives them, bf16, instead of
PEFT's cast to their float32 weights: ``pada.adapter_input_cast=false``, over the forward and the
backward), ``compile`` (``torch.compile`` of the ``trl`` model's forward, ``dynamic=True``),
``compile-layers`` (each decoder layer's forward compiled instead, one function for every layer:
``pada.compile_scope=layers``). The summed kernel time
against ``policy_ms`` says whether the pass is bound by its kernels or by the host launching them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

VARIANTS = ("trl", "no-dropout", "bf16-adapters", "uncast-inputs", "compile", "compile-layers")


def _model(config: str, variant: str, device: torch.device):
    from omegaconf import OmegaConf
    from peft import get_peft_model
    from transformers import Qwen3Config, Qwen3ForCausalLM
    from trl.trainer.utils import add_fused_lm_head

    from physcene.config import load_config
    from physcene.train.sft import lora_config

    cfg = load_config(f"train_{config}")
    vocab = int(cfg.model.tokenizer.vocab_size)  # the trained tokenizer's size: the LM head's width
    torch.manual_seed(0)
    arch = OmegaConf.to_container(cfg.model.arch, resolve=True)
    model = Qwen3ForCausalLM(Qwen3Config(vocab_size=vocab, tie_word_embeddings=True, pad_token_id=0,
                                         eos_token_id=1, bos_token_id=None, **arch)).to(torch.bfloat16)
    add_fused_lm_head(model, temperature=float(cfg.pada.temperature), outputs=("log_probs", "entropy"))
    lora = OmegaConf.merge(cfg.pada.lora, {"dropout": 0.0} if variant == "no-dropout" else {})
    model = get_peft_model(model, lora_config(lora)).to(device).train()
    if variant == "bf16-adapters":
        for name, p in model.named_parameters():
            if "lora_" in name:
                p.data = p.data.to(torch.bfloat16)
    forward = torch.compile(model, dynamic=True) if variant == "compile" else model
    if variant == "compile-layers":  # pada.compile_scope=layers: each decoder layer's forward compiled
        from physcene.train.decode import compiled_layers, text_model

        def forward(**kwargs):
            with compiled_layers(text_model(model), dynamic=True):
                return model(**kwargs)
    return model, forward, vocab


def _batch(rows: int, prompt: int, completion: int, vocab: int, device: torch.device, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    width = prompt + completion
    ids = torch.randint(3, vocab, (rows, width), generator=g)
    mask = torch.ones(rows, width, dtype=torch.long)
    pads = torch.randint(0, max(int(0.4 * prompt), 1), (rows,), generator=g)
    for r, p in enumerate(pads.tolist()):
        mask[r, :p] = 0
    labels = ids.masked_fill(mask == 0, -100)
    labels[:, :-completion] = -100
    return {"input_ids": ids.to(device), "attention_mask": mask.to(device), "labels": labels.to(device),
            "advantages": torch.randn(rows, 1, generator=g).to(device), "vocab": vocab}


def _policy_pass(forward, batch: dict, completion: int) -> None:
    with torch.autocast(batch["input_ids"].device.type, dtype=torch.bfloat16):
        out = forward(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"],
                      labels=batch["labels"], fused_lm_head=True)
    logps = out.log_probs[:, -completion:]
    entropy = out.entropy[:, -completion:]
    ratio = torch.exp(logps - logps.detach())
    loss = -(ratio * batch["advantages"]).mean()
    (loss + 0.0 * entropy.detach().mean()).backward()


def _ref_pass(model, forward, batch: dict, completion: int) -> None:
    with torch.no_grad(), model.disable_adapter(), torch.autocast(batch["input_ids"].device.type,
                                                                  dtype=torch.bfloat16):
        out = forward(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"],
                      labels=batch["labels"], fused_lm_head=True)
        out.log_probs[:, -completion:].sum().item()


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _median_ms(fn, repeat: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    _sync()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        _sync()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def _kernels(fn) -> dict:
    if not torch.cuda.is_available():
        return {}
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        fn()
        _sync()
    kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    by_name: dict[str, list[float]] = {}
    for e in kernels:
        by_name.setdefault(e.name, []).append(e.device_time_total / 1e3)
    top = sorted(by_name.items(), key=lambda kv: -sum(kv[1]))[:12]
    return {"kernels": len(kernels), "kernel_ms": sum(sum(v) for v in by_name.values()),
            "top": [{"name": n[:90], "calls": len(v), "ms": sum(v)} for n, v in top]}


def profile(variant: str, args) -> dict:
    from peft.helpers import disable_input_dtype_casting

    device = torch.device(args.device)
    model, forward, vocab = _model(args.config, variant, device)
    batch = _batch(args.rows, args.prompt, args.completion, vocab, device)
    row: dict = {}
    # uncast-inputs: the switch held over every pass of this variant (the reference pass has no adapters)
    with disable_input_dtype_casting(model, active=variant == "uncast-inputs"):
        _profile_passes(model, forward, batch, args, row)
    if device.type == "cuda":
        row["max_memory_gib"] = torch.cuda.max_memory_allocated() / 2**30
        torch.cuda.reset_peak_memory_stats()
    return row


def _profile_passes(model, forward, batch: dict, args, row: dict) -> None:
    try:
        def policy():
            _policy_pass(forward, batch, args.completion)
            model.zero_grad(set_to_none=True)

        start = time.perf_counter()
        policy()
        _sync()
        row["first_call_s"] = time.perf_counter() - start  # a compiled variant: its compile
        row["policy_ms"] = _median_ms(policy, args.repeat, args.warmup)
        row["ref_ms"] = _median_ms(lambda: _ref_pass(model, forward, batch, args.completion),
                                   args.repeat, args.warmup)
        row.update(_kernels(policy))
        # another length, as the next micro-batch of a round has: does its first call compile again?
        other = _batch(args.rows, args.prompt, args.completion + 37, batch["vocab"],
                       batch["input_ids"].device, seed=1)
        start = time.perf_counter()
        _policy_pass(forward, other, args.completion + 37)
        model.zero_grad(set_to_none=True)
        _sync()
        row["other_length_first_call_s"] = time.perf_counter() - start
        row["adapter_input_dtypes"] = _adapter_input_dtypes(model, lambda: _policy_pass(forward, batch,
                                                                                      args.completion))
        model.zero_grad(set_to_none=True)
    except Exception as error:  # noqa: BLE001 - a variant that fails (a compile error) is a figure too
        row["error"] = f"{type(error).__name__}: {error}"[:500]


def _adapter_input_dtypes(model, fn) -> list[str]:
    """The dtypes the LoRA A matrices read during ``fn`` (float32: PEFT cast them; bfloat16: as autocast
    gives them)."""
    seen, hooks = set(), []
    for name, module in model.named_modules():
        if name.endswith("lora_A.default"):
            hooks.append(module.register_forward_pre_hook(lambda _, a: seen.add(str(a[0].dtype))))
    try:
        fn()
    finally:
        for hook in hooks:
            hook.remove()
    return sorted(seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="cuda (the figures), or cpu (a smoke run)")
    parser.add_argument("--config", default="small")
    parser.add_argument("--rows", type=int, default=32, help="a micro-batch (pada.per_device_batch_size)")
    parser.add_argument("--prompt", type=int, default=180)
    parser.add_argument("--completion", type=int, default=512)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--out", default=None, help="write the figures as JSON (after each variant)")
    args = parser.parse_args()
    import peft
    import transformers
    import trl

    from physcene.commands.bench.timing import device_name
    from physcene.train.models import set_attention_kernels

    set_attention_kernels({})  # the trainer's default: cuDNN attention off (docs/training.md)
    result = {"device": device_name(torch.device(args.device)), "config": args.config, "rows": args.rows,
              "prompt": args.prompt, "completion": args.completion, "repeat": args.repeat,
              "versions": {"torch": torch.__version__, "transformers": transformers.__version__,
                           "peft": peft.__version__, "trl": trl.__version__}, "variants": {}}
    for variant in args.variants:
        row = result["variants"][variant] = profile(variant, args)
        print(variant, json.dumps({k: v for k, v in row.items() if k != "top"}), flush=True)
        for k in row.get("top", [])[:6]:
            print(f"    {k['ms']:8.2f} ms {k['calls']:5d} x {k['name']}", flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
