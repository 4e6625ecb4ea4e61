"""Evaluate one trained checkpoint the way the ablation's eval stage does (rows NAME and NAME+tto).

    python docs/results/ablation_eval.py runs/small/sft --n 24 --constrained --cache static \
        --out docs/results/ablation_constrained_cpu.json

The same function as ``physcene train ablation``'s last stage (``physcene.train.ablation._evaluate``:
the first N test scenes of seed 0, greedy generation, rule judge, TTO for the ``+tto`` row), on one
model, without training anything; ``--constrained`` decodes under ``physcene.train.constrained``.
Used to evaluate the 2 x H200 SFT checkpoint on this CPU machine.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from physcene.train.ablation import _evaluate

from physcene.config import load_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="checkpoint directory (physcene train sft/pada output)")
    parser.add_argument("--name", default="sft", help="row name: sft (adds sft+tto), grpo, pada*, pada")
    parser.add_argument("--n", type=int, default=24, help="test scenes")
    parser.add_argument("--constrained", action="store_true", help="CTRC-constrained decoding")
    parser.add_argument("--cache", default="static", help="KV cache: dynamic, static, static_compile")
    parser.add_argument("--config", default="small")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    cfg = load_config(f"train_{args.config}", [f"ablation.n_test={args.n}", "eval.max_new_tokens=4096",
                                               f"eval.constrained={str(args.constrained).lower()}",
                                               f"eval.cache={args.cache}"])
    start = time.monotonic()
    rows = _evaluate(cfg, {args.name: Path(args.model)}, budget_s=float("inf"))
    import torch

    result = {"rows": rows, "seconds": round(time.monotonic() - start, 1),
              "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
              "model": str(args.model), "n_test": args.n,
              "decoding": "greedy, CTRC-constrained" if args.constrained else "greedy",
              "command": "python docs/results/ablation_eval.py " + " ".join(
                  [args.model, f"--name {args.name}", f"--n {args.n}", f"--cache {args.cache}",
                   *(["--constrained"] if args.constrained else []), f"--out {args.out}"])}
    Path(args.out).write_text(json.dumps(result, indent=1))
    keys = ("parse_rate", "scr", "qpr7", "judge_avg")
    print(json.dumps({r["name"]: {k: r[k] for k in keys} for r in rows}))


if __name__ == "__main__":
    main()
