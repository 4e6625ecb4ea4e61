"""Where a PADA policy's KL to its reference sits: at the tokens the CTRC constraint chose, or elsewhere.

    python docs/results/overruled_kl.py runs/small/pada/checkpoint-225 runs/small/anchors_l3.jsonl.gz \
        --prompts 2 --per 2 --out docs/results/overruled_kl_session9.json

Samples ``per`` completions of each of the first ``prompts`` records under the constraint (temperature
1, rejection draws, as PADA's groups are sampled), records the positions where the constraint overruled
the policy's draw (``CTRCConstraint.overruled``), then scores every completion token under the policy
(adapter on) and the reference (adapter off) and reports TRL's per-token KL estimate
``exp(ref - logp) - (ref - logp) - 1`` at the overruled and at the free positions, with the largest
single terms. The adapter's base model is read from its ``adapter_config.json`` unless ``--base``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from peft import PeftModel
from physcene.train.constrained import CTRCConstraint, sampling_warpers
from physcene.train.models import load_model, load_tokenizer
from physcene.train.records import load_records
from transformers import LogitsProcessorList


def _logps(model, ids, attention, prompt_length, completion, reference: bool) -> torch.Tensor:
    with torch.no_grad():
        if reference:
            with model.disable_adapter():
                logits = model(input_ids=ids, attention_mask=attention).logits
        else:
            logits = model(input_ids=ids, attention_mask=attention).logits
    logp = torch.log_softmax(logits[:, prompt_length - 1:-1].float(), dim=-1)
    return logp.gather(-1, completion[..., None])[..., 0]


def _summary(kl, policy, reference, where, everywhere) -> dict:
    return {"tokens": int(where.sum()), "kl_mean": float(kl[where].mean()), "kl_max": float(kl[where].max()),
            "kl_share": float(kl[where].sum() / kl[everywhere].sum()),
            "tokens_kl_above_1": int((kl[where] > 1).sum()),
            "policy_logp_mean": float(policy[where].mean()),
            "reference_logp_mean": float(reference[where].mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("adapter", help="a PADA adapter directory (or checkpoint-N)")
    parser.add_argument("records", help="CTRC JSONL(.gz) with a prompt column (an anchor file works)")
    parser.add_argument("--base", help="base model directory (default: the adapter's base model)")
    parser.add_argument("--prompts", type=int, default=2)
    parser.add_argument("--per", type=int, default=2, help="completions sampled per prompt")
    parser.add_argument("--max-new-tokens", type=int, default=2304)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    base = args.base or json.loads((Path(args.adapter) / "adapter_config.json").read_text())[
        "base_model_name_or_path"]
    tokenizer = load_tokenizer(base)
    model = PeftModel.from_pretrained(load_model(base, dtype="float32"), args.adapter).eval()
    prompts = [r["prompt"] for r in load_records(args.records)[:args.prompts] for _ in range(args.per)]
    tokenizer.padding_side = "left"
    encoded = tokenizer(prompts, return_tensors="pt", padding=True, add_special_tokens=False)
    config = model.generation_config
    config.update(do_sample=True, temperature=1.0, top_k=0, top_p=1.0, max_new_tokens=args.max_new_tokens,
                  pad_token_id=tokenizer.pad_token_id, eos_token_id=tokenizer.eos_token_id)
    constraint = CTRCConstraint(tokenizer, prompts, greedy=False, warpers=sampling_warpers(config))
    torch.manual_seed(args.seed)
    start = time.monotonic()
    with torch.no_grad():
        ids = model.generate(**encoded, generation_config=config,
                             logits_processor=LogitsProcessorList([constraint]))
    seconds = time.monotonic() - start
    prompt_length = encoded["input_ids"].shape[1]
    completion = ids[:, prompt_length:]
    eos = completion == tokenizer.eos_token_id
    full = torch.full((len(prompts),), completion.shape[1])
    length = torch.where(eos.any(1), eos.int().argmax(1) + 1, full)
    valid = torch.arange(completion.shape[1])[None] < length[:, None]
    attention = torch.cat([encoded["attention_mask"], valid.long()], 1)
    policy = _logps(model, ids, attention, prompt_length, completion, reference=False)
    reference = _logps(model, ids, attention, prompt_length, completion, reference=True)
    gap = reference - policy
    kl = torch.exp(gap) - gap - 1
    overruled = torch.zeros_like(valid)
    for row, positions in enumerate(constraint.stats.overruled):
        overruled[row, [p for p in positions if p < completion.shape[1]]] = True
    overruled &= valid
    top = torch.topk(kl.masked_fill(~valid, -1).flatten(), 10)
    largest = []
    for value, index in zip(top.values.tolist(), top.indices.tolist()):
        row, position = divmod(index, completion.shape[1])
        before = tokenizer.decode(completion[row, max(0, position - 12):position])
        largest.append({"kl": value, "overruled": bool(overruled[row, position]),
                        "policy_logp": float(policy[row, position]),
                        "reference_logp": float(reference[row, position]),
                        "token": tokenizer.decode([int(completion[row, position])]), "after": before[-50:]})
    result = {"adapter": args.adapter, "records": args.records, "completions": len(prompts),
              "generation_seconds": round(seconds, 1),
              "overruled": _summary(kl, policy, reference, overruled, valid),
              "free": _summary(kl, policy, reference, valid & ~overruled, valid), "largest": largest,
              "command": "python docs/results/overruled_kl.py " + " ".join(
                  [args.adapter, args.records, f"--prompts {args.prompts}", f"--per {args.per}",
                   f"--out {args.out}"])}
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("overruled", "free")}, indent=1))


if __name__ == "__main__":
    main()
