"""The paper's ablation (Table "CTRC / +GRPO / +TTO / +PADA* / +PADA") end to end, within a time budget.

``run_ablation(cfg, budget_min)`` runs SFT -> anchors -> ``grpo``, ``pada_star``, ``pada`` -> eval of
the reference, SFT, SFT + TTO, GRPO, PADA* and PADA on the test split with the eval harness (rule
judge; the split's draw is ``ablation.test_seed`` whatever the run's seed, so rows of every seed score
the same scenes), and writes ``ablation.json`` ``{"rows": [{name, seed, rl_steps, scr, acr, qpr7,
qpr8, qpr9, judge_avg, parse_rate, floating, shrunk, out_of_zone, layouts, n, by_level}], "gpu",
"commands", "stages", "test_split"}`` (:data:`ROW_KEYS`; rates and shares as fractions) plus Markdown
tables (all levels; SCR / ACR per level) and the learning curves (:mod:`physcene.train.ablation_plot`).
``ablation.variants`` picks the RL rows; ``ablation.checkpoints`` adds a row per kept intermediate
checkpoint of them (``"pada@12"``, under ``checkpoint_rows``, ``rl_steps`` 12: the metrics against RL
steps); ``ablation.validation`` (N scenes of another draw of the split, ``ablation.validation_seed``)
gives every model row its ``val_scr`` and ``val_parse_rate`` and marks the row of each RL run with the
most clean validation scenes ``chosen``, so the kept checkpoint is picked without reading the test split;
``ablation.layouts`` keeps every row's layouts as ``<layouts>/<row>.jsonl.gz`` (one ``{"id", "layout"}``
record per scene, ``layout`` null and ``parse_error`` set where the output did not parse), which
``physcene check`` and ``physcene eval --generator file:...`` read to recompute the row
(``ablation.reference`` adds the reference layouts' row). Each stage gets a share of the budget
(``ablation.shares``); a training stage that runs out of time stops at its next optimizer step and
saves (``TimeBudget``), so the table always comes out, with the time each stage took recorded under
``stages`` (and the steps it ran in each model's ``physcene_run.json``). With ``ablation.reuse``
(default) a stage whose final model exists is not rerun, so the pipeline can be driven by repeated
commands under a job time limit.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib
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

from physcene.artifacts import ArtifactError, checkpoint_digest, file_sha256, repo_root
from physcene.files import write_atomic
from physcene.layout import layout_to_dict, row_file, write_layout_records
from physcene.reward import RewardConfig, band_low_ratio
from physcene.scene import Scene
from physcene.train.ablation_plot import write_learning_curves
from physcene.train.anchors import anchor_nll, run_anchors
from physcene.train.generate import generate as checkpoint_generate
from physcene.train.generate import sampling
from physcene.train.models import RUN_INFO, TrainingSetupError, read_run_info
from physcene.train.pada import NoAnchorsError, run_pada
from physcene.train.records import load_records
from physcene.train.sft import TimeBudget, run_sft

__all__ = ["ROW_KEYS", "ROW_NAMES", "TimeBudget", "ablation_row", "ablation_variants", "check_ablation",
           "checkpoint_models", "evaluation_split", "layout_records", "level_table", "mark_chosen",
           "markdown_table", "merge_ablations", "row_file", "run_ablation", "shrunk_share", "table_figures",
           "table_row", "validation_split", "write_ablation"]

ROW_NAMES = ("reference", "sft", "sft+tto", "grpo", "pada*", "pada")
# Every row of ablation.json has these (shares and rates as fractions, null where nothing parsed).
ROW_KEYS = ("name", "seed", "rl_steps", "scr", "acr", "qpr7", "qpr8", "qpr9", "judge_avg", "parse_rate",
            "floating", "shrunk", "out_of_zone", "layouts")
_FRACTIONS = ("scr", "acr", "qpr7", "qpr8", "qpr9", "parse_rate", "floating", "shrunk", "out_of_zone")
_VARIANTS = {"grpo": "grpo", "pada_star": "pada*", "pada": "pada"}  # ablation.variants -> row name
_RL_ROWS = tuple(_VARIANTS.values())
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


def _finite(x):
    return None if x is None or x != x else float(x)


def shrunk_share(scenes: list, engine, config: RewardConfig | None = None) -> float | None:
    """The share of the objects of ``scenes`` that reward.valid_terms' ``shrunk`` names: a dimension
    below ``shrink_ratio`` x the low edge of its category's size band (None without objects)."""
    config = config or RewardConfig()
    scenes = [s for s in scenes if len(s)]
    if not scenes:
        return None
    batch = engine.pack(scenes)
    mask = batch.mask.cpu().numpy()
    shrunk = (band_low_ratio(batch, config.size_tolerance) < config.shrink_ratio) & mask
    return float(shrunk.sum() / mask.sum())


def table_figures(report: dict, outputs: list, engine) -> dict:
    """What :func:`ablation_row` leaves out of the table's schema: QPR at τ = 8 and 9 and the shares
    of out-of-zone and shrunk objects."""
    s = report["summary"]
    qpr = {float(k): v for k, v in s["QPR"].items()}
    return {"qpr8": _finite(qpr.get(8.0)), "qpr9": _finite(qpr.get(9.0)),
            "out_of_zone": _finite(s.get("out_of_zone", {}).get("objects")),
            "shrunk": shrunk_share([o for o in outputs if isinstance(o, Scene)], engine)}


def layout_records(items, outputs) -> list[dict]:
    """One ``{"id", "level", "scene_type", "layout"}`` record per benchmark item (MesaTask layout;
    null with ``parse_error`` where the output did not parse), the form ``file:X.jsonl.gz`` reads."""
    out = []
    for it, o in zip(items, outputs):
        record = {"id": it.id, "level": it.level, "scene_type": it.scene_type}
        if isinstance(o, Scene):
            record["layout"] = layout_to_dict(o)
        else:
            record.update(layout=None, parse_error=str(o))
        out.append(record)
    return out


def _repository_path(path: Path) -> str:
    """``path`` relative to the checkout it lies in (the row's ``layouts``), else as given."""
    path = path.resolve()
    for parent in path.parents:
        if (parent / ".git").exists():
            return path.relative_to(parent).as_posix()
    return str(path)


def table_row(name: str, items, outputs: list, results, engine, *, seed: int, rl_steps: int,
              layouts: Path | None = None) -> dict:
    """One row of the table (:data:`ROW_KEYS`, with ``n``, ``by_level`` and the parse error kinds) from
    the eval harness's results of ``outputs``; with ``layouts`` (a folder) the outputs are written
    to ``<layouts>/<row>.jsonl.gz`` and the row names that file by its repository path."""
    from physcene.eval.harness import method_report

    report = method_report(results, outputs)
    row = {**ablation_row(name, report), "seed": seed, "rl_steps": rl_steps,
           **table_figures(report, outputs, engine), "layouts": None}
    if layouts is not None:
        path = write_layout_records(layout_records(items, outputs), Path(layouts) / row_file(name))
        row["layouts"] = _repository_path(path)
    return row


def check_ablation(data: dict, source: str = "ablation.json") -> dict:
    """``data`` if it has the table's schema (``rows`` of :data:`ROW_KEYS`, ``gpu``, ``commands``),
    else a ValueError naming the row and the key."""
    for key in ("rows", "gpu", "commands"):
        if key not in data:
            raise ValueError(f"{source}: no {key!r}")
    for k, row in enumerate([*data["rows"], *data.get("checkpoint_rows", [])]):
        where = f"{source}: row {k} ({row.get('name', '?')})"
        if "skipped" in row:
            continue
        missing = [key for key in ROW_KEYS if key not in row]
        if missing:
            raise ValueError(f"{where} lacks {missing}")
        if row["name"].split("@")[0] not in ROW_NAMES:
            raise ValueError(f"{where}: name must be one of {list(ROW_NAMES)} (@N for a checkpoint)")
        for key in [k for k in (*_FRACTIONS, "val_scr", "val_parse_rate") if k in row]:  # val_*: validation
            if row[key] is not None and not _is_fraction(row[key]):
                raise ValueError(f"{where}: {key} must be a fraction in [0, 1] or null, got {row[key]!r}")
        if "chosen" in row and not isinstance(row["chosen"], bool):
            raise ValueError(f"{where}: chosen must be true or false, got {row['chosen']!r}")
    return data


def _is_fraction(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and 0.0 <= x <= 1.0


def mark_chosen(rows: list[dict]) -> list[dict]:
    """``rows`` with ``chosen`` on every row of an RL run that validation scored (``grpo``, ``pada*``,
    ``pada`` and their ``name@N`` checkpoints, per seed): true on the row with the most clean validation
    scenes, false on the others. The kept checkpoint is thereby picked on the validation draw, never on
    the test split it is reported on. A clean scene parsed and collides nowhere: the share is
    ``(1 - val_scr) * val_parse_rate``, so a checkpoint cannot be picked for a low SCR over the few
    layouts it still writes (SCR counts parsed scenes only). Ties go to the later step (more training
    at the same figure); a row where nothing parsed ranks last."""
    runs: dict[tuple, list[int]] = {}
    for k, row in enumerate(rows):
        if "val_scr" in row and row["name"].split("@")[0] in _RL_ROWS:
            runs.setdefault((row["name"].split("@")[0], row.get("seed")), []).append(k)

    def rank(k: int) -> tuple:
        scr, parsed = rows[k]["val_scr"], rows[k].get("val_parse_rate", 1.0)
        clean = 0.0 if scr is None else (1.0 - scr) * parsed
        return scr is None, -clean, -int(rows[k].get("rl_steps") or 0)

    chosen = {min(members, key=rank) for members in runs.values()}
    scored = {k for members in runs.values() for k in members}
    return [{**row, "chosen": k in chosen} if k in scored else row for k, row in enumerate(rows)]


def _variant_runs(cfg: DictConfig, variants: list[str]) -> list[tuple[str, str, str]]:
    """(variant, row name, output folder) of each RL variant of the table, in the table's order."""
    return [(v, _VARIANTS[v], OmegaConf.merge(cfg, {"pada": {"variant": v}}).pada.output_dir)
            for v in _VARIANTS if v in variants]


def finished_run(out_dir) -> bool:
    """Whether a stage's folder holds its final model: its run info, not marked ``complete: false`` (an
    RL run records its base at the start with complete=false, train/models.py ``base_checked``)."""
    return (Path(str(out_dir)) / RUN_INFO).is_file() and bool(read_run_info(out_dir).get("complete", True))


def decode_layouts(cfg: DictConfig, variants: list[str]) -> dict:
    """``ablation.decode_only``: the layouts of every model of the table (the SFT model, each variant's
    final model and, with ``ablation.checkpoints``, its kept checkpoints) on the test draw and the
    validation draw, kept under ``ablation.layouts`` with their source records; nothing is trained or
    scored. The same command without ``decode_only`` then re-scores the kept layouts instead of decoding
    them (:func:`_earlier_layouts`): decoding on a GPU host, scoring elsewhere. Layouts already kept from
    the same checkpoint and settings are left as they are; a stage without a finished model is listed as
    missing. Returns ``{"decoded": [...], "kept": [...], "missing": [...]}``."""
    a, state = cfg.ablation, PartialState()
    if not a.get("layouts"):
        raise TrainingSetupError("ablation.decode_only keeps the layouts for a later scoring: set "
                                 "ablation.layouts to a folder")
    sft = Path(str(cfg.sft.output_dir))
    models, done = {}, {"decoded": [], "kept": [], "missing": []}
    for _, name, out_dir in [("sft", "sft", sft), *_variant_runs(cfg, variants)]:
        if finished_run(out_dir):
            models[name] = Path(str(out_dir))
        else:
            done["missing"].append(f"{name}: {out_dir}")
    if a.get("checkpoints", False):
        models.update(checkpoint_models(models, a.checkpoints))
    folder = Path(str(a.layouts))
    draws = [(evaluation_split(a), folder)]
    if (validation := validation_split(a)) is not None:
        draws.append((validation, folder / "validation"))
    for split, where in draws:
        items = None
        sources = {name: _row_source(cfg, path, split) for name, path in models.items()}
        adopted = _adopt_layouts(where, sources) if state.is_main_process else {}
        state.wait_for_everyone()
        for name, path in models.items():
            source, label = sources[name], f"{name} ({split['name']}, seed {split['seed']})"
            if _kept(where, name, source):
                done["kept"].append(label + (f" (as {adopted[name]})" if name in adopted else ""))
                continue
            items = items if items is not None else _load_split(split)
            outputs = _decode(cfg, path, items, sft)
            if state.is_main_process:
                write_layout_records(layout_records(items, outputs), where / row_file(name))
                _record_source(where, name, source)
                print(f"ablation: {label} decoded to {where / row_file(name)}", file=sys.stderr)
            done["decoded"].append(label)
    state.wait_for_everyone()
    return done


def checkpoint_models(models: dict[str, Path], steps=True) -> dict[str, Path]:
    """``{"pada@12": .../pada/checkpoint-12, ...}``: the kept intermediate checkpoints of the RL rows
    (``ablation.checkpoints``: true, every one; a list of steps, those of them that were kept), in step
    order; the final model's own step is its row already."""
    if steps is not True:
        try:
            if isinstance(steps, str):
                raise TypeError(steps)
            wanted = {int(step) for step in steps}
        except (TypeError, ValueError):
            raise TrainingSetupError("ablation.checkpoints is true, false or a list of RL steps, "
                                     f"not {steps!r}") from None
    out = {}
    for name in ("grpo", "pada*", "pada"):
        if name not in models:
            continue
        kept = sorted(int(d.name.split("-")[1]) for d in Path(models[name]).glob("checkpoint-*")
                      if d.name.split("-")[1].isdigit() and (d / "adapter_config.json").is_file())
        final = read_run_info(models[name]).get("steps")
        out.update({f"{name}@{step}": Path(models[name]) / f"checkpoint-{step}"
                    for step in kept if step != final and (steps is True or step in wanted)})
    return out


def _completions(path: Path, items, **options) -> list[str]:
    """The checkpoint's completions of the items' prompts: the eval harness's ``model:PATH`` generator."""
    return checkpoint_generate(path, [it.prompt for it in items], **options)


def _gpu() -> str:
    if not torch.cuda.is_available():
        return "cpu"
    return f"{torch.cuda.device_count()} x {torch.cuda.get_device_name(0)}"


def _rl_steps(name: str, path: Path) -> int:
    """The RL optimizer steps behind a row: 0 for the SFT model, N for ``name@N``, else the steps its
    run info records."""
    if name == "sft":
        return 0
    if "@" in name:
        return int(name.split("@")[1])
    return int(read_run_info(path).get("steps") or 0)


def evaluation_split(a: DictConfig) -> dict:
    """The scenes every row is scored on: the first ``ablation.n_test`` of ``ablation.test_split`` drawn
    with ``ablation.test_seed``. Not the run's seed: rows of every seed then score the same scenes and
    stand in one table (``ablation-merge``)."""
    return {"name": str(a.test_split), "seed": int(a.get("test_seed", 0)), "n": int(a.n_test)}


def validation_split(a: DictConfig) -> dict | None:
    """The scenes the kept checkpoint is picked on (``ablation.validation`` of them, drawn from the test
    split's generator with ``ablation.validation_seed``), None when ``ablation.validation`` is null. The
    draw of the test split itself is refused: picking on it would read the figures it reports."""
    n = a.get("validation")
    if n is None:
        return None
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise TrainingSetupError(f"ablation.validation: {n!r} is not a number of scenes (a positive "
                                 "integer; null: no validation)")
    test, seed = evaluation_split(a), int(a.get("validation_seed", 1))
    if seed == test["seed"]:
        raise TrainingSetupError(f"ablation.validation_seed: {seed} equals ablation.test_seed: the "
                                 "validation scenes would be the test scenes; set another validation_seed")
    return {"name": test["name"], "seed": seed, "n": n}


def _load_split(split: dict) -> list:
    from physcene.eval.harness import load_benchmark

    return load_benchmark(split["name"], n=split["n"], seed=split["seed"], progress=False)


def _decode(cfg: DictConfig, path: Path, items: list, base: Path | None = None) -> list:
    """The model's outputs for ``items`` at the table's generation settings (``eval.*``, the run's
    seed): the one decoding of the test rows and of the validation scenes, so a checkpoint is picked
    on the decoding it is reported with. Under accelerate the items are split between the processes
    (generation is the slow part) and gathered in input order."""
    from physcene.eval.harness import generate

    state = PartialState()
    with state.split_between_processes(list(range(len(items)))) as shard:
        model = partial(_completions, path, max_new_tokens=int(cfg.eval.max_new_tokens),
                        device=str(state.device), cache=str(cfg.eval.get("cache", "dynamic")),
                        constrained=bool(cfg.eval.get("constrained", False)),
                        follow_plan=bool(cfg.eval.get("follow_plan", True)),
                        seed=int(cfg.seed), base=base, **sampling(float(cfg.eval.get("temperature", 0.0))))
        part = generate([items[i] for i in shard], f"model:{path}", progress=False,
                        generators={f"model:{path}": model})
    return gather_object(part)  # rank order = shard order = input order


def _model_outputs(cfg: DictConfig, name: str, path: Path, items: list, folder, source: dict | None,
                   base: Path | None = None) -> list:
    """A model's outputs for ``items``: its layouts under ``folder`` when an earlier evaluation wrote them
    from the same checkpoint, settings and split (``source``, with ``ablation.reuse``), else decoded
    (an adapter on ``base``, the table's SFT model)."""
    earlier = _earlier_layouts(items, folder, name, source) if cfg.ablation.get("reuse", True) else None
    return earlier if earlier is not None else _decode(cfg, path, items, base)


def _row_source(cfg: DictConfig, path: Path, split: dict) -> dict:
    """What a row's layouts come from (kept beside them, compared before they are re-scored): the
    checkpoint's digest, the decoding settings (``eval.*`` and the run's seed) and the split's draw."""
    decoding = {"seed": int(cfg.seed), **OmegaConf.to_container(cfg.eval, resolve=True)}
    return {"model": checkpoint_digest(path), "decoding": decoding, "split": split}


def _validation_figures(items: list, outputs: list, engine, folder, name: str, source: dict | None) -> dict:
    """``val_scr`` (null where nothing parsed) and ``val_parse_rate`` of a model's outputs on the
    validation scenes; with ``ablation.layouts`` they are kept under ``<layouts>/validation/`` (the ids
    are the test split's too) for a rerun to re-score."""
    from physcene.eval.harness import make_judge, score_scenes
    from physcene.eval.metrics import summarize

    judge = make_judge("rule", [it.reference for it in items])  # SCR reads no judge; score_scenes needs one
    results = score_scenes(items, outputs, judge, engine, progress=False)
    if folder is not None:
        write_layout_records(layout_records(items, outputs), Path(folder) / row_file(name))
        _record_source(folder, name, source)
    figures = _figures(summarize(results))
    return {"val_scr": figures["scr"], "val_parse_rate": figures["parse_rate"]}


def _evaluate(cfg: DictConfig, models: dict[str, Path], budget_s: float) -> list[dict]:
    """Rows for every model, in ``models``' order: generate once per model, TTO the SFT output for
    ``sft+tto``, after a row for the reference layouts; with ``ablation.validation`` each model row
    also gets ``val_scr``. With ``ablation.layouts`` each row's layouts are written to
    ``<layouts>/<row>.jsonl.gz`` (re-score with ``physcene eval --generator file:FILE``).

    Under accelerate every process generates its share of every model (:func:`_decode`); the main
    process scores, repairs and reports, the others return no rows. With ``ablation.reuse`` and
    ``ablation.layouts`` a row whose figures an earlier evaluation kept (``<row>.row.json``) from the
    same layouts, scored by the same physcene code on the same kind of device (with the same held-out
    anchors and validation draw), is taken as it was (:func:`_kept_row`): a table grown by new
    checkpoints scores only those.
    """
    from physcene.eval.harness import make_judge, repair_outputs, score_scenes
    from physcene.physics import PhysicsEngine

    a = cfg.ablation
    state = PartialState()
    test, validation = evaluation_split(a), validation_split(a)
    items = _load_split(test)
    val_items = _load_split(validation) if validation else None
    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine(device=str(state.device))
    layouts = a.get("layouts")
    val_folder = Path(str(layouts)) / "validation" if layouts else None
    heldout = None
    if a.get("heldout_anchors"):
        if not Path(str(a.heldout_anchors)).is_file():
            raise TrainingSetupError(f"ablation.heldout_anchors: {a.heldout_anchors!r} does not exist (the "
                                     "anchors of prompts outside the RL pool: anchors.exclude)")
        heldout = load_records(str(a.heldout_anchors))
    rows, start = [], time.monotonic()
    # what every kept row's figures must have been scored with (ablation.reuse, kept layouts only)
    scoring = ({"code": scoring_code_digest(), "device": state.device.type, "split": test,
                "validation": validation, "heldout": file_sha256(a.heldout_anchors) if heldout else None,
                "max_length": int(cfg.pada.max_completion_length)}
               if layouts and a.get("reuse", True) else None)

    def add_row(name, outputs, results, rl_steps=0):
        rows.append(table_row(name, items, outputs, results, engine, seed=int(cfg.seed), rl_steps=rl_steps,
                              layouts=Path(str(layouts)) if layouts else None))

    def scored(name: str, inputs: dict, score) -> None:
        """Row ``name``: kept from an earlier evaluation of the same ``inputs`` by the same scoring, else
        ``score()`` (which adds it) and kept for the next one."""
        key = {**scoring, "inputs": inputs, "seed": int(cfg.seed)} if scoring else None
        kept = _kept_row(layouts, name, key) if key else None
        if kept is not None:
            rows.append(kept)
            print(f"ablation: {name} figures kept from {_row_figures_file(layouts, name)}", file=sys.stderr)
            return
        score()
        if key:
            write_atomic(_row_figures_file(layouts, name), json.dumps({"key": key, "row": rows[-1]}) + "\n")

    if a.get("reference", False) and state.is_main_process:
        references = [it.reference for it in items]
        scored("reference", {"reference": True}, lambda: add_row(
            "reference", references, score_scenes(items, references, judge, engine, progress=False)))

    base = models.get("sft")  # the adapters' base: the table's SFT model, wherever they were trained
    base_source = _row_source(cfg, base, test) if base is not None and layouts else None
    # hashed only where the layouts are kept: what the reuse check and the record compare; the split and
    # its seed are part of it, so layouts of another draw are never re-scored as these scenes
    sources = {name: (base_source if path == base else _row_source(cfg, path, test)) if layouts else None
               for name, path in models.items()}
    if layouts and a.get("reuse", True) and state.is_main_process:
        _adopt_layouts(layouts, sources)  # before any row's layouts are written again
    state.wait_for_everyone()
    for name, path in models.items():
        source = sources[name]
        val_source = _row_source(cfg, path, validation) if layouts and validation else None
        outputs = _model_outputs(cfg, name, path, items, layouts, source, base)
        val_outputs = (_model_outputs(cfg, name, path, val_items, val_folder, val_source, base)
                       if validation else None)
        if not state.is_main_process:
            continue

        def score_model(name, path, outputs, val_outputs, val_source):
            results = score_scenes(items, outputs, judge, engine, progress=False)
            add_row(name, outputs, results, _rl_steps(name, path))
            if heldout:  # PADA's mechanism: how likely the model finds repaired layouts it did not train on
                rows[-1]["anchor_nll"] = anchor_nll(path, heldout, device=str(state.device), base=base,
                                                    max_length=int(cfg.pada.max_completion_length))["nll"]
            if validation:
                rows[-1].update(_validation_figures(val_items, val_outputs, engine, val_folder, name,
                                                    val_source))

        # an adapter's held-out NLL is read on the table's SFT model: its digest is an input too
        scored(name, {"source": source, "validation": val_source,
                      "base": base_source["model"] if base_source and name != "sft" else None},
               partial(score_model, name, path, outputs, val_outputs, val_source))
        _record_source(layouts, name, source)
        if name == "sft":  # repaired (unless kept): the row reports TTO's own figures

            def score_repaired(outputs):
                repaired, extras = repair_outputs(outputs, tto_overrides=list(cfg.anchors.tto), engine=engine,
                                                  progress=False)
                add_row("sft+tto", repaired,
                        score_scenes(items, repaired, judge, engine, extras=extras, progress=False))

            scored("sft+tto", {"source": source, "tto": list(cfg.anchors.tto)},
                   partial(score_repaired, outputs))
        if time.monotonic() - start > budget_s:  # every rank generates every model: no early exit
            print(f"ablation: eval budget spent after {name}", file=sys.stderr)
    state.wait_for_everyone()
    return rows


@functools.cache
def scoring_code_digest() -> str:
    """sha256 over the installed physcene code and configs (every file of the ``physcene``,
    ``physcene.eval``, ``physcene.kernels``, ``physcene.train`` and ``physcene.configs`` packages but
    bytecode): a row's kept figures are taken only from the code that scores them now."""
    h = hashlib.sha256()
    for package in ("physcene", "physcene.eval", "physcene.kernels", "physcene.train", "physcene.configs"):
        root = Path(importlib.import_module(package).__file__).parent
        for f in sorted(root.rglob("*")):
            if f.is_file() and "__pycache__" not in f.parts and f.suffix != ".pyc":
                h.update(f"{package}/{f.relative_to(root).as_posix()}\0".encode())
                h.update(f.read_bytes())
    return h.hexdigest()


def _row_figures_file(layouts, name: str) -> Path:
    return Path(str(layouts)) / row_file(name, ".row.json")


def _kept_row(layouts, name: str, key: dict) -> dict | None:
    """The row an earlier evaluation kept beside its layouts when it was scored from ``key`` (the row's
    inputs and the scoring: code, device, split, held-out anchors, validation draw) and its layouts file
    is still there, else None."""
    kept = _row_figures_file(layouts, name)
    if not kept.is_file():
        return None
    record = json.loads(kept.read_text())
    row = record.get("row") or {}
    if record.get("key") != json.loads(json.dumps(key)) or row.get("name") != name:
        return None
    if row.get("layouts") and not (Path(str(layouts)) / row_file(name)).is_file():
        return None
    return row


def _source_file(layouts, name: str) -> Path:
    return Path(str(layouts)) / row_file(name, ".source.json")


def _record_source(layouts, name: str, source: dict) -> None:
    """Beside a row's layouts, what wrote them (the checkpoint's digest, the decoding settings, the
    split and its seed)."""
    if layouts:
        write_atomic(_source_file(layouts, name), json.dumps(source, sort_keys=True) + "\n")


def _kept(layouts, name: str, source: dict) -> bool:
    """Whether ``<layouts>`` holds the row's layouts file, written from ``source``: the same checkpoint
    with the same settings on the same draw of the split (a record without the split never matches)."""
    if not layouts or not (Path(str(layouts)) / row_file(name)).is_file():
        return False
    recorded = _source_file(layouts, name)
    return recorded.is_file() and json.loads(recorded.read_text()) == json.loads(json.dumps(source))


def _adopt_layouts(layouts, sources: dict[str, dict]) -> dict[str, str]:
    """Before anything is decoded or re-written: each row of ``sources`` (name -> what its layouts come
    from) without layouts of its own whose source another row's layouts file under ``layouts`` records
    gets a copy of that file and its record. A run's final model decoded as its row and kept as a
    checkpoint once the run went on (``pada`` at 100 steps is ``pada@100`` after a resume) is the same
    model under another name. Returns {row: the file it was copied from}."""
    folder = Path(str(layouts))
    if not folder.is_dir():
        return {}
    recorded = {}
    for record in sorted(folder.glob("*.source.json")):
        written = record.with_name(record.name.removesuffix(".source.json") + ".jsonl.gz")
        if written.is_file():
            recorded.setdefault(json.dumps(json.loads(record.read_text()), sort_keys=True), written)
    adopted = {}
    for name, source in sources.items():
        same = recorded.get(json.dumps(source, sort_keys=True))  # as _record_source writes it
        if same is None or same.name == row_file(name) or _kept(folder, name, source):
            continue
        shutil.copyfile(same, folder / row_file(name))
        _record_source(folder, name, source)
        adopted[name] = same.name
    return adopted


def _earlier_layouts(items, layouts, name: str, source: dict) -> list | None:
    """A row's outputs from its layouts file when an earlier evaluation wrote it from ``source``
    (:func:`_kept`), else None: a rerun decodes only what changed."""
    if not _kept(layouts, name, source):
        return None
    from physcene.eval.harness import generate

    print(f"ablation: {name} layouts read from {Path(str(layouts)) / row_file(name)}", file=sys.stderr)
    return generate(items, f"file:{Path(str(layouts)) / row_file(name)}", progress=False)


def markdown_table(rows: list[dict]) -> str:
    """The ablation rows as a Markdown table (rates and shares in %): every figure of the schema, so a
    reward that is gamed shows beside the SCR (floating, shrunk and out-of-zone objects); with
    validation a ``val SCR`` column, and the row each RL run keeps named ``(chosen)``."""
    pct = (lambda x: "—" if x is None else f"{100 * x:.1f}%")  # noqa: E731
    num = (lambda x: "—" if x is None else f"{x:.2f}")  # noqa: E731
    nll = any("anchor_nll" in r for r in rows)  # a column where the held-out anchors were scored
    val = any("val_scr" in r for r in rows)  # a column (and the chosen rows marked) where validation ran
    columns = ["method", "seed", "RL steps", "SCR", *(["val SCR"] if val else []), "ACR", "QPR 7 / 8 / 9",
               "judge avg", "parse rate", "floating", "shrunk", "out of zone",
               *(["held-out anchor NLL"] if nll else []), "n"]
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        if "skipped" in r:
            empty = " |" * (len(columns) - 4)
            lines.append(f"| {r['name']} | | | skipped: {r['skipped']} |{empty}")
            continue
        qpr = " / ".join(pct(r.get(k)) for k in ("qpr7", "qpr8", "qpr9"))
        value = r.get("anchor_nll")
        anchor = (" —" if value is None else f" {value:.4f}") + " |" if nll else ""
        name = r["name"] + (" (chosen)" if val and r.get("chosen") else "")
        validated = f" {pct(r.get('val_scr'))} |" if val else ""
        lines.append(f"| {name} | {r.get('seed', 0)} | {r.get('rl_steps', 0)} | {pct(r['scr'])} |{validated} "
                     f"{pct(r['acr'])} | {qpr} | {num(r['judge_avg'])} | {pct(r['parse_rate'])} | "
                     f"{pct(r.get('floating'))} | {pct(r.get('shrunk'))} | {pct(r.get('out_of_zone'))} |"
                     f"{anchor} {r['n']} |")
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


def ablation_variants(a: DictConfig) -> list[str]:
    """The RL variants ``ablation.variants`` names: null (or no key) is all three, an empty list none
    (the table of SFT, SFT + TTO and the reference alone)."""
    listed = a.get("variants")
    if listed is None:
        return list(_VARIANTS)
    if not (OmegaConf.is_list(listed) or isinstance(listed, (list, tuple))):
        raise TrainingSetupError(f"ablation.variants: {listed!r} is not a list; expected some of "
                                 f"{list(_VARIANTS)}, e.g. ablation.variants=[pada]")
    if unknown := [v for v in listed if v not in _VARIANTS]:
        raise TrainingSetupError(f"ablation.variants: unknown variant(s) {unknown}; "
                                 f"expected some of {list(_VARIANTS)}")
    return list(listed)


def run_ablation(cfg: DictConfig, budget_min: float | None = None) -> dict:
    """Run the whole ablation per ``cfg`` (see the module docstring); returns the ablation.json dict."""
    a = cfg.ablation
    variants, validation = ablation_variants(a), validation_split(a)  # refused before hours of training
    budget_s = 60.0 * float(budget_min if budget_min is not None else a.budget_min)
    shares = {**DEFAULT_SHARES, **(OmegaConf.to_container(a.shares) if a.get("shares") else {})}
    stages, t0 = {}, time.monotonic()

    def timed(stage, fn, *args, **kwargs):
        start = time.monotonic()
        result = fn(*args, **kwargs)
        stages[stage] = {"seconds": round(time.monotonic() - start, 1), **stages.get(stage, {})}
        return result

    reuse = bool(a.get("reuse", True))
    if a.get("decode_only", False):
        return {"rows": [], "decode_only": decode_layouts(cfg, variants)}

    def finished(out_dir) -> bool:  # a stage that already wrote its final model (reuse=true)
        return reuse and finished_run(out_dir)

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
    for variant, name, out_dir in _variant_runs(cfg, variants):
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
    extra = checkpoint_models(models, a.checkpoints) if a.get("checkpoints", False) else {}
    evaluated = mark_chosen(timed("eval", _evaluate, cfg, {**models, **extra}, shares["eval"] * budget_s))
    rows = [r for r in evaluated if r["name"] not in extra and r["name"] != "reference"] + skipped
    reference = [r for r in evaluated if r["name"] == "reference"]
    rows = reference + rows
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
        "test_split": evaluation_split(a),
        **({"validation_split": validation} if validation else {}),
        "decoding": {"eval": "constrained" if cfg.eval.get("constrained", False) else "greedy",
                     "eval_temperature": float(cfg.eval.get("temperature", 0.0)),
                     "follow_plan": bool(cfg.eval.get("follow_plan", True)),
                     "anchors": "constrained" if cfg.anchors.get("constrained", False) else "greedy",
                     "pada": "constrained" if cfg.pada.get("constrained", False) else "sampled",
                     "cache": str(cfg.eval.get("cache", "dynamic"))},
    }
    if PartialState().is_main_process:
        write_ablation(result, Path(str(a.output)))
    return result


def write_ablation(result: dict, out: Path) -> Path:
    """``result`` to ``out`` (JSON), its table beside it (``.md``: every row, then per level) and its
    learning curves (``.svg``)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, json.dumps(result, indent=1) + "\n")
    every = result["rows"] + result.get("checkpoint_rows", [])
    out.with_suffix(".md").write_text(markdown_table(every) + "\n" + level_table(every))
    write_learning_curves(result, out.with_suffix(".svg"))
    return out


def merge_ablations(sources: list[str | Path], out: str | Path, layouts: str | Path | None = None) -> dict:
    """One table from the ``ablation.json`` of several runs (the seeds of ``rl_ablation.sh``): their rows
    and checkpoint rows, each keeping its ``seed``, the sources' GPUs and commands; written to ``out``
    with its ``.md`` and ``.svg``. With ``layouts`` (a folder) every row's layouts file is copied to
    ``<layouts>/s<seed>/`` and the row names the copy, so the table and its layouts travel together
    (``physcene eval --generator file:...`` recomputes a row). Two rows with the same name, seed and
    steps are an error naming both sources, and so are sources scored on different draws of the test
    split (``test_split``: their rows would not compare). A merged table is a source too: a new seed's
    table merged into it, with the same ``layouts``, leaves its rows' layouts where they are."""
    merged: dict = {"rows": [], "checkpoint_rows": [], "gpu": [], "commands": [], "sources": []}
    seen: dict[tuple, str] = {}
    split: tuple[dict, str] | None = None  # the first source's test_split, and that source
    for source in map(Path, sources):
        data = check_ablation(json.loads(source.read_text()), str(source))
        merged["sources"].append(str(source))
        if data.get("test_split") is not None:
            if split is not None and data["test_split"] != split[0]:
                raise ValueError(f"{source}: scored on the test split {data['test_split']}, {split[1]} on "
                                 f"{split[0]}: rows of different draws do not stand in one table")
            split = split or (data["test_split"], str(source))
            merged["test_split"] = data["test_split"]
        for key in ("gpu", "commands"):
            for value in data[key] if isinstance(data[key], list) else [data[key]]:
                if value not in merged[key]:
                    merged[key].append(value)
        for part in ("rows", "checkpoint_rows"):
            for row in data.get(part, []):
                row = dict(row)
                ident = (row["name"], row.get("seed"), row.get("rl_steps"))
                if ident in seen:
                    raise ValueError(f"{source}: row {row['name']} (seed {row.get('seed')}, "
                                     f"{row.get('rl_steps')} RL steps) is also in {seen[ident]}")
                seen[ident] = str(source)
                if layouts is not None and row.get("layouts"):
                    found = _row_layouts(row["layouts"], source)
                    copy = Path(layouts) / f"s{row.get('seed', 0)}" / found.name
                    copy.parent.mkdir(parents=True, exist_ok=True)
                    if not (copy.exists() and copy.samefile(found)):  # a merged table grown: in place
                        shutil.copyfile(found, copy)
                    row["layouts"] = _repository_path(copy)
                merged[part].append(row)
    merged["gpu"] = merged["gpu"][0] if len(merged["gpu"]) == 1 else merged["gpu"]
    write_ablation(check_ablation(merged, str(out)), Path(out))
    return merged


def _row_layouts(layouts: str, source: Path) -> Path:
    """A row's layouts file: as written (a repository path, from the current folder or the checkout's
    root) or beside its ``ablation.json``."""
    candidates = [Path(layouts), source.parent / Path(layouts).name]
    with contextlib.suppress(ArtifactError):  # outside a checkout: the other candidates
        candidates.insert(1, repo_root() / layouts)
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise ValueError(f"{source}: layouts {layouts!r} not found (looked at "
                         f"{', '.join(map(str, candidates))})")
    return found
