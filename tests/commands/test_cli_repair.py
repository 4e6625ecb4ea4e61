"""``physcene repair``: layout.json, directory trees and JSONL datasets in, the same structure out."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from physcene.cli import main
from physcene.data.noisy import noisy_scenes
from physcene.layout import layout_to_dict, load_layout, read_layout, write_layout


@pytest.fixture(scope="module")
def scenes():
    return noisy_scenes(3, 6, seed=21, push_cm=10.0)


def _check_report(entry: dict) -> None:
    for key in ("energy_before", "energy_after", "max_displacement_cm", "relations", "unsatisfied",
                "max_depth_before_cm", "max_depth_after_cm"):
        assert key in entry
    assert entry["energy_after"] <= entry["energy_before"]
    assert entry["relations"]["in_on_kept"] == 1.0


def test_repair_one_layout(tmp_path, scenes, capsys):
    src = write_layout(scenes[0], tmp_path / "in" / "layout.json")
    out = tmp_path / "out" / "layout.json"
    assert main(["repair", str(src), "-o", str(out), "steps=60"]) == 0
    repaired = read_layout(out)
    assert repaired.ids() == scenes[0].ids()
    [entry] = json.loads((tmp_path / "out" / "layout.report.json").read_text())
    _check_report(entry)
    assert "repaired 1 scene(s)" in capsys.readouterr().out


def test_repair_tree_mirrors_structure(tmp_path, scenes):
    root = tmp_path / "Layout_info"
    for k, scene in enumerate(scenes[:2]):
        write_layout(replace(scene, scene_type=""), root / "office_table" / f"scene_{k}" / "layout.json")
    out = tmp_path / "fixed"
    assert main(["repair", str(tmp_path), "-o", str(out), "steps=40"]) == 0
    written = sorted(p.relative_to(out).as_posix() for p in out.rglob("layout.json"))
    assert written == [f"Layout_info/office_table/scene_{k}/layout.json" for k in range(2)]
    report = json.loads((out / "repair_report.json").read_text())
    assert [r["layout"] for r in report] == written
    for entry in report:
        _check_report(entry)
    assert read_layout(out / written[0]).scene_type == "office table"


def test_repair_jsonl_keeps_records(tmp_path, scenes):
    src = tmp_path / "data.jsonl"
    records = [{"id": f"s{k}", "instruction": "tidy desk", "layout": layout_to_dict(s)}
               for k, s in enumerate(scenes)]
    src.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "fixed.jsonl"
    assert main(["repair", str(src), "-o", str(out), "--device", "cpu", "steps=40"]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["id"] for r in records] == ["s0", "s1", "s2"]
    assert all(r["instruction"] == "tidy desk" and r["layout"]["objects"] for r in records)
    report = json.loads((tmp_path / "fixed.report.json").read_text())
    assert [r["id"] for r in report] == ["s0", "s1", "s2"]
    for entry in report:
        _check_report(entry)


def test_repair_jsonl_writes_the_completion_of_the_repaired_layout(tmp_path, scenes):
    """`physcene data` records carry the CTRC completion of their layout: repairing the dataset
    re-writes it from the repaired layout at the precision it had (SFT reads the completion)."""
    from physcene.ctrc import completion_text, decimals_of, parse
    from physcene.graph import build_hierarchy

    hierarchies = [build_hierarchy(s) for s in scenes]
    src = tmp_path / "train.jsonl"
    src.write_text("".join(json.dumps({"id": f"s{k}", "prompt": "p", "layout": layout_to_dict(h),
                                       "completion": completion_text(h, decimals=2)}) + "\n"
                           for k, h in enumerate(hierarchies)))
    out = tmp_path / "fixed.jsonl"
    assert main(["repair", str(src), "-o", str(out), "--device", "cpu", "steps=40"]) == 0
    assert decimals_of(completion_text(hierarchies[0], decimals=2)) == 2  # the noisy poses have 2
    report = json.loads((tmp_path / "fixed.report.json").read_text())
    for record, before in zip(map(json.loads, out.read_text().splitlines()), hierarchies):
        assert record["prompt"] == "p" and decimals_of(record["completion"]) == 2
        written = parse(record["completion"])
        repaired = load_layout(record["layout"])
        for o in written.objects:
            np.testing.assert_allclose(o.center, repaired.get(o.instance_id).center, atol=0.02)
        assert written.ids() != [] and sorted(written.ids()) == sorted(before.ids())
    assert max(entry["max_displacement_cm"] for entry in report) > 0.5  # the old text would be wrong


def test_repair_refuses_decimals_out_of_range(tmp_path, capsys):
    assert main(["repair", "x.jsonl", "-o", str(tmp_path / "o.jsonl"), "--decimals", "9"]) == 2
    assert "--decimals must be from 0 to 8, got 9" in capsys.readouterr().err


@pytest.mark.parametrize("content, message", [
    ('{"id": 1}\n', "expected a record with a 'layout' object"),
    ("not json\n", "invalid JSON"),
])
def test_bad_jsonl_exits_2_naming_the_line(tmp_path, capsys, content, message):
    src = tmp_path / "bad.jsonl"
    src.write_text(content)
    assert main(["repair", str(src), "-o", str(tmp_path / "o.jsonl")]) == 2
    err = capsys.readouterr().err
    assert message in err and f"{src}:1" in err and "Traceback" not in err


def test_bad_override_and_missing_input_exit_2(tmp_path, scenes, capsys):
    src = write_layout(scenes[0], tmp_path / "layout.json")
    assert main(["repair", str(src), "-o", str(tmp_path / "o.json"), "stepz=3"]) == 2
    assert "tto.yaml: unknown keys ['stepz']" in capsys.readouterr().err
    assert main(["repair", str(tmp_path / "missing.json"), "-o", str(tmp_path / "o.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()


def test_repair_a_table_rows_gzipped_layouts(tmp_path, scenes):
    """A table row's layouts (``.jsonl.gz``, as the ablation and plan_following write them) repair into
    the table's ``sft+tto`` form: gzipped out, byte-identical on a rerun, an output that did not parse
    passed through as it was, a model's out-of-bounds size repaired as eval scored it."""
    import gzip

    from physcene.layout import write_layout_records

    big = layout_to_dict(scenes[1])
    big["objects"][0]["size"] = [1610.0, 5.0, 5.0]  # a model's output eval scores as written
    records = [{"id": "t0", "level": 2, "layout": layout_to_dict(scenes[0])},
               {"id": "t1", "level": 3, "layout": None, "parse_error": "no complete layout JSON"},
               {"id": "t2", "level": 3, "layout": big}]
    src = write_layout_records(records, tmp_path / "sft.jsonl.gz")
    out = tmp_path / "sft_tto.jsonl.gz"
    assert main(["repair", str(src), "-o", str(out), "--quiet", "steps=40"]) == 0
    written = [json.loads(line) for line in gzip.decompress(out.read_bytes()).decode().splitlines()]
    assert [r["id"] for r in written] == ["t0", "t1", "t2"]
    assert written[1] == records[1]
    assert written[0]["layout"] != records[0]["layout"] and written[2]["layout"]["objects"]
    report = json.loads((tmp_path / "sft_tto.report.json").read_text())
    assert report[1] == {"record": 1, "id": "t1", "skipped": "no layout (parse_error)"}
    _check_report(report[0])
    first = out.read_bytes()
    assert main(["repair", str(src), "-o", str(out), "--quiet", "steps=40"]) == 0
    assert out.read_bytes() == first


def test_repair_refuses_an_unreadable_gzip_and_writes_nothing(tmp_path, capsys):
    src = tmp_path / "rows.jsonl.gz"
    src.write_text("not gzip")
    out = tmp_path / "fixed.jsonl.gz"
    assert main(["repair", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "rows.jsonl.gz: cannot be read" in err and not out.exists()
