"""Can a layout model learn from pada.denoise's targets? An offline check on the CPU.

    python -m physcene.train.analysis.denoise_offline runs/small/sft runs/small/anchors_l3.jsonl.gz \
        --probe-records t24/test.jsonl --train 384 --test 64 --steps 48 --out denoise_offline.json

The targets are pada.denoise's (train/denoise.py) built on the SFT model's own greedy outputs (the anchor
file's ``sft_completion`` column): each blamed object moved to its free spot, or by TTO, and its numbers
rewritten in the model's own text. A LoRA like PADA's (r 16, alpha 32, every projection) is trained on
the cross-entropy of the rewritten numbers only, given the model's own prefix, over the first
``--train`` rows with a target (``--steps`` AdamW steps of ``--batch`` rows, lr 5e-4), the sequence cut
after its last supervised token. Before and after: the NLL per rewritten token of the next ``--test``
rows (held out: the model must place objects it was not shown where the repair put them, which needs
the neighbours already written), of the numbers those rows were written with (what the repair
replaced), and the neighbour probe of context_probe.py on ``--probe-records``.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import torch

from physcene.train.analysis import context_probe
from physcene.train.targets import teacher_forced_nll

_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def supervised_rows(tokenizer, records: list[dict], targets: list) -> list[dict]:
    """Per record with a target: prompt ids, target ids (cut after the last rewritten token), the mask
    of the rewritten numbers' tokens, and the mask of the original numbers' tokens in the original text
    (the same object lines, cut the same way)."""
    from physcene.train.pada import tokenize_target

    rows = []
    for record, target in zip(records, targets):
        if target is None:
            continue
        prompt = tokenizer(record["prompt"], add_special_tokens=False)["input_ids"]
        ids, mask = tokenize_target(tokenizer, target.text, target.spans, max_length=1 << 20)
        old_spans = _original_spans(record["sft_completion"], target)
        old_ids, old_mask = tokenize_target(tokenizer, record["sft_completion"], old_spans,
                                            max_length=1 << 20)
        cut = max(k for k, m in enumerate(mask) if m) + 1
        old_cut = max((k for k, m in enumerate(old_mask) if m), default=-1) + 1
        rows.append({"prompt": prompt, "ids": ids[:cut], "mask": mask[:cut],
                     "old_ids": old_ids[:old_cut], "old_mask": old_mask[:old_cut]})
    return rows


def _original_spans(text: str, target) -> list[tuple[int, int]]:
    """The character spans in the original ``text`` of the numbers ``target`` rewrote (its spans,
    shifted back by how much longer each earlier rewrite made the text)."""
    spans, shift = [], 0
    for a, b in target.spans:
        m = _NUMBER.match(text, a - shift)
        spans.append((m.start(), m.end()))
        shift += (b - a) - (m.end() - m.start())
    return spans


def mean_nll(model, rows: list[dict], ids_key: str = "ids", mask_key: str = "mask", batch: int = 4) -> float:
    """NLL per supervised token over ``rows`` (teacher forced, no gradient)."""
    total, count = 0.0, 0
    with torch.no_grad():
        for start in range(0, len(rows), batch):
            nll, n = _batch_nll(model, rows[start:start + batch], ids_key, mask_key)
            total, count = total + float(nll), count + int(n)
    return total / max(count, 1)


def _batch_nll(model, rows: list[dict], ids_key: str, mask_key: str) -> tuple[torch.Tensor, torch.Tensor]:
    """(summed NLL, supervised tokens) of a batch of [prompt | target] rows (``ids_key`` / ``mask_key``)."""
    return teacher_forced_nll(model, [(r["prompt"], r[ids_key], r[mask_key]) for r in rows])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="SFT checkpoint directory")
    parser.add_argument("anchors", help="anchor JSONL (.gz ok) with prompt and sft_completion")
    parser.add_argument("--probe-records", help="CTRC JSONL for the neighbour probe (physcene data synth)")
    parser.add_argument("--probe-n", type=int, default=24)
    parser.add_argument("--train", type=int, default=384, help="rows with a target to train on")
    parser.add_argument("--test", type=int, default=64, help="held-out rows with a target")
    parser.add_argument("--steps", type=int, default=48)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--margin-cm", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="write the result as JSON here")
    args = parser.parse_args()
    from peft import LoraConfig, get_peft_model

    from physcene.reward import ChargeConfig, PhysicsReward, RewardConfig
    from physcene.train.denoise import denoise_targets
    from physcene.train.models import load_model, load_tokenizer
    from physcene.train.records import load_records
    from physcene.tto import TTOConfig

    torch.manual_seed(args.seed)
    started = time.perf_counter()
    records = [r for r in load_records(args.anchors) if r.get("sft_completion")]
    texts = [r["sft_completion"] for r in records]
    reward = PhysicsReward(RewardConfig(device="cpu"),
                           charges=ChargeConfig(terms=("penetration", "floating", "out_of_zone")))
    targets = denoise_targets(texts, reward.score(texts).object_charges, engine=reward.engine,
                              margin_cm=args.margin_cm, config=TTOConfig.load(["lambda_zone=100.0"]))
    tokenizer = load_tokenizer(args.model)
    rows = supervised_rows(tokenizer, records, targets)
    train, test = rows[:args.train], rows[args.train:args.train + args.test]
    model = load_model(args.model, dtype="float32")
    model = get_peft_model(model, LoraConfig(r=16, lora_alpha=32, lora_dropout=0.0, task_type="CAUSAL_LM",
                                             target_modules=["q_proj", "k_proj", "v_proj", "o_proj",
                                                             "gate_proj", "up_proj", "down_proj"]))
    probe = context_probe
    probe_rows = load_records(args.probe_records)[:args.probe_n] if args.probe_records else []

    def measure() -> dict:
        model.eval()
        out = {"held_out_nll_rewritten": mean_nll(model, test),
               "held_out_nll_original": mean_nll(model, test, "old_ids", "old_mask")}
        if probe_rows:
            scorer = probe._Scorer(None, "cpu", model=model, tokenizer=tokenizer)
            out["neighbour_probe"] = probe.probe(scorer, probe_rows)["neighbour"]
        return out

    before = measure()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=args.lr)
    losses = []
    model.train()
    for step in range(args.steps):
        batch = [train[(step * args.batch + k) % len(train)] for k in range(args.batch)]
        nll, n = _batch_nll(model, batch, "ids", "mask")
        loss = nll / n.clamp(min=1)
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        losses.append(float(loss.detach()))
        print(f"step {step + 1}/{args.steps}: {losses[-1]:.3f}", flush=True)
    after = measure()
    result = {"model": args.model, "anchors": args.anchors, "rows_with_target": len(rows),
              "train": len(train), "test": len(test), "steps": args.steps, "batch": args.batch, "lr": args.lr,
              "train_loss_first_4": losses[:4], "train_loss_last_4": losses[-4:],
              "before": before, "after": after, "seconds": round(time.perf_counter() - started, 1)}
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
