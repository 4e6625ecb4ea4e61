"""The ablation table's schema (docs/results/ablation.json): rows recomputable from their gzipped
layouts by `physcene check` and `physcene eval --generator file:...`, and the learning curves."""

from __future__ import annotations

import gzip
import json

import pytest

from physcene.cli import main
from physcene.ctrc import ParseError
from physcene.eval.harness import generate, load_benchmark, make_judge, score_scenes
from physcene.layout import layout_record_lines, write_layout_records
from physcene.train.ablation import ROW_KEYS, check_ablation, row_file, table_row
from physcene.train.ablation_plot import learning_curves, learning_curves_svg, write_learning_curves


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """Rows of the reference and the heuristic placer on 4 test scenes (the placer's last output
    replaced by one that did not parse), their layouts under ``layouts/``."""
    from physcene.physics import PhysicsEngine

    folder = tmp_path_factory.mktemp("ablation")
    items = load_benchmark("test", n=4, progress=False)
    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine()
    rows = []
    for name, generator, steps in (("reference", "reference", 0), ("pada", "heuristic", 50)):
        outputs = generate(items, generator, progress=False)
        if name == "pada":
            outputs[-1] = ParseError("truncated JSON at char 12")
        results = score_scenes(items, outputs, judge, engine, progress=False)
        rows.append(table_row(name, items, outputs, results, engine, seed=0, rl_steps=steps,
                              layouts=folder / "layouts"))
    return folder, {"rows": rows, "gpu": "cpu", "commands": ["pytest"]}


def test_rows_have_the_schema_and_name_their_layouts(table):
    folder, data = table
    assert check_ablation(data) is data
    reference, pada = data["rows"]
    assert set(ROW_KEYS) <= set(reference) and reference["rl_steps"] == 0 and pada["rl_steps"] == 50
    assert reference["parse_rate"] == 1.0 and pada["parse_rate"] == 0.75
    assert reference["shrunk"] == 0.0 and reference["out_of_zone"] == 0.0
    assert all(0.0 <= pada[k] <= 1.0 for k in ("scr", "floating", "shrunk", "out_of_zone", "qpr8", "qpr9"))
    assert pada["layouts"].endswith("layouts/pada.jsonl.gz")
    records = [json.loads(line) for _, line in layout_record_lines(folder / "layouts" / "pada.jsonl.gz")]
    assert [r["layout"] is None for r in records] == [False, False, False, True]
    assert records[-1]["parse_error"] == "truncated JSON at char 12"
    bad = {**data, "rows": [{**pada, "shrunk": 3.0}]}
    with pytest.raises(ValueError, match=r"row 0 \(pada\): shrunk must be a fraction"):
        check_ablation(bad)
    with pytest.raises(ValueError, match=r"row 0 \(sft\) lacks \['layouts'\]"):
        unnamed = {k: v for k, v in pada.items() if k != "layouts"} | {"name": "sft"}
        check_ablation({**data, "rows": [unnamed]})
    assert row_file("pada*") == "pada_star.jsonl.gz" and row_file("sft+tto") == "sft_tto.jsonl.gz"
    assert row_file("pada@12", ".source.json") == "pada-12.source.json"


def test_eval_and_check_read_the_gzipped_layouts_and_recompute_the_row(table, tmp_path, capsys):
    folder, data = table
    pada = data["rows"][1]
    path = folder / "layouts" / "pada.jsonl.gz"
    assert main(["eval", "--generator", f"file:{path}", "--n", "4", "--out", str(tmp_path / "eval"),
                 "--quiet", "--json", "render=0", "save_layouts=false"]) == 0
    summary = next(iter(json.loads(capsys.readouterr().out)["methods"].values()))["summary"]
    assert summary["collision"]["0.0"]["SCR"] == pytest.approx(pada["scr"])
    assert summary["parse_errors"] == 1 and summary["judge"]["avg"] == pytest.approx(pada["judge_avg"])
    assert main(["check", str(path), "--json", "--quiet"]) == 2  # the record that did not parse
    scenes = json.loads(capsys.readouterr().out)["scenes"]
    assert [s["error"] is None for s in scenes] == [True, True, True, False]
    assert "did not parse: truncated JSON" in scenes[-1]["error"]
    broken = tmp_path / "broken.jsonl.gz"
    broken.write_bytes(b"not gzip")
    assert main(["eval", "--generator", f"file:{broken}", "--n", "1", "--out", str(tmp_path / "e2")]) == 2
    assert f"generator file:{broken}: cannot be read" in capsys.readouterr().err


def test_write_layout_records_is_gzip_by_suffix_and_byte_stable(tmp_path):
    records = [{"id": "a", "layout": None, "parse_error": "x"}]
    first = write_layout_records(records, tmp_path / "a.jsonl.gz").read_bytes()
    assert first == write_layout_records(records, tmp_path / "b.jsonl.gz").read_bytes()  # no mtime inside
    assert gzip.decompress(first).decode() == json.dumps(records[0]) + "\n"
    assert write_layout_records(records, tmp_path / "c.jsonl").read_text() == json.dumps(records[0]) + "\n"


def test_learning_curves_start_at_the_sft_row(table, tmp_path):
    _, data = table
    pada = data["rows"][1]
    rows = [{**pada, "name": "sft", "rl_steps": 0, "scr": 0.9},
            {**pada, "name": "pada@25", "scr": 0.7, "rl_steps": 25}, pada,
            {**pada, "name": "grpo", "seed": 1, "scr": 0.8}, {**pada, "name": "reference", "scr": 0.8},
            {"name": "pada*", "skipped": "no anchors"}]
    curves = learning_curves({"rows": rows})
    assert curves[("pada", 0)] == [(0, 0.9), (25, 0.7), (50, pada["scr"])]
    assert curves[("grpo", 1)] == [(50, 0.8)]  # no SFT row of seed 1
    assert curves[("reference", 0)] == [(0, 0.8)] and ("pada*", 0) not in curves
    svg = learning_curves_svg({"rows": rows})
    assert svg.startswith("<svg") and svg.count("<polyline") == 2 and "pada (seed 0)" in svg
    source = tmp_path / "ablation.json"
    source.write_text(json.dumps({"rows": rows, "gpu": "cpu", "commands": []}))
    assert write_learning_curves(source).read_text() == svg
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_learning_curves(tmp_path / "none.json")


def test_seeds_merge_into_one_table_with_their_layouts(table, tmp_path):
    """`physcene train ablation-merge`: two seeds' tables become one (rows keep their seed, the curves
    get a line per seed), every row's layouts copied to <layouts>/s<seed>/ and named there; a row in
    both sources (same name, seed and steps) is refused."""
    folder, data = table
    seed1 = {**data, "gpu": "cpu", "rows": [{**r, "seed": 1} for r in data["rows"]]}
    for name, d in (("s0.json", data), ("s1.json", seed1)):
        (tmp_path / name).write_text(json.dumps(d))
    out, layouts = tmp_path / "merged" / "ablation.json", tmp_path / "merged" / "layouts"
    assert main(["train", "ablation-merge", "--config", "tiny", f"ablation.output={out}",
                 "--sources", str(tmp_path / "s0.json"), str(tmp_path / "s1.json"),
                 "--layouts", str(layouts)]) == 0
    merged = check_ablation(json.loads(out.read_text()))
    assert [(r["name"], r["seed"]) for r in merged["rows"]] == [("reference", 0), ("pada", 0),
                                                                ("reference", 1), ("pada", 1)]
    assert merged["gpu"] == "cpu" and merged["commands"] == ["pytest"]
    for row in merged["rows"]:
        copy = layouts / f"s{row['seed']}" / row_file(row["name"])
        assert copy.is_file() and row["layouts"].endswith(f"s{row['seed']}/{row_file(row['name'])}")
    assert {("pada", 0), ("pada", 1)} <= set(learning_curves(merged))
    assert out.with_suffix(".md").is_file() and out.with_suffix(".svg").is_file()
    assert main(["train", "ablation-merge", "--config", "tiny", f"ablation.output={out}",
                 "--sources", str(tmp_path / "s0.json"), str(tmp_path / "s0.json")]) != 0


def test_a_merged_table_grows_by_a_new_seed_in_place(table, tmp_path):
    """The merged table is itself a source: seed 1's table merged into it, written over it with the same
    layouts folder, keeps seed 0's rows and their layouts files as they were and adds seed 1's."""
    from physcene.train.ablation import merge_ablations

    _, data = table
    (tmp_path / "s0.json").write_text(json.dumps(data))
    out, layouts = tmp_path / "docs" / "ablation.json", tmp_path / "docs" / "ablation"
    merge_ablations([tmp_path / "s0.json"], out, layouts)
    kept = {p.name: p.read_bytes() for p in (layouts / "s0").iterdir()}
    grown = tmp_path / "grown_from.json"
    grown.write_text(out.read_text())
    seed1 = {**data, "rows": [{**r, "seed": 1} for r in data["rows"]]}
    (tmp_path / "s1.json").write_text(json.dumps(seed1))
    merged = merge_ablations([grown, tmp_path / "s1.json"], out, layouts)
    assert [(r["name"], r["seed"]) for r in merged["rows"]] == [("reference", 0), ("pada", 0),
                                                                ("reference", 1), ("pada", 1)]
    assert {p.name: p.read_bytes() for p in (layouts / "s0").iterdir()} == kept
    assert sorted(p.name for p in (layouts / "s1").iterdir()) == sorted(kept)


def test_tables_of_different_test_draws_are_not_merged(table, tmp_path):
    """Two seeds' tables scored on different draws of the test split (``test_split``) are refused with
    one error naming both draws; the same draw merges and the merged table records it."""
    from physcene.train.ablation import merge_ablations

    _, data = table
    split = {"name": "test", "seed": 0, "n": 4}
    seed1 = {**data, "rows": [{**r, "seed": 1} for r in data["rows"]]}
    (tmp_path / "s0.json").write_text(json.dumps({**data, "test_split": split}))
    (tmp_path / "s1.json").write_text(json.dumps({**seed1, "test_split": {**split, "seed": 1}}))
    with pytest.raises(ValueError, match="different draws"):
        merge_ablations([tmp_path / "s0.json", tmp_path / "s1.json"], tmp_path / "bad.json")
    (tmp_path / "s1.json").write_text(json.dumps({**seed1, "test_split": split}))
    merged = merge_ablations([tmp_path / "s0.json", tmp_path / "s1.json"], tmp_path / "ok.json")
    assert merged["test_split"] == split
