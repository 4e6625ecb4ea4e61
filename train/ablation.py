"""The paper's ablation (Table "CTRC / +GRPO / +TTO / +PADA* / +PADA") end to end, within a time budget.

``run_ablation(cfg, budget_min)`` runs SFT -> anchors -> ``grpo``, ``pada_star``, ``pada`` -> eval of
SFT, SFT + TTO, GRPO, PADA* and PADA on the test split with the eval harness (rule judge), and writes
``ablation.json`` ``{"rows": [{name, scr, acr, qpr7, judge_avg, parse_rate, n}], "gpu", "commands",
"stages"}`` plus a Markdown table. Each stage gets a share of the budget (``ablation.shares``); a
training stage that runs out of time stops at its next optimizer step and saves (``TimeBudget``), so
the table always comes out, with the time each stage took recorded under ``stages`` (and the steps
it ran in each model's ``physcene_run.json``). With ``ablation.reuse`` (default) a stage whose final
model exists is not rerun, so the pipeline can be driven by repeated commands under a job time limit.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from physcene.train.models import RUN_INFO
from physcene.train.sft import TimeBudget

__all__ = ["ROW_NAMES", "TimeBudget", "ablation_row", "run_ablation"]

ROW_NAMES = ("sft", "sft+tto", "grpo", "pada*", "pada")
DEFAULT_SHARES = {"sft": 0.45, "anchors": 0.10, "grpo": 0.10, "pada_star": 0.10, "pada": 0.10, "eval": 0.15}


def ablation_row(name: str, report: dict) -> dict:
    """One table row from an eval-harness method report (SCR/ACR at 0 cm, QPR at τ = 7)."""
    s = report["summary"]
    collision = s["collision"].get(0.0, s["collision"].get("0.0", {}))
    qpr = s["QPR"].get(7.0, s["QPR"].get("7.0"))
    n = int(s["n"])

    def finite(x):  # NaN (no parsed layout to measure) -> null in JSON, "—" in the table
        return None if x is None or x != x else float(x)

    return {"name": name, "scr": finite(collision.get("SCR")), "acr": finite(collision.get("ACR")),
            "qpr7": finite(qpr), "judge_avg": finite(s["judge"]["avg"]),
            "parse_rate": (n - int(s.get("parse_errors", 0))) / max(n, 1), "n": n,
            "parse_error_kinds": [list(k) for k in s.get("parse_error_kinds", [])]}


def _gpu() -> str:
    import torch

    if not torch.cuda.is_available():
        return "cpu"
    return f"{torch.cuda.device_count()} x {torch.cuda.get_device_name(0)}"


def _evaluate(cfg: DictConfig, models: dict[str, Path], budget_s: float) -> list[dict]:
    """Rows for every model: generate once per model, TTO the SFT output for ``sft+tto``.

    Under accelerate the test prompts are split between the processes for generation (the slow
    part) and gathered in input order; the main process scores, repairs and reports, the others
    return no rows.
    """
    from accelerate import PartialState
    from accelerate.utils import gather_object
    from physcene.eval.harness import (
        generate,
        load_benchmark,
        make_judge,
        method_report,
        repair_outputs,
        score_scenes,
    )

    from physcene.physics import PhysicsEngine

    a = cfg.ablation
    state = PartialState()
    items = load_benchmark(str(a.test_split), n=int(a.n_test), seed=int(cfg.seed), progress=False)
    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine(device=str(state.device))
    rows, start = [], time.monotonic()
    for name in ROW_NAMES:
        if name == "sft+tto" or name not in models:
            continue
        with state.split_between_processes(list(range(len(items)))) as shard:
            part = generate([items[i] for i in shard], f"model:{models[name]}", progress=False,
                            max_new_tokens=int(cfg.eval.max_new_tokens), device=str(state.device),
                            cache=str(cfg.eval.get("cache", "dynamic")),
                            constrained=bool(cfg.eval.get("constrained", False)))
        outputs = gather_object(part)  # rank order = shard order = input order
        if not state.is_main_process:
            continue
        results = score_scenes(items, outputs, judge, engine, progress=False)
        rows.append(ablation_row(name, method_report(results, outputs)))
        if name == "sft":
            repaired, extras = repair_outputs(outputs, tto_overrides=list(cfg.anchors.tto), engine=engine,
                                              progress=False)
            results = score_scenes(items, repaired, judge, engine, extras=extras, progress=False)
            rows.append(ablation_row("sft+tto", method_report(results, repaired)))
        if time.monotonic() - start > budget_s:
            print(f"ablation: eval budget spent after {name}", file=sys.stderr)
    state.wait_for_everyone()
    return rows


def markdown_table(rows: list[dict]) -> str:
    """The ablation rows as a Markdown table (rates in %)."""
    pct = (lambda x: "—" if x is None else f"{100 * x:.1f}%")  # noqa: E731
    num = (lambda x: "—" if x is None else f"{x:.2f}")  # noqa: E731
    lines = ["| method | SCR | ACR | QPR(7) | judge avg | parse rate | n |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {r['name']} | skipped: {r['skipped']} | | | | | |")
            continue
        lines.append(f"| {r['name']} | {pct(r['scr'])} | {pct(r['acr'])} | {pct(r['qpr7'])} | "
                     f"{num(r['judge_avg'])} | {pct(r['parse_rate'])} | {r['n']} |")
    return "\n".join(lines) + "\n"


def run_ablation(cfg: DictConfig, budget_min: float | None = None) -> dict:
    """Run the whole ablation per ``cfg`` (see the module docstring); returns the ablation.json dict."""
    from physcene.train.anchors import run_anchors
    from physcene.train.pada import NoAnchorsError, run_pada
    from physcene.train.sft import run_sft

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
        return reuse and (Path(str(out_dir)) / RUN_INFO).is_file()

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
    for variant, name in (("grpo", "grpo"), ("pada_star", "pada*"), ("pada", "pada")):
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
    rows = timed("eval", _evaluate, cfg, models, shares["eval"] * budget_s) + skipped
    anchors_summary = Path(str(cfg.anchors.output)).with_suffix(".summary.json")
    result = {
        "rows": rows,
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
    from accelerate import PartialState

    if PartialState().is_main_process:
        out = Path(str(a.output))
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1))
        out.with_suffix(".md").write_text(markdown_table(rows))
    return result
