"""``physcene train sft|anchors|pada|ablation|ablation-plot|ablation-merge --config NAME [key=value ...]``
(docs/training.md).

``--config tiny`` reads ``configs/train/tiny.yaml`` over ``configs/train/base.yaml`` (``small``,
``qwen3_vl_8b`` likewise; the older names ``train_tiny`` ... too; a YAML path is read as given).
Every stage resumes: SFT and PADA from the last ``checkpoint-*`` in their output directory, anchors
by keeping a complete anchor file. Multi-GPU: prefix with
``accelerate launch --config_file configs/accelerate/multi_gpu.yaml -m physcene.cli``.
"""

from __future__ import annotations

import json

from physcene.config import load_config

NAME = "train"
HELP = ("train the layout model: sft, anchors (SFT output + TTO), pada (grpo|pada_star|pada), ablation, "
        "ablation-plot, ablation-merge")
SETTINGS = "configs/train/<--config>.yaml over configs/train/base.yaml (docs/training.md)"

STAGES = ("sft", "anchors", "pada", "ablation", "ablation-plot", "ablation-merge")


def add_arguments(parser) -> None:
    parser.add_argument("stage", choices=STAGES, help="which stage to run")
    parser.add_argument("--config", default="tiny",
                        help="tiny, small, qwen3_vl_8b (configs/train/<name>.yaml over base.yaml) "
                             "or a YAML path")
    parser.add_argument("--variant", choices=("pada", "pada_star", "grpo"),
                        help="pada stage: which objective (default: the config's pada.variant)")
    parser.add_argument("--budget-min", type=float, default=None,
                        help="ablation: wall-clock budget in minutes for the whole pipeline")
    parser.add_argument("--sources", nargs="+", default=None, metavar="ABLATION_JSON",
                        help="ablation-merge: the runs' tables (e.g. runs/rl/s0/ablation.json "
                             "runs/rl/s1/ablation.json), merged into ablation.output")
    parser.add_argument("--layouts", default=None, metavar="DIR",
                        help="ablation-merge: copy every row's layouts to DIR/s<seed>/ and name the copies")


def training_config(name: str, overrides=()):
    """``configs/train/<name>.yaml`` over ``configs/train/base.yaml`` (or a YAML path, or a config name
    such as ``train_tiny``) with ``key=value`` overrides."""
    path_like = name.endswith((".yaml", ".yml")) or "/" in name or name.startswith("train_")
    # train_<name> is configs/train/<name>.yaml (physcene.config.config_path); unknown, it is named so
    return load_config(name if path_like else f"train_{name}", list(overrides))


def _main_process() -> bool:
    """Rank 0 under ``accelerate launch`` (every rank runs the stage; one prints)."""
    import os

    return int(os.environ.get("RANK", "0")) == 0


def run(args) -> int:
    try:
        return _run_stage(args)
    finally:  # under accelerate: leave NCCL cleanly (no "destroy_process_group() was not called")
        import sys

        dist = sys.modules.get("torch.distributed")
        if dist is not None and dist.is_available() and dist.is_initialized():
            dist.destroy_process_group()


def _run_stage(args) -> int:
    overrides = list(args.overrides)
    if args.variant:
        overrides.append(f"pada.variant={args.variant}")
    cfg = training_config(args.config, overrides)
    if args.stage == "sft":
        from physcene.train.sft import run_sft

        out = run_sft(cfg)
        if _main_process():
            print(f"sft model: {out}")
    elif args.stage == "anchors":
        from physcene.train.anchors import run_anchors

        out = run_anchors(cfg)
        summary = out.with_suffix(".summary.json")
        if not _main_process():
            return 0
        print(f"anchors: {out}")
        if summary.is_file():
            print(summary.read_text())
    elif args.stage == "pada":
        from physcene.train.pada import run_pada

        out = run_pada(cfg)
        if _main_process():
            print(f"{cfg.pada.variant} adapter: {out}")
    elif args.stage == "ablation-merge":
        from physcene.train.ablation import merge_ablations

        if not args.sources:
            raise ValueError("train ablation-merge: name the tables to merge: --sources A.json B.json ...")
        merged = merge_ablations(args.sources, str(cfg.ablation.output), layouts=args.layouts)
        print(f"{len(merged['rows'])} rows and {len(merged['checkpoint_rows'])} checkpoint rows: "
              f"{cfg.ablation.output}")
    elif args.stage == "ablation-plot":  # the learning curves of ablation.output, beside it (.svg)
        from physcene.train.ablation_plot import write_learning_curves

        print(f"learning curves: {write_learning_curves(str(cfg.ablation.output))}")
    else:
        from physcene.train.ablation import run_ablation

        result = run_ablation(cfg, budget_min=args.budget_min)
        print(json.dumps(result.get("decode_only", result["rows"]), indent=1))
    return 0
