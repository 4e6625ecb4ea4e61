"""``physcene check``, ``physcene reward`` and ``physcene bench reward`` end to end."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from physcene.cli import main
from physcene.ctrc import completion_text
from physcene.layout import layout_to_dict
from physcene.scene import Scene, SceneObject, Zone

ZONE = Zone(0.0, 120.0, 0.0, 60.0)


def layout(*objects) -> dict:
    return layout_to_dict(Scene(ZONE, objects, scene_type="test"))


def box(name, center, size, yaw=0.0):
    return SceneObject(name, "box", center, size, yaw)


# two boxes overlapping by 2 cm along x, a third hovering 3 cm above the table
COLLIDING = layout(box("1_box_0", (30, 30, 5), (10, 10, 10)), box("2_box_1", (38, 30, 5), (10, 10, 10)),
                   box("3_box_2", (80, 30, 4.5), (6, 6, 3)))
CLEAN = layout(box("1_box_0", (30, 30, 5), (10, 10, 10)), box("2_box_1", (60, 30, 5), (10, 10, 10)))


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    for name, data in (("a", COLLIDING), ("b", CLEAN)):
        (tmp_path / "tree" / name).mkdir(parents=True)
        (tmp_path / "tree" / name / "layout.json").write_text(json.dumps(data))
    return tmp_path / "tree"


def run_json(capsys, argv) -> tuple[int, dict]:
    code = main(argv)
    return code, json.loads(capsys.readouterr().out)


def test_check_a_tree_as_json(capsys, tree):
    code, doc = run_json(capsys, ["check", str(tree), "--json"])
    assert code == 0
    a, b = doc["scenes"]
    assert a["path"].endswith("a/layout.json") and b["path"].endswith("b/layout.json")
    assert set(a) == {"path", "objects", "pairs", "max_depth_cm", "energy", "floating",
                      "table_penetration_cm", "error"}
    assert a["objects"] == 3 and a["error"] is None
    assert [(p["a"], p["b"]) for p in a["pairs"]] == [("1_box_0", "2_box_1")]
    assert a["pairs"][0]["depth_cm"] == pytest.approx(2.0, abs=0.05)
    assert a["max_depth_cm"] == pytest.approx(2.0, abs=0.05) and a["energy"] > 0
    assert a["floating"] == ["3_box_2"] and a["table_penetration_cm"] == 0.0
    assert b["pairs"] == [] and b["energy"] == 0.0 and b["floating"] == []


def test_check_jsonl_and_unreadable_inputs(capsys, tmp_path, tree):
    data = tmp_path / "data.jsonl"
    data.write_text(json.dumps({"id": 1, "layout": COLLIDING}) + "\n" + json.dumps({"id": 2}) + "\n")
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    code, doc = run_json(capsys, ["check", str(data), str(broken), str(tmp_path / "missing.json"), "--json"])
    assert code == 2  # unreadable input, named
    paths = [s["path"] for s in doc["scenes"]]
    assert paths == [f"{data}:1", f"{data}:2", str(broken), str(tmp_path / "missing.json")]
    errors = [s["error"] for s in doc["scenes"]]
    assert errors[0] is None and all(e and p in e for e, p in zip(errors[1:], paths[1:]))
    assert doc["scenes"][0]["pairs"][0]["a"] == "1_box_0"


def test_check_text_output_exits_zero_with_collisions(capsys, tree):
    assert main(["check", str(tree / "a" / "layout.json")]) == 0
    out = capsys.readouterr().out
    assert "1_box_0~2_box_1" in out and "floating: 3_box_2" in out


def test_reward_command(capsys, tmp_path):
    path = tmp_path / "c.jsonl"
    colliding = completion_text(Scene(ZONE, [box("1_box_0", (30, 30, 5), (10, 10, 10)),
                                             box("2_box_1", (38, 30, 5), (10, 10, 10))]))
    clean = completion_text(Scene(ZONE, [box("1_box_0", (30, 30, 5), (10, 10, 10))]))
    rows = [{"prompt": "p", "completion": clean}, {"prompt": "p", "completion": "nonsense"},
            {"prompt": "p", "completion": [{"role": "assistant", "content": colliding}]}]
    path.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    code, doc = run_json(capsys, ["reward", str(path), "--json"])
    assert code == 0
    assert doc["rewards"][:2] == [50.0, -100.0] and doc["rewards"][2] == pytest.approx(-0.2, abs=2e-3)
    path.write_text('{"prompt": "p"}\n')
    assert main(["reward", str(path)]) == 2
    assert f"{path}:1" in capsys.readouterr().err


def test_bench_reward_small(capsys):
    code, doc = run_json(capsys, ["bench", "reward", "--scenes", "8", "--objects", "5", "--points", "128",
                                  "--resolution", "16", "--repeat", "1", "--json"])
    assert code == 0
    for key in ("warp_forward", "warp_grad", "reference_forward", "reference_grad", "reward_from_text"):
        assert doc[key]["seconds"] > 0 and doc[key]["scenes_per_s"] > 0
    assert doc["queries_evaluated"] <= doc["queries_all_pairs"] and doc["speedup_forward"] > 0


def test_check_takes_physics_overrides_after_the_paths(capsys, tree):
    path = str(tree / "a" / "layout.json")
    code, doc = run_json(capsys, ["check", path, "--json", "graph=false", "floating_tolerance_cm=5"])
    assert code == 0 and doc["scenes"][0]["floating"] == []  # 3 cm above the table: within 5 cm
    assert doc["scenes"][0]["pairs"][0]["depth_cm"] == pytest.approx(2.0, abs=0.05)
    assert main(["check", path, "narrowphase_block_dim=2048"]) == 2
    assert "narrowphase_block_dim=2048" in capsys.readouterr().err
