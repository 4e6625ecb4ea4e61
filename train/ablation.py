"""The paper's ablation (Table "CTRC / +GRPO / +TTO / +PADA* / +PADA") end to end, within a time budget.

``run_ablation(cfg, budget_min)`` runs SFT -> anchors -> ``grpo``, ``pada_star``, ``pada`` -> eval of
SFT, SFT + TTO, GRPO, PADA* and PADA on the test split with the eval harness (rule judge), and writes
``ablation.json`` ``{"rows": [{name, scr, acr, qpr7, judge_avg, parse_rate, n, floating, by_level}], "gpu",
"commands", "stages"}`` plus Markdown tables (all levels; SCR / ACR per level). ``ablation.variants``
picks the RL rows; ``ablation.checkpoints`` adds a row per kept intermediate checkpoint of them
(``"pada@12"``, under ``checkpoint_rows``: the metrics against RL steps); ``ablation.layouts`` keeps
every row's parsed layouts for re-scoring. Each stage gets a share of the budget (``ablation.shares``); a
training stage that runs out of time stops at its next optimizer step and saves (``TimeBudget``), so
the table always comes out, with the time each stage took recorded under ``stages`` (and the steps
it ran in each model's ``physcene_run.json``). With ``ablation.reuse`` (default) a stage whose final
model exists is not rerun, so the pipeline can be driven by repeated commands under a job time limit.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from functools import partial
from pathlib import Path

import torch
from accelerate import PartialState
from accelerate.utils import gather_object
from omegaconf import DictConfig, OmegaConf

from physcene.train.anchors import run_anchors
from physcene.train.generate import generate as checkpoint_generate
from physcene.train.models import RUN_INFO, TrainingSetupError, read_run_info
from physcene.train.pada import NoAnchorsError, run_pada
from physcene.train.sft import TimeBudget, run_sft

__all__ = ["ROW_NAMES", "TimeBudget", "ablation_row", "checkpoint_models", "level_table", "markdown_table",
           "run_ablation"]

ROW_NAMES = ("sft", "sft+tto", "grpo", "pada*", "pada")
DEFAULT_SHARES = {"sft": 0.45, "anchors": 0.10, "grpo": 0.10, "pada_star": 0.10, "pada": 0.10, "eval": 0.15}


def _figures(summary: dict) -> dict:
    """SCR/ACR at 0 cm, QPR at τ = 7, judge average and parse rate of one eval-harness summary, and the
    share of floating objects where it has one (a collision-only reward pays for lifting objects out of
    collisions: docs/results.md)."""
    collision = summary["collision"].get(0.0, summary["collision"].get("0.0", {}))
    qpr = summary["QPR"].get(7.0, summary["QPR"].get("7.0"))
    n = int(summary["n"])

    def finite(x):  # NaN (no parsed layout to measure) -> null in JSON, "—" in the table
        return None if x is None or x != x else float(x)

    figures = {"scr": finite(collision.get("SCR")), "acr": finite(collision.get("ACR")),
               "qpr7": finite(qpr), "judge_avg": finite(summary["judge"]["avg"]),
               "parse_rate": (n - int(summary.get("parse_errors", 0))) / max(n, 1), "n": n}
    if "floating" in summary:
        figures["floating"] = finite(summary["floating"]["objects"])
    return figures


def ablation_row(name: str, report: dict) -> dict:
    """One table row from an eval-harness method report, with the same figures per difficulty level
    under ``by_level`` when the report has them."""
    s = report["summary"]
    row = {"name": name, **_figures(s),
           "parse_error_kinds": [list(k) for k in s.get("parse_error_kinds", [])]}
    if report.get("by_level"):
        row["by_level"] = {str(level): _figures(summary) for level, summary in report["by_level"].items()}
    return row


def checkpoint_models(models: dict[str, Path]) -> dict[str, Path]:
    """``{"pada@12": .../pada/checkpoint-12, ...}``: every kept intermediate checkpoint of the RL rows
    (``ablation.checkpoints``), in step order; the final model's own step is its row already."""
    out = {}
    for name in ("grpo", "pada*", "pada"):
        if name not in models:
            continue
        steps = sorted(int(d.name.split("-")[1]) for d in Path(models[name]).glob("checkpoint-*")
                       if d.name.split("-")[1].isdigit() and (d / "adapter_config.json").is_file())
        final = read_run_info(models[name]).get("steps")
        out.update({f"{name}@{step}": Path(models[name]) / f"checkpoint-{step}"
                    for step in steps if step != final})
    return out


def _completions(path: Path, items, **options) -> list[str]:
    """The checkpoint's completions of the items' prompts: the eval harness's ``model:PATH`` generator."""
    return checkpoint_generate(path, [it.prompt for it in items], **options)


def _gpu() -> str:
    if not torch.cuda.is_available():
        return "cpu"
    return f"{torch.cuda.device_count()} x {torch.cuda.get_device_name(0)}"


def _evaluate(cfg: DictConfig, models: dict[str, Path], budget_s: float) -> list[dict]:
    """Rows for every model, in ``models``' order: generate once per model, TTO the SFT output for
    ``sft+tto``. With ``ablation.layouts`` each row's parsed layouts are written to
    ``<layouts>/<row>/<id>.json`` (re-score with ``physcene eval --generator file:DIR``).

    Under accelerate the test prompts are split between the processes for generation (the slow
    part) and gathered in input order; the main process scores, repairs and reports, the others
    return no rows.
    """
    from physcene.eval.harness import (
        generate,
        load_benchmark,
        make_judge,
        method_report,
        repair_outputs,
        save_layouts,
        score_scenes,
    )
    from physcene.physics import PhysicsEngine

    a = cfg.ablation
    state = PartialState()
    items = load_benchmark(str(a.test_split), n=int(a.n_test), seed=int(cfg.seed), progress=False)
    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine(device=str(state.device))
    layouts = a.get("layouts")
    rows, start = [], time.monotonic()

    def add_row(name, outputs, results):
        rows.append(ablation_row(name, method_report(results, outputs)))
        if layouts:  # this run's layouts only: a scene that no longer parses leaves no stale file
            shutil.rmtree(Path(str(layouts)) / name, ignore_errors=True)
            save_layouts(items, outputs, Path(str(layouts)) / name)

    for name, path in models.items():
        with state.split_between_processes(list(range(len(items)))) as shard:
            model = partial(_completions, path, max_new_tokens=int(cfg.eval.max_new_tokens),
                            device=str(state.device), cache=str(cfg.eval.get("cache", "dynamic")),
                            constrained=bool(cfg.eval.get("constrained", False)))
            part = generate([items[i] for i in shard], f"model:{path}", progress=False,
                            generators={f"model:{path}": model})
        outputs = gather_object(part)  # rank order = shard order = input order
        if not state.is_main_process:
            continue
        add_row(name, outputs, score_scenes(items, outputs, judge, engine, progress=False))
        if name == "sft":
            repaired, extras = repair_outputs(outputs, tto_overrides=list(cfg.anchors.tto), engine=engine,
                                              progress=False)
            add_row("sft+tto", repaired,
                    score_scenes(items, repaired, judge, engine, extras=extras, progress=False))
        if time.monotonic() - start > budget_s:  # every rank generates every model: no early exit
            print(f"ablation: eval budget spent after {name}", file=sys.stderr)
    state.wait_for_everyone()
    return rows


def markdown_table(rows: list[dict]) -> str:
    """The ablation rows as a Markdown table (rates in %)."""
    pct = (lambda x: "—" if x is None else f"{100 * x:.1f}%")  # noqa: E731
    num = (lambda x: "—" if x is None else f"{x:.2f}")  # noqa: E731
    lines = ["| method | SCR | ACR | QPR(7) | judge avg | parse rate | n | floating objects |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['name']} | skipped: {r['skipped']} | | | | | | |")
            continue
        lines.append(f"| {r['name']} | {pct(r['scr'])} | {pct(r['acr'])} | {pct(r['qpr7'])} | "
                     f"{num(r['judge_avg'])} | {pct(r['parse_rate'])} | {r['n']} | "
                     f"{pct(r.get('floating'))} |")
    return "\n".join(lines) + "\n"


def level_table(rows: list[dict]) -> str:
    """SCR / ACR of each row per difficulty level (rows without ``by_level`` are left out)."""
    rows = [r for r in rows if r.get("by_level")]
    levels = sorted({lv for r in rows for lv in r["by_level"]}, key=int)
    if not rows:
        return ""
    pct = (lambda x: "—" if x is None else f"{100 * x:.1f}%")  # noqa: E731
    head = " | ".join(f"L{lv} SCR / ACR" for lv in levels)
    lines = [f"| method | {head} |", "|---|" + "---|" * len(levels)]
    for r in rows:
        cells = [f"{pct(f['scr'])} / {pct(f['acr'])} (n={f['n']})" if (f := r["by_level"].get(lv)) else "—"
                 for lv in levels]
        lines.append(f"| {r['name']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run_ablation(cfg: DictConfig, budget_min: float | None = None) -> dict:
    """Run the whole ablation per ``cfg`` (see the module docstring); returns the ablation.json dict."""
    a = cfg.ablation
    budget_s = 60.0 * float(budget_min if budget_min is not None else a.budget_min)
    shares = {**DEFAULT_SHARES, **(OmegaConf.to_container(a.shares) if a.get("shares") else {})}
    stages, t0 = {}, time.monotonic()

    def timed(stage, fn, *args, **kwargs):
        start = time.monotonic()
        result = fn(*args, **kwargs)
        stages[stage] = {"seconds": round(time.monotonic() - start, 1), **stages.get(stage, {})}
        return result

    reuse = bool(a.get("reuse", True))

    def finished(out_dir) -> bool:  # a stage that already wrote its final model (reuse=true)
        # an RL run records its base at the start with complete=false (train/models.py base_checked)
        done = (Path(str(out_dir)) / RUN_INFO).is_file() and read_run_info(out_dir).get("complete", True)
        return reuse and done

    sft_dir = Path(str(cfg.sft.output_dir))
    if finished(sft_dir):
        stages["sft"] = {"reused": True}
    else:
        budget = TimeBudget(shares["sft"] * budget_s)
        sft_dir = timed("sft", run_sft, cfg, callbacks=[budget])
        stages["sft"]["stopped_by_budget"] = budget.stopped_early
    timed("anchors", run_anchors, cfg)
    models = {"sft": sft_dir}
    skipped = []
    names = {"grpo": "grpo", "pada_star": "pada*", "pada": "pada"}
    variants = list(a.get("variants") or names)
    if unknown := [v for v in variants if v not in names]:
        raise TrainingSetupError(f"ablation.variants: unknown variant(s) {unknown}; "
                                 f"expected some of {list(names)}")
    for variant, name in ((v, names[v]) for v in names if v in variants):
        out_dir = OmegaConf.merge(cfg, {"pada": {"variant": variant}}).pada.output_dir
        if finished(out_dir):
            models[name], stages[variant] = Path(str(out_dir)), {"reused": True}
            continue
        budget = TimeBudget(shares[variant] * budget_s)
        try:
            models[name] = timed(variant, run_pada, cfg, variant=variant, callbacks=[budget])
        except NoAnchorsError as exc:  # an SFT model that writes no parsable layout: say so in the table
            skipped.append({"name": name, "skipped": str(exc)})
            continue
        stages[variant]["stopped_by_budget"] = budget.stopped_early
    extra = checkpoint_models(models) if a.get("checkpoints", False) else {}
    evaluated = timed("eval", _evaluate, cfg, {**models, **extra}, shares["eval"] * budget_s)
    rows = [r for r in evaluated if r["name"] not in extra] + skipped
    checkpoint_rows = [r for r in evaluated if r["name"] in extra]
    anchors_summary = Path(str(cfg.anchors.output)).with_suffix(".summary.json")
    result = {
        "rows": rows,
        **({"checkpoint_rows": checkpoint_rows} if extra else {}),
        "gpu": _gpu(),
        "commands": [" ".join(["physcene", *sys.argv[1:]]) if sys.argv[1:] else "run_ablation()"],
        "config": str(cfg.name),
        "budget_min": budget_s / 60.0,
        "total_seconds": round(time.monotonic() - t0, 1),
        "stages": stages,
        "anchors": json.loads(anchors_summary.read_text()) if anchors_summary.is_file() else None,
        "decoding": {"eval": "constrained" if cfg.eval.get("constrained", False) else "greedy",
                     "anchors": "constrained" if cfg.anchors.get("constrained", False) else "greedy",
                     "pada": "constrained" if cfg.pada.get("constrained", False) else "sampled",
                     "cache": str(cfg.eval.get("cache", "dynamic"))},
    }
    if PartialState().is_main_process:
        out = Path(str(a.output))
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1))
        every = rows + checkpoint_rows
        out.with_suffix(".md").write_text(markdown_table(every) + "\n" + level_table(every))
    return result
