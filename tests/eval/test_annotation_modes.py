"""physcene.eval.analysis.annotation_modes: SCR on the scenes the data annotated carefully and carelessly,
for the split's layouts and for layout files."""

from __future__ import annotations

import gzip
import json

import pytest

from physcene.data.benchmark import DataConfig, build_scenes
from physcene.data.splits import plan_split
from physcene.eval.analysis import annotation_modes
from physcene.layout import layout_to_dict

N = 8


def test_rows_split_each_level_by_the_annotation():
    entries = [(1, True, 0.0), (1, True, 2.0), (1, False, 3.0), (2, False, 0.0), (2, False, 1.0)]
    rows = annotation_modes.annotation_rows(entries)
    assert rows["1"]["careful"] == {"n": 2, "scr": 0.5, "median_deepest_cm": 2.0}
    assert rows["1"]["careless"] == {"n": 1, "scr": 1.0, "median_deepest_cm": 3.0}
    assert rows["2"]["careful"] == {"n": 0, "scr": None, "median_deepest_cm": None}
    assert rows["all"]["n"] == 5 and rows["all"]["scr"] == pytest.approx(3 / 5)
    assert rows["all"]["careless"]["median_deepest_cm"] == 2.0  # of 3.0 and 1.0: the colliding scenes only


def test_a_file_of_the_reference_layouts_reads_as_the_reference(tmp_path, monkeypatch, capsys):
    items = plan_split("test", N, 0)
    scenes = [(f"test-{i.index:05d}", build_scenes("test", 0, i, DataConfig())) for i in items]
    path = tmp_path / "reference.jsonl.gz"
    with gzip.open(path, "wt") as f:
        for rid, (_, noisy, _, _) in scenes:
            f.write(json.dumps({"id": rid, "layout": layout_to_dict(noisy)}) + "\n")
    out = tmp_path / "modes.json"
    argv = ["annotation_modes.py", "--n", str(N), f"files={path}", "--out", str(out)]
    monkeypatch.setattr("sys.argv", argv)
    annotation_modes.main()
    result = json.loads(out.read_text())
    rows = result["rows"]
    assert rows["files"] == rows["reference"]
    careful = sum(noise.careful for _, (_, _, noise, _) in scenes)
    assert rows["reference"]["all"]["careful"]["n"] == careful
    assert rows["reference"]["all"]["careless"]["n"] == N - careful
    assert rows["clean"]["all"]["n"] == N
    assert result["careful_by_level"] == list(DataConfig().noise.careful_by_level)
    assert "files" in capsys.readouterr().out


def test_a_layouts_argument_without_a_name_is_a_usage_error(monkeypatch, capsys):
    monkeypatch.setattr("sys.argv", ["annotation_modes.py", "--n", "2", "rows.jsonl.gz"])
    with pytest.raises(SystemExit) as err:
        annotation_modes.main()
    assert err.value.code == 2 and "expected NAME=FILE" in capsys.readouterr().err
