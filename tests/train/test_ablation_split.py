"""The ablation's scenes: every run seed is scored on the test split's one draw (``ablation.test_seed``),
``ablation.variants=[]`` trains no RL variant, and ``ablation.validation`` picks each RL run's kept
checkpoint on another draw (``val_scr``, ``chosen``) without reading the test split.

Models here are folders with a config.json whose completions a stub returns (the reference layouts, or
text that does not parse), so the evaluation path runs on CPU without decoding."""

from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

from physcene.artifacts import checkpoint_digest
from physcene.config import load_config
from physcene.eval.harness import load_benchmark
from physcene.layout import layout_record_lines, layout_to_dict
from physcene.train import ablation
from physcene.train.ablation import (
    ROW_KEYS,
    ablation_variants,
    check_ablation,
    mark_chosen,
    markdown_table,
    validation_split,
)
from physcene.train.models import RUN_INFO, TrainingSetupError


def _config(tmp_path, *overrides: str):
    return load_config("train_tiny", [
        f"output_dir={tmp_path / 'run'}", f"ablation.layouts={tmp_path / 'layouts'}", "ablation.n_test=3",
        "anchors.tto=[steps=5,report_relations=false]", *overrides])


def _model(folder, steps: int | None = None):
    """A folder the ablation takes for a checkpoint: hashable files and, for an RL model, its steps."""
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"name": folder.name}))
    if steps is not None:
        (folder / RUN_INFO).write_text(json.dumps({"steps": steps}))
    return folder


@pytest.fixture
def stub_decoding(monkeypatch):
    """``ablation._completions`` replaced: each call is recorded (path, item ids, options); a path in
    ``unparsable`` answers text that does not parse, any other the items' reference layouts."""
    calls, unparsable = [], set()

    def completions(path, items, **options):
        calls.append((path.name, [it.id for it in items], options))
        return ["not a layout" if path.name in unparsable else it.reference for it in items]

    monkeypatch.setattr(ablation, "_completions", completions)
    return calls, unparsable


def _layouts(path) -> list:
    return [json.loads(line)["layout"] for _, line in layout_record_lines(path)]


def _draw(seed: int, n: int = 3) -> list:
    return [layout_to_dict(it.reference) for it in load_benchmark("test", n=n, seed=seed, progress=False)]


def test_a_run_of_seed_1_is_scored_on_the_test_split_of_seed_0(tmp_path, stub_decoding):
    """seed=1 is the run's seed (its rows' seed column), not the draw of the test split: the reference
    row and a model's row are the scenes of load_benchmark(..., seed=0), and the model's source record
    names that draw."""
    calls, _ = stub_decoding
    cfg = _config(tmp_path, "seed=1", "ablation.reference=true")
    models = {"grpo": _model(tmp_path / "grpo", steps=2)}
    rows = ablation._evaluate(cfg, models, budget_s=600)
    assert [(r["name"], r["seed"]) for r in rows] == [("reference", 1), ("grpo", 1)]
    assert _draw(0) != _draw(1)  # the two draws differ: the check below tells them apart
    assert _layouts(tmp_path / "layouts" / "reference.jsonl.gz") == _draw(0)
    assert _layouts(tmp_path / "layouts" / "grpo.jsonl.gz") == _draw(0)
    assert calls[0][2]["seed"] == 1  # the run's seed still seeds its decoding
    source = json.loads((tmp_path / "layouts" / "grpo.source.json").read_text())
    assert source["split"] == {"name": "test", "seed": 0, "n": 3}


def test_layouts_of_another_draw_are_decoded_again_not_re_scored(tmp_path, stub_decoding, capsys):
    """A row's kept layouts are re-scored only when their source names the same split and seed: a
    record without them (written before the split was recorded) or of another ablation.test_seed
    decodes again."""
    calls, _ = stub_decoding
    cfg = _config(tmp_path)
    models = {"grpo": _model(tmp_path / "grpo", steps=2)}
    ablation._evaluate(cfg, models, budget_s=600)
    ablation._evaluate(cfg, models, budget_s=600)
    assert len(calls) == 1 and "grpo layouts read from" in capsys.readouterr().err
    record = tmp_path / "layouts" / "grpo.source.json"
    record.write_text(json.dumps({k: v for k, v in json.loads(record.read_text()).items() if k != "split"}))
    ablation._evaluate(cfg, models, budget_s=600)
    assert len(calls) == 2 and "layouts read" not in capsys.readouterr().err
    ablation._evaluate(OmegaConf.merge(cfg, {"ablation": {"test_seed": 5}}), models, budget_s=600)
    assert len(calls) == 3 and "layouts read" not in capsys.readouterr().err
    assert _layouts(tmp_path / "layouts" / "grpo.jsonl.gz") == _draw(5)


def test_variants_null_is_all_and_an_empty_list_none():
    assert ablation_variants(OmegaConf.create({"variants": None})) == ["grpo", "pada_star", "pada"]
    assert ablation_variants(OmegaConf.create({})) == ["grpo", "pada_star", "pada"]
    assert ablation_variants(OmegaConf.create({"variants": []})) == []
    assert ablation_variants(OmegaConf.create({"variants": ["pada", "grpo"]})) == ["pada", "grpo"]
    with pytest.raises(TrainingSetupError, match=r"ablation.variants: unknown variant\(s\) \['ppo'\]"):
        ablation_variants(OmegaConf.create({"variants": ["ppo"]}))
    with pytest.raises(TrainingSetupError, match="ablation.variants: 'pada' is not a list"):
        ablation_variants(OmegaConf.create({"variants": "pada"}))


def test_an_ablation_of_no_variants_trains_no_rl_model(tmp_path, monkeypatch):
    """`physcene train ablation ablation.variants=[]`: SFT and anchors run, no RL stage, and the
    evaluation gets the SFT model alone."""
    evaluated = {}

    def evaluate(cfg, models, budget_s):
        evaluated.update(models)
        return []

    def no_rl(*args, **kwargs):
        raise AssertionError(f"an RL stage ran: {kwargs.get('variant')}")

    monkeypatch.setattr(ablation, "run_sft", lambda cfg, callbacks: tmp_path / "sft")
    monkeypatch.setattr(ablation, "run_anchors", lambda cfg: None)
    monkeypatch.setattr(ablation, "run_pada", no_rl)
    monkeypatch.setattr(ablation, "_evaluate", evaluate)
    result = ablation.run_ablation(_config(tmp_path, "ablation.variants=[]"), budget_min=1)
    assert list(evaluated) == ["sft"] and set(result["stages"]) == {"sft", "anchors", "eval"}


def _row(name: str, val_scr, rl_steps: int, seed: int = 0) -> dict:
    return {**dict.fromkeys(ROW_KEYS), "name": name, "seed": seed, "rl_steps": rl_steps, "n": 4,
            "val_scr": val_scr}


def test_each_rl_run_keeps_its_row_of_lowest_validation_scr():
    """Per run and seed: the lowest val_scr is chosen; a tie goes to the later step; a row where
    nothing parsed (val_scr null) ranks last; SFT and rows without validation get no ``chosen``."""
    rows = [_row("sft", 0.1, 0), {k: v for k, v in _row("sft+tto", None, 0).items() if k != "val_scr"},
            _row("grpo@1", 0.3, 1), _row("grpo@2", 0.2, 2), _row("grpo", 0.2, 3),
            _row("pada*@5", None, 5), _row("pada*@3", 0.4, 3), _row("pada*", None, 8),
            _row("pada@4", None, 4), _row("pada", None, 6),
            _row("grpo@1", 0.1, 1, seed=1), _row("grpo", 0.2, 3, seed=1)]
    chosen = [(r["name"], r["seed"], r.get("chosen")) for r in mark_chosen(rows)]
    assert chosen == [("sft", 0, None), ("sft+tto", 0, None),
                      ("grpo@1", 0, False), ("grpo@2", 0, False), ("grpo", 0, True),
                      ("pada*@5", 0, False), ("pada*@3", 0, True), ("pada*", 0, False),
                      ("pada@4", 0, False), ("pada", 0, True),
                      ("grpo@1", 1, True), ("grpo", 1, False)]
    assert "chosen" not in rows[4]  # the rows given are left as they were
    assert all("chosen" not in r for r in mark_chosen([{k: v for k, v in r.items() if k != "val_scr"}
                                                       for r in rows]))


def test_a_checkpoint_that_parses_little_is_not_chosen_for_its_low_scr():
    """SCR counts parsed scenes only: a checkpoint whose few parsed layouts are clean (val_scr 0.1 at
    parse rate 0.2: 18 % of scenes clean) loses to one at val_scr 0.5 that parses everything (50 %)."""
    rows = [{**_row("pada@2", 0.1, 2), "val_parse_rate": 0.2},
            {**_row("pada", 0.5, 4), "val_parse_rate": 1.0}]
    assert [r["chosen"] for r in mark_chosen(rows)] == [False, True]


def test_the_table_has_a_validation_column_and_marks_the_chosen_row():
    rows = mark_chosen([_row("sft", 0.5, 0), _row("pada*@2", 0.25, 2), _row("pada*", 0.5, 4),
                        {"name": "grpo", "skipped": "no anchors"}])
    table = markdown_table(rows).splitlines()
    assert table[0].startswith("| method | seed | RL steps | SCR | val SCR | ACR |")
    assert table[3].startswith("| pada*@2 (chosen) | 0 | 2 | — | 25.0% |")
    assert table[4].startswith("| pada* | 0 | 4 | — | 50.0% |")
    assert len({line.count("|") for line in table}) == 1  # the skipped row spans the new column too
    plain = markdown_table([{k: v for k, v in r.items() if k not in ("val_scr", "chosen")} for r in rows])
    assert "val SCR" not in plain and "(chosen)" not in plain


def test_the_schema_takes_val_scr_and_chosen_of_the_right_types():
    data = {"rows": [_row("sft", 0.5, 0), {**_row("pada", None, 4), "chosen": True}], "gpu": "cpu",
            "commands": []}
    assert check_ablation(data) is data
    for key, value, message in (("val_scr", 1.5, "val_scr must be a fraction"),
                                ("val_scr", "0.2", "val_scr must be a fraction"),
                                ("val_scr", True, "val_scr must be a fraction"),
                                ("chosen", "yes", "chosen must be true or false"),
                                ("chosen", 1, "chosen must be true or false")):
        bad = {**data, "rows": [{**data["rows"][1], key: value}]}
        with pytest.raises(ValueError, match=rf"row 0 \(pada\): {message}"):
            check_ablation(bad)


def test_validation_on_the_test_draw_is_refused(tmp_path, monkeypatch):
    """ablation.validation_seed equal to ablation.test_seed would pick on the test scenes: refused
    before any stage trains, naming both keys."""
    monkeypatch.setattr(ablation, "run_sft", lambda *a, **k: pytest.fail("SFT ran"))
    cfg = _config(tmp_path, "ablation.validation=4", "ablation.test_seed=3", "ablation.validation_seed=3")
    with pytest.raises(TrainingSetupError, match="ablation.validation_seed: 3 equals ablation.test_seed"):
        ablation.run_ablation(cfg, budget_min=1)
    assert validation_split(_config(tmp_path, "ablation.validation=4").ablation) == \
        {"name": "test", "seed": 1, "n": 4}
    assert validation_split(_config(tmp_path).ablation) is None
    for n in (0, "four"):
        with pytest.raises(TrainingSetupError, match="ablation.validation: .* is not a number of scenes"):
            validation_split(_config(tmp_path, f"ablation.validation={n}").ablation)


def test_validation_scores_every_model_row_and_picks_the_checkpoint(tmp_path, stub_decoding, capsys):
    """With ablation.validation every model row (SFT, the RL row, its checkpoint) gets val_scr from the
    validation draw, decoded with the test rows' settings and kept under <layouts>/validation/; the
    RL run's checkpoint with the lower val_scr is chosen (the final model here writes nothing that
    parses); a rerun re-scores both draws from their layouts."""
    calls, unparsable = stub_decoding
    unparsable.add("grpo")
    cfg = _config(tmp_path, "ablation.validation=2")
    models = {"sft": _model(tmp_path / "sft"), "grpo": _model(tmp_path / "grpo", steps=2),
              "grpo@1": _model(tmp_path / "grpo" / "checkpoint-1")}
    rows = mark_chosen(ablation._evaluate(cfg, models, budget_s=600))
    assert [(r["name"], "val_scr" in r, r.get("chosen")) for r in rows] == \
        [("sft", True, None), ("sft+tto", False, None), ("grpo", True, False), ("grpo@1", True, True)]
    assert rows[0]["val_scr"] is not None and rows[2]["val_scr"] is None
    validation = [it.id for it in load_benchmark("test", n=2, seed=1, progress=False)]
    assert [ids for _, ids, _ in calls] == [[f"test-{k:05d}" for k in range(3)], validation] * 3
    assert all(options == calls[0][2] for _, _, options in calls)  # one decoding for both draws
    kept = tmp_path / "layouts" / "validation"
    assert _layouts(kept / "grpo-1.jsonl.gz") == _draw(1, n=2)
    source = json.loads((kept / "grpo-1.source.json").read_text())
    assert source["split"] == {"name": "test", "seed": 1, "n": 2}
    result = {"rows": rows, "gpu": "cpu", "commands": ["pytest"]}
    ablation.write_ablation(check_ablation(result), tmp_path / "ablation.json")
    assert "| grpo@1 (chosen) |" in (tmp_path / "ablation.md").read_text()
    capsys.readouterr()
    again = mark_chosen(ablation._evaluate(cfg, models, budget_s=600))
    assert len(calls) == 6 and capsys.readouterr().err.count("layouts read from") == 6
    assert [(r.get("val_scr"), r.get("chosen")) for r in again] == [(r.get("val_scr"), r.get("chosen"))
                                                                   for r in rows]


def test_decode_only_keeps_every_models_layouts_and_the_scoring_run_re_scores_them(tmp_path, stub_decoding,
                                                                                   monkeypatch, capsys):
    """ablation.decode_only=true decodes the SFT model, the RL run and its kept checkpoint into
    ablation.layouts with their source records, trains and scores nothing, and names a variant whose
    model is not there; the same table without it re-scores all three instead of decoding them. Layouts
    already kept are not decoded twice."""
    calls, _ = stub_decoding
    cfg = _config(tmp_path, "ablation.decode_only=true", "ablation.checkpoints=true",
                  "ablation.variants=[grpo,pada]")
    run = tmp_path / "run"
    _model(run / "sft", steps=0)
    _model(run / "grpo", steps=2)
    (_model(run / "grpo" / "checkpoint-1") / "adapter_config.json").write_text("{}")
    monkeypatch.setattr(ablation, "_evaluate", lambda *a, **k: pytest.fail("decode_only scored"))
    monkeypatch.setattr(ablation, "run_anchors", lambda *a, **k: pytest.fail("decode_only made anchors"))
    result = ablation.run_ablation(cfg)
    assert result["rows"] == [] and [c[0] for c in calls] == ["sft", "grpo", "checkpoint-1"]
    assert result["decode_only"]["decoded"] == [f"{n} (test, seed 0)" for n in ("sft", "grpo", "grpo@1")]
    assert result["decode_only"]["missing"] == [f"pada: {run / 'pada'}"]
    for name in ("sft", "grpo", "grpo-1"):
        assert _layouts(tmp_path / "layouts" / f"{name}.jsonl.gz") == _draw(0)
        assert (tmp_path / "layouts" / f"{name}.source.json").is_file()
    again = ablation.run_ablation(cfg)
    assert len(calls) == 3 and again["decode_only"]["kept"] == result["decode_only"]["decoded"]
    capsys.readouterr()
    monkeypatch.undo()
    monkeypatch.setattr(ablation, "_completions", lambda *a, **k: pytest.fail("decoded again"))
    models = {"sft": run / "sft", "grpo": run / "grpo", "grpo@1": run / "grpo" / "checkpoint-1"}
    rows = ablation._evaluate(_config(tmp_path), models, budget_s=600)
    assert [r["name"] for r in rows] == ["sft", "sft+tto", "grpo", "grpo@1"]
    assert capsys.readouterr().err.count("layouts read from") == 3


def test_a_final_model_kept_as_a_checkpoint_row_after_a_resume_is_not_decoded_again(tmp_path, stub_decoding,
                                                                                    capsys):
    """A run decoded at its end (row ``grpo``, 2 steps) and then resumed to 3 steps: its step-2
    checkpoint (the same files, so the same source) becomes row ``grpo@2``, which takes the ``grpo``
    row's layouts before the new final model's replace them, under decode_only and in a scoring run
    alike; only the new final model is decoded."""
    import shutil

    calls, _ = stub_decoding
    cfg = _config(tmp_path, "ablation.decode_only=true", "ablation.checkpoints=true",
                  "ablation.variants=[grpo]")
    run = tmp_path / "run"
    _model(run / "sft", steps=0)
    (_model(run / "grpo", steps=2) / "adapter_config.json").write_text("{}")
    ablation.run_ablation(cfg)
    assert [c[0] for c in calls] == ["sft", "grpo"]
    shutil.copytree(tmp_path / "layouts", tmp_path / "scored")
    # the run goes on: its files at step 2 become checkpoint-2, its final model has 3 steps
    (run / "grpo").rename(tmp_path / "step2")
    (_model(run / "grpo", steps=3) / "config.json").write_text(json.dumps({"steps": 3}))
    (tmp_path / "step2").rename(run / "grpo" / "checkpoint-2")
    again = ablation.run_ablation(cfg)
    assert [c[0] for c in calls] == ["sft", "grpo", "grpo"]  # the new final model alone
    assert again["decode_only"]["kept"] == ["sft (test, seed 0)", "grpo@2 (test, seed 0) (as grpo.jsonl.gz)"]
    step2 = json.loads((tmp_path / "layouts" / "grpo-2.source.json").read_text())
    assert step2["model"] == checkpoint_digest(run / "grpo" / "checkpoint-2")
    capsys.readouterr()
    models = {"sft": run / "sft", "grpo": run / "grpo", "grpo@2": run / "grpo" / "checkpoint-2"}
    ablation._evaluate(_config(tmp_path, f"ablation.layouts={tmp_path / 'scored'}"), models, budget_s=600)
    assert [c[0] for c in calls] == ["sft", "grpo", "grpo", "grpo"]  # again the new final model alone
    assert "grpo@2 layouts read from" in capsys.readouterr().err


def test_checkpoints_as_a_list_of_steps_takes_those_that_were_kept(tmp_path, stub_decoding):
    """ablation.checkpoints=[2,4] decodes the kept checkpoints of those steps (a step not kept, or the
    final model's own, is no row); anything but true, false or a list of steps is one clear error."""
    calls, _ = stub_decoding
    run = tmp_path / "run"
    _model(run / "sft", steps=0)
    _model(run / "grpo", steps=4)
    for step in (1, 2, 3):
        (_model(run / "grpo" / f"checkpoint-{step}") / "adapter_config.json").write_text("{}")
    cfg = _config(tmp_path, "ablation.decode_only=true", "ablation.checkpoints=[2,4,5]",
                  "ablation.variants=[grpo]")
    result = ablation.run_ablation(cfg)
    assert [c[0] for c in calls] == ["sft", "grpo", "checkpoint-2"]
    assert result["decode_only"]["decoded"] == [f"{n} (test, seed 0)" for n in ("sft", "grpo", "grpo@2")]
    models = {"grpo": run / "grpo"}
    assert list(ablation.checkpoint_models(models, True)) == ["grpo@1", "grpo@2", "grpo@3"]
    with pytest.raises(TrainingSetupError, match="ablation.checkpoints is true, false or a list of RL steps"):
        ablation.checkpoint_models(models, "100")


def test_decode_only_needs_a_layouts_folder(tmp_path):
    with pytest.raises(TrainingSetupError, match="decode_only keeps the layouts .* set ablation.layouts"):
        ablation.run_ablation(_config(tmp_path, "ablation.decode_only=true", "ablation.layouts=null"))


def test_the_adapters_are_decoded_on_the_tables_sft_model(tmp_path, stub_decoding):
    """Every row is decoded with base= the table's SFT model: an RL adapter names its training host's
    base path, which a run carried to another host does not have."""
    calls, _ = stub_decoding
    models = {"sft": _model(tmp_path / "sft"), "grpo": _model(tmp_path / "grpo", steps=2)}
    ablation._evaluate(_config(tmp_path), models, budget_s=600)
    assert [options["base"] for _, _, options in calls] == [tmp_path / "sft"] * 2


def test_a_rerun_keeps_the_rows_scored_from_the_same_layouts_by_the_same_code(tmp_path, stub_decoding,
                                                                              monkeypatch, capsys):
    """A table evaluated again takes each row (reference, SFT, SFT + TTO, an RL row) as an earlier
    evaluation kept it beside its layouts: nothing is scored again. A changed checkpoint has its row
    decoded and scored again, the others kept; other scoring code, or ablation.reuse=false, scores
    every row again."""
    from physcene.eval import harness

    scored, score = [], harness.score_scenes

    def counted(items, outputs, *args, **kwargs):
        scored.append(len(outputs))
        return score(items, outputs, *args, **kwargs)

    monkeypatch.setattr(harness, "score_scenes", counted)
    calls, _ = stub_decoding
    cfg = _config(tmp_path, "ablation.reference=true")
    models = {"sft": _model(tmp_path / "sft"), "grpo": _model(tmp_path / "grpo", steps=2)}
    first = ablation._evaluate(cfg, models, budget_s=600)
    assert [r["name"] for r in first] == ["reference", "sft", "sft+tto", "grpo"] and len(scored) == 4
    capsys.readouterr()
    again = ablation._evaluate(cfg, models, budget_s=600)
    assert again == first and len(scored) == 4 and len(calls) == 2
    assert capsys.readouterr().err.count("figures kept from") == 4
    (tmp_path / "grpo" / "config.json").write_text(json.dumps({"name": "grpo", "trained": "more"}))
    ablation._evaluate(cfg, models, budget_s=600)
    assert len(scored) == 5 and [c[0] for c in calls] == ["sft", "grpo", "grpo"]
    assert capsys.readouterr().err.count("figures kept from") == 3
    monkeypatch.setattr(ablation, "scoring_code_digest", lambda: "other code")
    assert ablation._evaluate(cfg, models, budget_s=600) == ablation._evaluate(cfg, models, budget_s=600)
    assert len(scored) == 9  # once under the other code, then kept
    ablation._evaluate(OmegaConf.merge(cfg, {"ablation": {"reuse": False}}), models, budget_s=600)
    assert len(scored) == 13 and len(calls) == 5  # reuse=false: every model decoded and scored again
