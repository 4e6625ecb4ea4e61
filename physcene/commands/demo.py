"""``physcene demo``: the README's main job on built-in defaults (configs/demo.yaml).

Synthesises a small benchmark across the six scene types, scores the reference layouts with the
SDF engine and the rule judge, repairs them with TTO, prints the before/after table and writes
renders and a report under ``./physcene-demo/``. Offline; a few minutes on 2 CPU cores.
"""

from __future__ import annotations

import time

from physcene.commands import add_json, add_quiet, print_json
from physcene.config import load_config
from physcene.eval.harness import run_evaluation
from physcene.eval.report import main_table, threshold_table

NAME = "demo"
HELP = "synthesise a small benchmark, score it, repair it with TTO, write a before/after report"
SETTINGS = "configs/demo.yaml (docs/eval.md)"


def add_arguments(parser) -> None:
    parser.add_argument("--out", help="output directory (default: ./physcene-demo)")
    parser.add_argument("--n", type=int, help="number of scenes (default: 24)")
    add_quiet(parser)
    add_json(parser, "the paths written and every method's summary")


def run(args) -> int:
    cfg = load_config("demo", args.overrides)
    if args.out:
        cfg.out = args.out
    if args.n is not None:
        if args.n < 1:
            raise ValueError(f"--n must be >= 1, got {args.n}")
        cfg.n = args.n
    start = time.perf_counter()
    tables, path = run_evaluation(cfg, command="physcene demo", title="physcene demo — reference vs. TTO",
                                  progress=not args.quiet)
    seconds = time.perf_counter() - start
    if args.json:
        print_json({"split": cfg.split, "n": cfg.n, "seconds": seconds, "report": path,
                    "results": path.parent / "results.json", "renders": path.parent / "renders",
                    "methods": tables})
        return 0
    print(f"\n{cfg.n} {cfg.split}-split scenes, rule judge, SDF engine (cm); "
          f"{seconds:.0f} s\n")
    print(main_table(tables))
    print()
    print(threshold_table(tables))
    print(f"\nreport: {path}\nrenders: {path.parent / 'renders'}")
    return 0
