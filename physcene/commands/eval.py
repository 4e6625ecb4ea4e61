"""``physcene eval``: score generators on the benchmark the way the paper does (docs/eval.md)."""

from __future__ import annotations

import shlex
import sys

from physcene.artifacts import resolve_generators
from physcene.commands import add_json, add_quiet, print_json
from physcene.config import config_path, load_config
from physcene.eval.harness import EvalError, run_evaluation
from physcene.eval.report import failure_lines, main_table

NAME = "eval"
HELP = "evaluate layout generators on the test/OOD benchmark (SCR, ACR, judge scores, QPR)"
SETTINGS = "configs/eval.yaml, or the --config file (docs/eval.md)"


def add_arguments(parser) -> None:
    parser.add_argument("--split", choices=("test", "ood", "train"), help="benchmark split (default: test)")
    parser.add_argument("--generator", help="comma-separated: reference, tto, heuristic, file:DIR, "
                        "model:PATH (or an artifact's name), endpoint:URL (default: reference)")
    parser.add_argument("--judge", choices=("rule", "endpoint"), help="judge (default: rule)")
    parser.add_argument("--out", help="output directory (default: physcene-eval)")
    parser.add_argument("--n", type=int, help="evaluate only the first N scenes of the split")
    parser.add_argument("--repair", action="store_true", help="apply TTO to every generator's output")
    parser.add_argument("--config", default="eval", help="config name or YAML path (default: eval)")
    add_quiet(parser)
    add_json(parser, "the paths written and every method's summary")


def _config(args):
    cfg = load_config(args.config, args.overrides)
    for key in ("split", "generator", "judge", "out", "n"):
        if getattr(args, key, None) is not None:
            cfg[key] = getattr(args, key)
    if getattr(args, "repair", False):
        cfg.repair = True
    if cfg.get("generator"):  # model:NAME of an artifact -> its restored folder
        cfg.generator = resolve_generators(str(cfg.generator))
    # n is null in eval.yaml (all scenes), so the config path cannot know its type: checked here
    if cfg.n is not None and (isinstance(cfg.n, bool) or not isinstance(cfg.n, int)):
        raise ValueError(f"{config_path(args.config)}: n={cfg.n!r}: expected an integer or null")
    if cfg.n is not None and cfg.n < 1:
        raise ValueError(f"--n must be >= 1, got {cfg.n}")
    if float(cfg.get("temperature", 0.0)) < 0:
        raise ValueError(f"{config_path(args.config)}: temperature={cfg.temperature}: expected 0 (greedy) or "
                         "a positive number")
    return cfg


def model_generators(cfg, *, max_new_tokens: int = 4096, device: str | None = None,
                     progress: bool = False) -> dict:
    """A :data:`physcene.eval.harness.Generate` per ``model:PATH`` in ``cfg.generator``: the
    checkpoint's completions of the items' prompts (:func:`physcene.train.generate.generate`) with
    the config's KV ``cache``, ``constrained`` decoding, ``follow_plan`` and ``temperature`` (0:
    greedy, else sampled with the config's ``seed``); ``device``: None = the first GPU, else CPU;
    ``progress``: a bar on stderr over the prompts as their batches are decoded. The harness itself
    never imports the training code (eval/ sits below train/)."""
    specs = [g.strip() for g in str(cfg.generator).split(",") if g.strip().startswith("model:")]
    cache, constrained = str(cfg.get("cache", "dynamic")), bool(cfg.get("constrained", False))
    follow_plan = bool(cfg.get("follow_plan", True))
    temperature, seed = float(cfg.get("temperature", 0.0)), int(cfg.get("seed", 0))

    def model(path: str):
        def run_model(items) -> list[str]:
            try:  # here: transformers loads only when a checkpoint is evaluated
                from physcene.train.generate import generate, sampling
            except ImportError as exc:
                raise EvalError(f"generator model:{path}: physcene.train.generate is unavailable "
                                f"({exc})") from exc
            return generate(path, [it.prompt for it in items], max_new_tokens=max_new_tokens, device=device,
                            cache=cache, constrained=constrained, follow_plan=follow_plan,
                            seed=seed, progress=progress, **sampling(temperature))
        return run_model

    return {spec: model(spec[len("model:"):]) for spec in specs}


def run(args) -> int:
    cfg = _config(args)
    argv = sys.argv[1:] or ["eval"]
    command = "physcene " + " ".join(shlex.quote(a) for a in argv)
    tables, path = run_evaluation(cfg, command=command, title=f"physcene eval — {cfg.split} split",
                                  progress=not args.quiet,
                                  generators=model_generators(cfg, max_new_tokens=int(cfg.max_new_tokens),
                                                              progress=not args.quiet))
    if args.json:
        print_json({"split": cfg.split, "n": cfg.n, "report": path, "results": path.parent / "results.json",
                    "methods": tables})
        return 0
    print(main_table(tables))
    for name, m in tables.items():
        if m.get("paired"):
            pair = m["paired"]
            print(f"paired with {pair['against']} on {pair['scenes']} scenes: SCR {pair['scr_first']:.1%} -> "
                  f"{pair['scr_second']:.1%}, colliding in the first only {pair['only_first']}, "
                  f"in {name} only {pair['only_second']} (McNemar p = {pair['p_value']:.2g})")
    failures = failure_lines(tables)
    if failures:
        print("\nnot every scene was scored (each fails QPR):")
        print("\n".join(f"  {line}" for line in failures))
    print(f"\nreport: {path}\nresults: {path.parent / 'results.json'}")
    return 0
