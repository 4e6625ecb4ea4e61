"""``physcene bench TARGET``: throughput benchmarks with the numbers the issues ask for.

    physcene bench reward --device cuda                      # 512 scenes x 16 objects x 1024 points
    physcene bench reward --device cpu --scenes 256 --objects 12 --json
    physcene bench tto --device cuda
    physcene bench generate --device cuda --config small
    physcene bench train8b --device cuda --stage sft --out sft.json   # Qwen3-VL-8B's size, random weights
    physcene bench pada --device cuda --config small --tokens 2304
    physcene bench tokens --config small --json               # tokens per object, bpe vs ctrc tokenizer

``TARGETS`` is the one registry (name -> :class:`BenchTarget`). A new target is a module of this
package with ``TARGET = BenchTarget(help, add_arguments, run, summary)`` (``run(args) -> dict``:
args.device, args.repeat, args.json + its own options) and one line below. Every target takes
``--device``, ``--json`` and ``--repeat``; time with :func:`timed` (warm-up, device synchronised
around every timed call, median wall and CPU seconds).
"""

from __future__ import annotations

import json

import torch

from physcene.commands.bench import generate, pada, reward, tokens, train8b, tto
from physcene.commands.bench.reward import bench_scenes
from physcene.commands.bench.timing import BenchTarget, Timing, device_name, timed

NAME = "bench"
HELP = "Throughput benchmarks (targets: reward, tto, generate, pada, tokens, train8b)"
SETTINGS = ("configs/physics.yaml for reward, configs/tto.yaml for tto, configs/train/<--config>.yaml for "
            "generate, pada and tokens (docs/physics.md, docs/tto.md, docs/training.md)")

__all__ = ["TARGETS", "BenchTarget", "Timing", "bench_scenes", "device_name", "timed"]

TARGETS: dict[str, BenchTarget] = {"reward": reward.TARGET, "tto": tto.TARGET, "generate": generate.TARGET,
                                   "pada": pada.TARGET, "tokens": tokens.TARGET, "train8b": train8b.TARGET}


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="target", metavar="TARGET")
    sub.required = True
    for name, target in TARGETS.items():
        p = sub.add_parser(name, help=target.help, description=target.help)
        p.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N")
        p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
        p.add_argument("--repeat", type=int, default=None,
                       help="timed calls per figure (median); default per target (reward: 20 CUDA, 3 CPU)")
        target.add_arguments(p)


def run(args) -> int:
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {args.device}: CUDA is not available on this machine")
    target = TARGETS[args.target]
    if args.repeat is None:
        args.repeat = target.repeat[0] if device.type == "cuda" else target.repeat[1]
    result = target.run(args)
    print(json.dumps(result, indent=1) if args.json else target.summary(result))
    return 0
