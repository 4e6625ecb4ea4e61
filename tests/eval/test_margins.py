"""physcene.eval.analysis.margins: a margin between table-level neighbours removes near-contacts, not
overlaps; carriers and what they carry keep their sizes; the script reads a layout-records file."""

from __future__ import annotations

import gzip
import json
from types import SimpleNamespace

import pytest

from physcene.assets import primitive_asset
from physcene.data.splits import plan_split
from physcene.eval.analysis import margins
from physcene.layout import layout_to_dict
from physcene.physics import PhysicsEngine
from physcene.scene import TABLE, Scene, SceneObject, Zone


class Boxes:
    """Every category an exact box: penetration depths are the boxes' overlaps."""

    def __init__(self):
        self.box = primitive_asset("box", n_points=512)

    def resolve(self, category, asset_id=None):
        return SimpleNamespace(asset=self.box, fallback=None)


@pytest.fixture(scope="module")
def engine():
    return PhysicsEngine(Boxes())


def two_boxes(overlap_cm: float) -> Scene:
    """Two 10 cm boxes on the table, overlapping by ``overlap_cm`` along x, and a third carried by the
    first (its parent keeps its size)."""
    a = SceneObject("1_box_0", "box", (20.0, 20.0, 5.0), (10.0, 10.0, 10.0), parent=TABLE, relation="near")
    b = SceneObject("2_box_0", "box", (30.0 - overlap_cm, 20.0, 5.0), (10.0, 10.0, 10.0), parent=TABLE,
                    relation="near")
    tray = SceneObject("3_tray_0", "box", (60.0, 20.0, 1.0), (20.0, 20.0, 2.0), parent=TABLE, relation="near")
    cup = SceneObject("4_cup_0", "box", (60.0, 20.0, 4.0), (6.0, 6.0, 4.0), parent="3_tray_0", relation="on")
    return Scene(Zone(0.0, 120.0, 0.0, 60.0), (a, b, tray, cup))


def test_a_margin_removes_a_near_contact_and_leaves_an_overlap(engine):
    scenes = [(2, two_boxes(0.4)), (3, two_boxes(5.0))]
    rows = margins.margin_rows(scenes, [0.0, 1.0, 2.0, -2.0], engine)
    assert rows["0"]["scr"] == 1.0  # both collide as written
    assert rows["1"]["scr_by_level"] == {"2": 0.0, "3": 1.0}  # 0.5 cm a side clears 0.4 cm, not 5 cm
    assert rows["2"]["scr"] == 0.5
    assert rows["-2"]["scr"] == 1.0  # a negative margin grows the footprints
    assert rows["0"]["table_pairs_only"] == 1.0


def test_carriers_and_carried_objects_keep_their_sizes():
    moved = margins.with_margin(two_boxes(0.4), 1.5)
    sizes = {o.instance_id: o.size for o in moved.objects}
    assert sizes["1_box_0"] == (8.5, 8.5, 10.0)
    assert sizes["3_tray_0"] == (20.0, 20.0, 2.0) and sizes["4_cup_0"] == (6.0, 6.0, 4.0)
    assert [o.center for o in moved.objects] == [o.center for o in two_boxes(0.4).objects]


def test_the_script_reads_a_records_file(tmp_path, monkeypatch, capsys, engine):
    items = list(plan_split("test", 3, 0))
    path = tmp_path / "rows.jsonl.gz"
    with gzip.open(path, "wt") as f:
        for item, overlap in zip(items, (0.4, 5.0, 0.4)):
            record = {"id": f"test-{item.index:05d}", "layout": layout_to_dict(two_boxes(overlap))}
            f.write(json.dumps(record) + "\n")
    monkeypatch.setattr("physcene.physics.PhysicsEngine", lambda device: engine)
    out = tmp_path / "margins.json"
    argv = ["margins", str(path), "--n", "3", "--margins", "0", "1", "--out", str(out)]
    monkeypatch.setattr("sys.argv", argv)
    margins.main()
    result = json.loads(out.read_text())
    assert result["n"] == 3
    assert result["rows"]["0"]["scr"] == 1.0
    assert result["rows"]["1"]["scr"] == pytest.approx(1 / 3, abs=1e-4)
    assert "margin    1 cm" in capsys.readouterr().out
