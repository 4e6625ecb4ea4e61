"""physcene.eval.analysis.crowding: how full the tables are and how close table-level neighbours stand, on the
synthetic split's clean and noisy layouts and on layout files."""

from __future__ import annotations

import json

import pytest

from physcene.data.benchmark import DataConfig, build_record, build_scenes
from physcene.data.splits import plan_split
from physcene.eval.analysis import crowding
from physcene.layout import write_layout
from physcene.scene import TABLE


@pytest.fixture(scope="module")
def scenes():
    items = [i for i in plan_split("test", 40, 0) if i.level >= 3][:4]
    return [(i, build_scenes("test", 0, i, DataConfig())) for i in items]


def test_build_record_is_built_from_build_scenes():
    item = next(iter(plan_split("test", 1, 0)))
    record = build_record("test", 0, item, DataConfig())
    _, noisy, noise, _ = build_scenes("test", 0, item, DataConfig())
    assert record["noise"] == noise.as_dict()
    assert len(noisy) == record["n_objects"]


def test_clean_layouts_leave_gaps_and_stacking_everything_on_one_spot_overlaps(scenes):
    for _, (clean, _, _, _) in scenes:
        gaps = crowding.nearest_gaps(clean)
        assert gaps and min(gaps) >= 0.0
        assert 0.0 < crowding.crowd(clean) < 1.0
        first = crowding.table_level(clean)[0]
        piled = clean.with_objects(o.moved(center=(first.center[0], first.center[1], o.center[2]))
                                   if o.parent == TABLE else o for o in clean.objects)
        assert max(crowding.nearest_gaps(piled)) < 0.0


def test_the_script_reads_layout_folders_by_record_id(scenes, tmp_path, monkeypatch, capsys):
    folder = tmp_path / "noisy_as_files"
    folder.mkdir()
    for item, (_, noisy, _, _) in scenes:
        write_layout(noisy, folder / f"test-{item.index:05d}.json")
    out = tmp_path / "crowding.json"
    monkeypatch.setattr("sys.argv", ["crowding.py", "--n", "40", f"files={folder}", "--out", str(out)])
    crowding.main()
    rows = json.loads(out.read_text())["rows"]
    assert rows["clean"]["3"]["overlapping_share"] == 0.0
    direct = crowding.level_rows([(i.level, noisy) for i, (_, noisy, _, _) in scenes])
    assert rows["files"].keys() == direct.keys()
    for level, row in rows["files"].items():  # the files hold the noisy scenes: the same figures
        assert row["n"] == direct[level]["n"]
        for key in ("crowd_median", "gap_median_cm", "overlapping_share"):
            assert row[key] == pytest.approx(direct[level][key], abs=0.02)
    assert "files" in capsys.readouterr().out


def test_the_script_reads_a_file_of_layout_records(scenes, tmp_path, monkeypatch):
    """NAME=FILE.jsonl.gz (the ablation's row files): the same figures as a folder of the same layouts;
    a record whose layout is null (did not parse) is left out."""
    import gzip

    from physcene.layout import layout_to_dict

    path = tmp_path / "rows.jsonl.gz"
    with gzip.open(path, "wt") as f:
        for item, (_, noisy, _, _) in scenes:
            f.write(json.dumps({"id": f"test-{item.index:05d}", "layout": layout_to_dict(noisy)}) + "\n")
        f.write(json.dumps({"id": "test-00000", "layout": None, "parse_error": "cut"}) + "\n")
    out = tmp_path / "crowding.json"
    monkeypatch.setattr("sys.argv", ["crowding.py", "--n", "40", f"records={path}", "--out", str(out)])
    crowding.main()
    rows = json.loads(out.read_text())["rows"]["records"]
    direct = crowding.level_rows([(i.level, noisy) for i, (_, noisy, _, _) in scenes])
    assert rows.keys() == direct.keys() and all(rows[k]["n"] == direct[k]["n"] for k in direct)
