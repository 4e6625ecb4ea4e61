"""The evaluation harness: benchmark items -> generator -> (optional TTO) -> physics + judge ->
:class:`~physcene.eval.metrics.SceneResult` per scene -> reports.

Generators (``--generator``): ``reference`` (the split's layouts), ``tto`` (reference + TTO),
``heuristic`` (non-learned placer), ``file:DIR`` (layouts on disk; or ``file:FILE.jsonl[.gz]``, one
``{"id", "layout"}`` record per scene as the training ablation writes them), ``model:PATH`` (a trained
checkpoint: the caller passes its :data:`Generate` callable, e.g. ``physcene eval`` builds one on
:func:`physcene.train.generate.generate`; the harness never imports the training code),
``endpoint:URL`` (zero-shot LLM with the paper's Prompt 3 over an OpenAI-compatible endpoint). Any
of them can be followed by TTO (``repair=true``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from physcene.ctrc import ParseError, parse
from physcene.data import synthesize
from physcene.data.splits import DEFAULT_SIZES
from physcene.eval.baselines import heuristic_place, zero_shot_prompt
from physcene.eval.endpoint import EndpointError, EndpointJudge, chat_url, post_chat, reply_text
from physcene.eval.judges import EvalCase, LayoutStats, RuleJudge
from physcene.eval.metrics import (
    ScenePhysics,
    SceneResult,
    breakdown,
    diversity,
    paired_collisions,
    physics_from_score,
    summarize,
)
from physcene.eval.render import render_views
from physcene.eval.report import method_slug, write_report
from physcene.files import write_atomic
from physcene.layout import load_layout, read_layout, records_by_id, write_layout
from physcene.scene import Scene, SceneError
from physcene.tto import TTOConfig, relation_preservation, repair

__all__ = ["BenchmarkItem", "EvalError", "Generate", "GenerationFailure", "evaluate_method", "generate",
           "load_benchmark", "make_judge", "method_name", "method_names", "method_report", "repair_outputs",
           "run_evaluation", "save_layouts", "score_scenes", "write_json"]

GENERATOR_KINDS = ("reference", "tto", "heuristic", "file:", "model:", "endpoint:")


class EvalError(ValueError):
    """Bad evaluation input: an unknown generator, a missing layout directory ..."""


@dataclass(frozen=True)
class BenchmarkItem:
    """One benchmark request with its reference layout."""

    id: str
    scene_type: str
    level: int
    instruction: str
    prompt: str
    reference: Scene
    case: EvalCase


def load_benchmark(split: str, n: int | None = None, seed: int = 0,
                   progress: bool = True) -> list[BenchmarkItem]:
    """The first ``n`` records of a synthetic split (``train``/``test``/``ood``) from
    :func:`physcene.data.synthesize`, as benchmark items."""
    items = []
    records = synthesize(split, n=n, seed=seed)
    total = n if n is not None else DEFAULT_SIZES.get(split)
    for rec in tqdm(records, total=total, desc=f"synthesise {split}", disable=not progress, unit="scene"):
        scene = load_layout(rec["layout"], source=f"{split}:{rec['id']}")
        if not scene.scene_type:
            scene = scene.__class__(scene.zone, scene.objects, rec["scene_type"], rec["instruction"],
                                    scene.restricted_zones, scene.meta)
        items.append(BenchmarkItem(str(rec["id"]), rec["scene_type"], int(rec["level"]), rec["instruction"],
                                   rec.get("prompt", ""), scene, EvalCase.from_reference(scene)))
    return items


def _with_request(scene: Scene, item: BenchmarkItem) -> Scene:
    """A generated scene carrying the request's type and instruction (what judges read)."""
    return scene.__class__(scene.zone, scene.objects, item.scene_type, item.instruction,
                           scene.restricted_zones or item.reference.restricted_zones, scene.meta)


def _load_dir(items: Sequence[BenchmarkItem], directory: Path) -> list:
    """Layouts from ``DIR``: ``<id>.json`` / ``<id>/layout.json`` (MesaTask) or ``<id>.txt`` (a
    model completion, CTRC or Prompt-3 flat JSON). A missing file is an error naming the id."""
    if not directory.is_dir():
        raise EvalError(f"generator file:{directory}: not a directory")
    out = []
    for it in items:
        for cand in (directory / f"{it.id}.json", directory / it.id / "layout.json"):
            if cand.is_file():
                out.append(read_layout(cand))
                break
        else:
            txt = directory / f"{it.id}.txt"
            if not txt.is_file():
                raise EvalError(f"generator file:{directory}: no layout for benchmark id {it.id!r} "
                                f"(looked for {it.id}.json, {it.id}/layout.json, {it.id}.txt)")
            out.append(parse(txt.read_text(), zone=it.reference.zone))
    return out


@dataclass(frozen=True)
class GenerationFailure(ParseError):
    """No output for an item: the generator's request failed (an endpoint's error after its retries).
    Not a model output: it is counted as a failed generation (``generation_failures``), never
    parsed, repaired or scored; it fails QPR like an unparsable output."""


def _load_records(items: Sequence[BenchmarkItem], path: Path) -> list:
    """Layouts from a JSONL file (gzipped when it ends in ``.gz``) of ``{"id", "layout"}`` records; a
    record whose ``layout`` is null is the completion that did not parse (its ``parse_error``).
    A split's ids are positions in its draw, and the draw depends on ``n`` and the seed: a record whose
    level or layout instruction is not its scene's was written for another draw and is refused."""
    if not path.is_file():
        raise EvalError(f"generator file:{path}: no such file")
    by_id = records_by_id(path, error=EvalError, prefix="generator file:")
    out = []
    for it in items:
        if it.id not in by_id:
            raise EvalError(f"generator file:{path}: no layout for benchmark id {it.id!r}")
        number, record = by_id[it.id]
        layout = record.get("layout")
        instruction = layout.get("instruction") if isinstance(layout, dict) else None
        if record.get("level", it.level) != it.level or (instruction and instruction != it.instruction):
            raise EvalError(f"generator file:{path}:{number}: the record of {it.id!r} is of another scene "
                            f"(level {record.get('level')}, instruction {str(instruction)[:50]!r}; the "
                            f"split's: level {it.level}, {it.instruction[:50]!r}): it was written for "
                            "another draw of the split (score it with the --n and --seed it was made with)")
        if layout is None:
            out.append(ParseError(str(record.get("parse_error") or "no layout in the record")))
            continue
        try:
            out.append(load_layout(layout, source=f"{path}:{number}"))
        except (SceneError, TypeError, ValueError) as exc:
            raise EvalError(f"generator file:{path}:{number}: {exc}") from None
    return out


def _zero_shot(items: Sequence[BenchmarkItem], url: str, model: str, api_key_env: str,
               progress: bool, retries: int = 4) -> list:
    """The endpoint's Prompt-3 replies, parsed. The first request failing (after its retries) is an
    EvalError: the endpoint is down or wrongly named, and a table of failures would look like a
    result. A later failed request is a :class:`GenerationFailure` for its item."""
    endpoint = chat_url(url)
    out = []
    for it in tqdm(items, desc="zero-shot LLM", disable=not progress, unit="scene"):
        payload = {"model": model, "temperature": 0.0,
                   "messages": [{"role": "user", "content": zero_shot_prompt(it.reference)}]}
        try:
            text = reply_text(post_chat(endpoint, payload, api_key=os.environ.get(api_key_env),
                                        retries=retries))
        except EndpointError as exc:
            if all(isinstance(o, GenerationFailure) for o in out):  # nothing has answered yet
                raise EvalError(f"generator endpoint:{url}: {exc.reason}") from None
            out.append(GenerationFailure(f"endpoint request failed: {exc}"))
            continue
        out.append(parse(text, zone=it.reference.zone))
    return out


Generate = Callable[[Sequence[BenchmarkItem]], list]
"""A generator the caller supplies: benchmark items -> one output per item, a Scene, a ParseError
or a completion text (parsed against the item's zone)."""


def generate(items: Sequence[BenchmarkItem], generator: str, *, seed: int = 0, model: str = "gpt-4o",
             api_key_env: str = "PHYSCENE_GENERATOR_API_KEY", progress: bool = True,
             generators: Mapping[str, Generate] | None = None, retries: int = 4) -> list:
    """One output per item: a Scene, a ParseError (model output that did not parse) or a
    :class:`GenerationFailure` (an ``endpoint:URL`` request that failed after ``retries`` retries).

    ``generators``: callables by generator argument (``"model:runs/sft"``), looked up before the
    built-in kinds; a ``model:PATH`` generator must be one of them.
    """
    if generators and generator in generators:
        out = [parse(o, zone=it.reference.zone) if isinstance(o, str) else o
               for o, it in zip(generators[generator](items), items)]
    elif generator in ("reference", "tto"):
        out = [it.reference for it in items]
    elif generator == "heuristic":

        out = [heuristic_place(it.reference, seed=seed * 100003 + k) for k, it in enumerate(items)]
    elif generator.startswith("file:"):
        target = Path(generator[5:])
        records = target.name.endswith((".jsonl", ".jsonl.gz"))
        out = _load_records(items, target) if records else _load_dir(items, target)
    elif generator.startswith("model:"):
        raise EvalError(f"generator {generator}: no model generator was passed (generators=...); "
                        "physcene eval builds one from the checkpoint")
    elif generator.startswith("endpoint:"):
        out = _zero_shot(items, generator[9:], model, api_key_env, progress, retries)
    else:
        raise EvalError(f"unknown generator {generator!r}; expected one of reference, tto, heuristic, "
                        "file:DIR, model:PATH, endpoint:URL")
    return [o if isinstance(o, ParseError) else _with_request(o, it) for o, it in zip(out, items)]


def save_layouts(items: Sequence[BenchmarkItem], outputs: Sequence, directory: Path) -> int:
    """Write each parsed output as ``directory/<id>.json`` (MesaTask layout), re-scorable with
    ``--generator file:DIR``; outputs that did not parse are skipped. Returns how many were written."""
    written = 0
    for it, scene in zip(items, outputs):
        if isinstance(scene, Scene):
            write_layout(scene, Path(directory) / f"{it.id}.json")
            written += 1
    return written


def repair_outputs(outputs: list, *, tto_overrides: Sequence[str] = (), engine=None,
                   progress: bool = True) -> tuple[list, list[dict]]:
    """TTO over every parsed output (ParseErrors pass through). Returns (outputs, per-scene
    extras: energy before/after, max displacement, relation preservation)."""
    config = TTOConfig.load(list(tto_overrides))
    idx = [k for k, o in enumerate(outputs) if isinstance(o, Scene)]
    extras: list[dict] = [{} for _ in outputs]
    out = list(outputs)
    step = max(1, int(getattr(config, "batch_size", 16)))
    for start in tqdm(range(0, len(idx), step), desc="TTO repair", disable=not progress, unit="batch"):
        chunk = idx[start:start + step]
        for k, res in zip(chunk, repair([outputs[k] for k in chunk], config=config, engine=engine)):
            kept = relation_preservation(outputs[k], res.scene)
            out[k] = res.scene
            extras[k] = {"tto_energy_before": float(res.energy_before),
                         "tto_energy_after": float(res.energy_after),
                         "tto_max_displacement_cm": float(res.max_displacement_cm),
                         "relation_preservation": float(kept.get("in_on_kept", float("nan")))}
    return out, extras


def make_judge(kind: str, references: Sequence[Scene], *, url: str | None = None, model: str = "gpt-4o",
               cache_dir: str | None = None, image_size: Sequence[int] = (512, 384), retries: int = 4):
    """``rule`` (fitted on ``references``) or ``endpoint`` (needs ``url``; renders of
    ``image_size`` = (width, height) px; a failed request is retried ``retries`` times)."""
    if kind == "rule":
        return RuleJudge(LayoutStats.fit(references))
    if kind == "endpoint":
        if not url:
            raise EvalError("judge=endpoint needs judge_url=http://host:port/v1")
        size = (int(image_size[0]), int(image_size[1]))
        return EndpointJudge(url, model=model, cache_dir=cache_dir, image_size=size, retries=retries)
    raise EvalError(f"unknown judge {kind!r}; expected rule or endpoint")


def score_scenes(items: Sequence[BenchmarkItem], outputs: Sequence, judge, engine=None, *,
                 batch_size: int = 16, settle: bool = False, extras: Sequence[dict] | None = None,
                 progress: bool = True, desc: str = "score") -> list[SceneResult]:
    """Physics (engine, batched) + judge (+ optional MuJoCo settling) for every output.

    A judge request that fails before any judgement succeeded, or every judgement failing, is an
    EvalError naming the judge (its endpoint is down, or answers no scores); a judgement failing
    later is a value (``{"error": ..}``), counted as ``judge_failures``."""
    if engine is None:
        from physcene.physics import PhysicsEngine  # here: Warp loads only when an engine is needed

        engine = PhysicsEngine()
    extras = list(extras) if extras is not None else [{} for _ in outputs]
    scenes_idx = [k for k, o in enumerate(outputs) if isinstance(o, Scene) and len(o)]
    physics: dict[int, ScenePhysics] = {}
    bar = tqdm(total=len(outputs), desc=desc, disable=not progress, unit="scene")
    for start in range(0, len(scenes_idx), batch_size):
        chunk = scenes_idx[start:start + batch_size]
        scenes = [outputs[k] for k in chunk]
        for k, ph in zip(chunk, physics_from_score(scenes, engine.score(scenes))):
            physics[k] = ph
        bar.update(len(chunk))
    results = []
    judged, judge_errors = 0, []
    for k, (it, out) in enumerate(zip(items, outputs)):
        extra = dict(extras[k])
        if k not in physics:  # unparsed, failed or empty: counted here, the engine never saw it
            bar.update(1)
        if isinstance(out, GenerationFailure):
            extra["generation_error"] = out.reason
            failed = {"error": f"generation failed: {out.reason}", "avg": float("nan")}
            results.append(SceneResult(it.id, it.scene_type, it.level, ScenePhysics(0), failed, extra))
            continue
        if isinstance(out, ParseError):
            extra["parse_error"] = out.reason
            failed = {"error": f"unparsable output: {out.reason}", "avg": float("nan")}
            results.append(SceneResult(it.id, it.scene_type, it.level, ScenePhysics(0), failed, extra))
            continue
        ph = physics.get(k, ScenePhysics(len(out)))
        if settle and len(out):
            from physcene.settle import settle as settle_scene  # here: MuJoCo only for the stability column

            extra["stable"] = bool(settle_scene(out).stable)
        scores = judge.score(out, it.case, ph)
        if "error" not in scores:
            judged += 1
        elif scores.get("request_failed") and not judged:
            raise EvalError(f"judge {judge.name}: {scores['error']}")
        else:
            judge_errors.append(scores["error"])
        results.append(SceneResult(it.id, it.scene_type, it.level, ph, scores, extra))
    bar.close()
    if judge_errors and not judged:
        raise EvalError(f"judge {judge.name}: none of {len(judge_errors)} judgements gave scores; the "
                        f"first: {judge_errors[0]}")
    return results


def method_report(results: Sequence[SceneResult], outputs: Sequence) -> dict:
    """summary, per-level and per-type breakdowns and diversity of one method's results."""
    scenes = [o for o in outputs if isinstance(o, Scene)]
    return {"summary": summarize(results), "by_level": breakdown(results, "level"),
            "by_type": breakdown(results, "scene_type"), "diversity": diversity(scenes),
            "scenes": [r.to_dict() for r in results]}


def evaluate_method(items: Sequence[BenchmarkItem], generator: str, judge, *, engine=None,
                    repair: bool = False, tto_overrides: Sequence[str] = (), settle: bool = False,
                    seed: int = 0, progress: bool = True, **generator_options) -> tuple[dict, list]:
    """Generate (+ repair) and score one method. Returns (its report dict, its outputs).

    ``generator_options``: passed to :func:`generate` (``model``, ``generators`` ...)."""
    outputs = generate(items, generator, seed=seed, progress=progress, **generator_options)
    extras = None
    if repair or generator == "tto":
        outputs, extras = repair_outputs(outputs, tto_overrides=tto_overrides, engine=engine,
                                         progress=progress)
    results = score_scenes(items, outputs, judge, engine, settle=settle, extras=extras, progress=progress,
                           desc=f"score {generator}")
    return method_report(results, outputs), outputs


def write_json(path: Path, data) -> None:
    """JSON with NaN written as null (strict JSON readers reject NaN), renamed into place when complete."""
    def clean(x):
        if isinstance(x, float) and not np.isfinite(x):
            return None
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, np.generic):
            return clean(x.item())
        return x

    write_atomic(path, json.dumps(clean(data), indent=1))


def method_name(generator: str, repair: bool = False, *, whole_argument: bool = False) -> str:
    """A table row label: ``Reference``, ``Reference + TTO``, ``Heuristic placer``, ``Model (sft)``
    (the last folder of a path; ``whole_argument``: ``Model (runs/a/sft)``) ..."""
    if generator == "tto":
        return "Reference + TTO"
    base = {"reference": "Reference", "heuristic": "Heuristic placer"}.get(generator)
    if base is None:
        kind, _, arg = generator.partition(":")
        base = {"file": "Layouts", "model": "Model", "endpoint": "Zero-shot LLM"}.get(kind, kind)
        arg = arg.rstrip("/") if whole_argument else (Path(arg.rstrip("/")).name or arg)
        base = f"{base} ({arg})"
    return base + (" + TTO" if repair else "")


def method_names(generators: Sequence[str], repair: bool = False) -> list[str]:
    """:func:`method_name` of each generator, made unique: two whose short labels meet (``model:a/sft``
    and ``model:b/sft`` are both "Model (sft)") are labelled with their whole argument instead, so
    neither row overwrites the other. The same generator listed twice is an error."""
    if len(set(generators)) < len(generators):
        twice = sorted({g for g in generators if generators.count(g) > 1})
        raise EvalError(f"generator(s) listed twice: {', '.join(twice)}")
    short = [method_name(g, repair) for g in generators]
    return [method_name(g, repair, whole_argument=True) if short.count(name) > 1 else name
            for g, name in zip(generators, short)]


def run_evaluation(cfg, *, command: str = "", title: str = "physcene evaluation",
                   progress: bool = True,
                   generators: Mapping[str, Generate] | None = None) -> tuple[dict, Path]:
    """The whole ``physcene eval`` job for a config (configs/eval.yaml): benchmark, every
    generator in ``cfg.generator`` (comma-separated), scoring, renders, results.json and
    report.md under ``cfg.out``. ``generators``: the callables of the ``model:PATH`` generators
    (see :func:`generate`). Returns (the methods' reports, the report path)."""

    from physcene.physics import PhysicsEngine  # here: Warp loads only when an engine is needed

    specs = [g.strip() for g in str(cfg.generator).split(",") if g.strip()]
    if not specs:
        raise EvalError("no generator given")
    for g in specs:
        if not (g in GENERATOR_KINDS or g.startswith(GENERATOR_KINDS[3:])):
            raise EvalError(f"unknown generator {g!r}; expected reference, tto, heuristic, file:DIR, "
                            "model:PATH or endpoint:URL")
    if cfg.split not in ("train", "test", "ood"):
        raise EvalError(f"unknown split {cfg.split!r}; expected test, ood or train")
    out = Path(cfg.out)
    retries = cfg.get("endpoint_retries", 4)
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise EvalError(f"endpoint_retries must be an integer >= 0, got {retries!r}")
    items = load_benchmark(cfg.split, n=cfg.n, seed=cfg.seed, progress=progress)
    if not items:
        raise EvalError(f"split {cfg.split!r} gave no scenes")
    judge = make_judge(cfg.judge, [it.reference for it in items], url=cfg.judge_url,
                       model=cfg.judge_model, cache_dir=cfg.judge_cache or str(out / "judge_cache"),
                       image_size=cfg.get("judge_image_size", (512, 384)), retries=retries)
    device = str(cfg.get("device", "cpu"))
    engine = PhysicsEngine(device=device)
    # TTO optimises on the engine's device unless the tto overrides say otherwise.
    tto_overrides = list(cfg.tto)
    if not any(o.startswith("device=") for o in tto_overrides):
        tto_overrides.insert(0, f"device={device}")
    # The results of an older run must not sit beside this run's layouts and renders: gone until
    # this run's are complete (results.json, written last, is what says so).
    for old in (out / "results.json", out / "report.md"):
        old.unlink(missing_ok=True)
    methods: dict[str, dict] = {}
    renders: dict[str, dict[str, str]] = {}
    n_render = min(int(cfg.render), len(items))
    for gen, name in zip(specs, method_names(specs, bool(cfg.repair))):
        report, outputs = evaluate_method(items, gen, judge, engine=engine, repair=bool(cfg.repair),
                                          tto_overrides=tto_overrides, settle=bool(cfg.settle),
                                          seed=cfg.seed, progress=progress, model=cfg.generator_model,
                                          generators=generators, retries=retries)
        methods[name] = report
        slug = method_slug(name)
        if cfg.get("save_layouts", False):  # re-score later with --generator file:<out>/layouts/<slug>
            save_layouts(items, outputs, out / "layouts" / slug)
        todo = list(zip(items, outputs))[:n_render]
        for it, scene in tqdm(todo, desc=f"render {name}", disable=not progress, unit="scene"):
            if not isinstance(scene, Scene) or not len(scene):
                continue
            paths = render_views(scene, out / "renders" / slug, prefix=f"{it.id}_",
                                 size=tuple(cfg.render_size))
            for view, p in paths.items():
                renders.setdefault(it.id, {})[f"{name} {view}"] = str(p.relative_to(out))
    tables = {k: {kk: vv for kk, vv in v.items() if kk != "scenes"} for k, v in methods.items()}
    names = list(methods)
    first = [SceneResult.from_dict(d) for d in methods[names[0]]["scenes"]]
    for name in names[1:]:  # every method against the first, scene by scene
        second = [SceneResult.from_dict(d) for d in methods[name]["scenes"]]
        methods[name]["paired"] = tables[name]["paired"] = {"against": names[0],
                                                            **paired_collisions(first, second)}
    path = write_report(out, tables, title=title, command=command, renders=renders,
                        labels=bool(cfg.get("render_labels", False)))
    write_json(out / "results.json", {"split": cfg.split, "n": len(items), "judge": cfg.judge,
                                      "generators": specs, "repair": bool(cfg.repair),
                                      "methods": methods})
    return tables, path
