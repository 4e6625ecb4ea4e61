"""``physcene ctrc``: layout -> completion -> layout, and one-line errors with nothing written."""

import json
import subprocess
import sys

import pytest

from physcene.cli import main
from physcene.ctrc import parse
from physcene.layout import read_layout

EXAMPLE = "examples/office_table.layout.json"


def test_layout_to_completion_and_back(tmp_path, capsys):
    assert main(["ctrc", EXAMPLE]) == 0
    text = capsys.readouterr().out
    assert text.startswith("**Sub-instruction:**\n1. Place 1_laptop_0")
    completion = tmp_path / "completion.txt"
    completion.write_text(text)
    assert main(["ctrc", "--decode", str(completion)]) == 0
    layout = json.loads(capsys.readouterr().out)
    assert {"instance", "position", "size", "rotation", "z_rotation"} <= set(layout["objects"][0])
    path = tmp_path / "decoded.json"
    path.write_text(json.dumps(layout))
    original, decoded = read_layout(EXAMPLE), read_layout(path)
    for o in original.objects:
        d = decoded.get(o.instance_id)
        assert d.center == pytest.approx(o.center, abs=1e-4) and d.size == pytest.approx(o.size, abs=1e-4)
        assert d.yaw == pytest.approx(o.yaw, abs=1e-4)
    assert decoded.get("5_pen_0").parent == "4_pen_holder_0"
    # --output writes the same layout; --zone overrides the completion's zone.
    out = tmp_path / "out" / "layout.json"
    assert main(["ctrc", "--decode", str(completion), "--zone", "0,120,0,60", "-o", str(out)]) == 0
    assert read_layout(out).ids() == decoded.ids()


def test_prompt_and_graph_override(capsys):
    assert main(["ctrc", EXAMPLE, "--prompt"]) == 0
    prompt = capsys.readouterr().out
    assert "office table" in prompt and "desk lamp (1)" in prompt
    # Graph thresholds are key=value overrides: requiring the whole pen inside its holder
    # (in_height_fraction > 1) turns "in" into a table-level object.
    assert main(["ctrc", EXAMPLE]) == 0
    assert "Place 5_pen_0 in 4_pen_holder_0." in capsys.readouterr().out
    assert main(["ctrc", EXAMPLE, "in_height_fraction=1.1"]) == 0
    out = capsys.readouterr().out
    assert "Place 5_pen_0 in" not in out and "Place 7_mug_0 on 6_saucer_0." in out


@pytest.mark.parametrize("content, needle", [
    ('{"objects": [{"instance_id": "cup_0", "parent_id": "root_zone", "relation_type": "near", '
     '"relative_bbox": [0, 1, 0, -1, 0, 1]}], "item_placement_zone": [0, 10, 0, 10]}',
     "object 'cup_0', field 'relative_bbox'"),
    ('{"objects": [{"instance_id": "cup_0", "parent_id": "mug_9", "relation_type": "on", '
     '"relative_bbox": [0, 1, 0, 1, 0, 1]}], "item_placement_zone": [0, 10, 0, 10]}',
     "object 'cup_0', field 'parent_id'"),
    ('**Scene Layout:**\n{"objects": [{"instance_id": "cup_0", ', "truncated"),
    ("", "empty completion"),
])
def test_decode_errors_one_line_nothing_written(tmp_path, capsys, content, needle):
    src = tmp_path / "bad.txt"
    src.write_text(content)
    out = tmp_path / "layout.json"
    assert main(["ctrc", "--decode", str(src), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and not out.exists()
    err = captured.err.strip()
    assert "\n" not in err and str(src) in err and needle in err, err


@pytest.mark.parametrize("mutate, needle", [
    (lambda d: d["objects"][3].update(size=[8, -8, 10]), "object '4_pen_holder_0', field 'size'"),
    (lambda d: d["objects"][0].update(position=[1, 2]), "object '1_laptop_0', field 'position'"),
    (lambda d: d.update(item_placement_zone="big"), "field 'item_placement_zone'"),
])
def test_broken_layout_one_line(tmp_path, capsys, mutate, needle):
    data = json.loads(open(EXAMPLE).read())
    mutate(data)
    src = tmp_path / "layout.json"
    src.write_text(json.dumps(data))
    out = tmp_path / "completion.txt"
    assert main(["ctrc", str(src), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and not out.exists()
    err = captured.err.strip()
    assert "\n" not in err and str(src) in err and needle in err, err


def test_console_exit_status_no_traceback(tmp_path):
    """The real process: exit status 2, one stderr line, no traceback."""
    src = tmp_path / "layout.json"
    src.write_text('{"item_placement_zone": [0, 10, 0, 10], "objects": [{"instance": "cup_0", '
                   '"position": [1, 1, 1], "size": [2, 2, 0]}]}')
    proc = subprocess.run([sys.executable, "-m", "physcene.cli", "ctrc", str(src)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert f"{src}, object 'cup_0', field 'size'" in proc.stderr


def test_invalid_json_layout_and_missing_file(tmp_path, capsys):
    src = tmp_path / "layout.json"
    src.write_text('{"objects": [')
    assert main(["ctrc", str(src)]) == 2
    assert "line 1" in capsys.readouterr().err
    assert main(["ctrc", str(tmp_path / "nope.json")]) == 2
    assert main(["ctrc", "--decode", str(src), "--zone", "0,1,0"]) == 2
    assert "--zone" in capsys.readouterr().err


def test_decode_prompt3_output(tmp_path, capsys):
    src = tmp_path / "zero_shot.txt"
    src.write_text('<json>{"item_placement_zone": [0, 80, 0, 40], "objects": [{"instance": '
                   '"lotion_bottle_0", "z_rotation": 0.0, "size": [5, 5, 15], "position": [10, 10, 7.5], '
                   '"description": "b"}]}<json>')
    assert main(["ctrc", "--decode", str(src)]) == 0
    scene = parse(src.read_text())
    first = json.loads(capsys.readouterr().out)["objects"][0]
    assert first["instance"] == scene.ids()[0] == "lotion_bottle_0"
