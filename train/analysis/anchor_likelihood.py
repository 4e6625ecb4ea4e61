"""How likely each model finds held-out anchors: PADA's mechanism, measured on prompts it never trained on.

PADA adds α · CE toward the anchors (the SFT model's layouts repaired by TTO) to GRPO's loss; its claim
is that this keeps the policy near physically valid layouts while it learns from the reward. This
measures it for every model of an RL run: the mean NLL per anchor token (EOS included) of an anchor
file made from prompts outside the RL pool (``anchors.exclude``, the held-out anchors of
``train/scripts/rl_ablation.sh``), teacher-forced (:func:`physcene.train.anchors.anchor_nll`). The
ablation writes the same figure into each row when ``ablation.heldout_anchors`` is set; this runs it
on kept checkpoints without evaluating them again:

    python -m physcene.train.analysis.anchor_likelihood runs/rl/anchors_heldout.jsonl.gz \\
        sft=artifacts/small-sft pada@50=artifacts/rl-s0-pada/checkpoint-50 pada=artifacts/rl-s0-pada \\
        --out docs/results/anchor_nll.json

``--base`` loads the adapters on that SFT model instead of the path their ``adapter_config.json`` names
(the training host's; :func:`physcene.train.generate.adapter_base`). ``--temperature T`` reads the NLL
under ``softmax(logits / T)``: PADA's cross-entropy is taken at the rollouts' temperature (TRL divides the
logits of its log-probabilities by ``pada.temperature``), so runs at different temperatures compare at
their own T, and at 1 as the model decodes.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import torch

from physcene.train.anchors import anchor_nll
from physcene.train.records import load_records

__all__ = ["anchor_likelihoods"]


def anchor_likelihoods(anchors: str | Path, models: dict[str, str], *, device: str = "cpu",
                       batch_size: int = 16, max_length: int = 8192, base: str | Path | None = None,
                       temperature: float = 1.0) -> dict:
    """``{"anchors", "n", "tokens", "temperature", "models": {name: {"path", "nll", "seconds"}}}`` for each
    named model (a checkpoint folder: an SFT model or an RL adapter, on ``base`` where given) on the anchor
    file ``anchors``, the NLL under ``softmax(logits / temperature)``."""
    records = load_records(str(anchors))
    out: dict = {"anchors": str(anchors), "temperature": temperature, "models": {}}
    for name, path in models.items():
        start = time.perf_counter()
        figure = anchor_nll(path, records, device=device, batch_size=batch_size, max_length=max_length,
                            base=base, temperature=temperature)
        out.update(n=figure["n"], tokens=figure["tokens"])
        out["models"][name] = {"path": str(path), "nll": figure["nll"],
                               "seconds": round(time.perf_counter() - start, 1)}
        print(f"{name}: {figure['nll']:.4f} nats per anchor token ({figure['n']} anchors)", file=sys.stderr)
    return out


def _named(spec: str) -> tuple[str, str]:
    name, sep, path = spec.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(
            f"a model is NAME=PATH (e.g. pada@50=runs/rl/s0/pada/checkpoint-50), got {spec!r}")
    if not Path(path).is_dir():
        raise argparse.ArgumentTypeError(f"model {name}: {path!r} is not a checkpoint folder")
    return name, path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("anchors", help="anchor JSONL (.gz ok): records with prompt and anchor")
    parser.add_argument("models", nargs="+", type=_named, help="NAME=PATH of each checkpoint folder")
    parser.add_argument("--out", help="write the result as JSON here")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--max-length", type=int, default=2304, help="anchor tokens kept (the rollout bound)")
    parser.add_argument("--base", help="the SFT model the adapters are loaded on (default: the one each "
                                       "adapter_config.json names)")
    parser.add_argument("--temperature", type=float, default=1.0,
                        help="the NLL under softmax(logits / T) (default 1; a PADA run's own "
                             "cross-entropy is taken at its pada.temperature)")
    args = parser.parse_args()
    if not Path(args.anchors).is_file():
        parser.error(f"anchors: {args.anchors!r} does not exist")
    if not args.temperature > 0:
        parser.error(f"--temperature must be > 0, got {args.temperature}")
    result = anchor_likelihoods(args.anchors, dict(args.models), device=args.device,
                                batch_size=args.batch_size, max_length=args.max_length, base=args.base,
                                temperature=args.temperature)
    result["device"] = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "cpu"
    result["command"] = "python -m physcene.train.analysis.anchor_likelihood " + shlex.join(sys.argv[1:])
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
