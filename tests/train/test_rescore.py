"""rescore: a table's rows scored again from their layouts, with what the layouts do not give kept."""

from __future__ import annotations

import json

import pytest

from physcene.eval.harness import make_judge, score_scenes
from physcene.layout import write_layout_records
from physcene.physics import PhysicsEngine
from physcene.train.ablation import _load_split, layout_records, table_row
from physcene.train.analysis.rescore import main, rescore_table

SPLIT = {"name": "test", "seed": 0, "n": 4}


def test_rows_are_scored_again_from_their_layouts(tmp_path):
    items = _load_split(SPLIT)
    references = [it.reference for it in items]
    layouts = write_layout_records(layout_records(items, references), tmp_path / "reference.jsonl.gz")
    engine = PhysicsEngine(device="cpu")
    results = score_scenes(items, references, make_judge("rule", references), engine, progress=False)
    truth = table_row("reference", items, references, results, engine, seed=0, rl_steps=0)
    stale = {**truth, "scr": 0.3, "judge_avg": 1.0, "layouts": str(layouts),  # 0.3: no SCR of 4 scenes
             "anchor_nll": 0.5}
    table = tmp_path / "ablation.json"
    table.write_text(json.dumps({"rows": [stale], "checkpoint_rows": [], "gpu": "none", "commands": [],
                                 "test_split": SPLIT}))
    changed = rescore_table(table, root="/")
    assert [c["name"] for c in changed] == ["reference"]
    assert changed[0]["before"]["scr"] == 0.3 and changed[0]["after"]["scr"] == truth["scr"]
    (row,) = json.loads(table.read_text())["rows"]
    assert {k: row[k] for k in ("scr", "acr", "qpr7", "judge_avg", "floating", "shrunk", "out_of_zone")} == \
        {k: truth[k] for k in ("scr", "acr", "qpr7", "judge_avg", "floating", "shrunk", "out_of_zone")}
    assert row["anchor_nll"] == 0.5 and row["layouts"] == str(layouts)  # what the layouts do not give
    assert rescore_table(table, root="/") == []  # scored with the same code: nothing moves
    assert rescore_table(table, root="/", seed=1) == []  # no row of seed 1
    assert (tmp_path / "ablation.md").is_file()


def test_a_table_without_its_split_is_refused(tmp_path):
    table = tmp_path / "ablation.json"
    table.write_text(json.dumps({"rows": [], "gpu": "none", "commands": []}))
    with pytest.raises(ValueError, match=r"ablation.json: no test_split \(name, seed, n\)"):
        main([str(table)])
