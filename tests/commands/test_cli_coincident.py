"""Coincident objects through the CLI (``physcene check``, ``reward``, ``repair``) with the real asset
library: never read as clean (docs/physics.md, "Sound penetration")."""

from __future__ import annotations

import json

import pytest

from physcene.cli import main
from physcene.ctrc import completion_text
from physcene.graph import build_hierarchy, footprint_overlap
from physcene.layout import layout_to_dict, load_layout
from physcene.physics import PhysicsEngine
from physcene.scene import Scene, SceneObject, Zone

ZONE = Zone(0.0, 120.0, 0.0, 60.0)
PAIRS = {  # category, size (cm), how many at one pose
    "box": ("box", (10.0, 10.0, 10.0), 2),
    "sphere": ("sphere", (8.0, 8.0, 8.0), 2),
    "cylinder": ("cylinder", (6.0, 6.0, 12.0), 2),
    "slab": ("box", (30.0, 20.0, 1.0), 2),
    "mug": ("mug", (9.0, 12.0, 10.0), 2),
    "six cubes": ("box", (10.0, 10.0, 10.0), 6),
}


def coincident(name: str) -> Scene:
    category, size, n = PAIRS[name]
    return Scene(ZONE, [SceneObject(f"{k + 1}_{category}_{k}", category, (60.0, 30.0, size[2] / 2), size, 0.2)
                        for k in range(n)], scene_type="test")


@pytest.mark.parametrize("name", list(PAIRS))
def test_coincident_objects_collide_in_check_reward_and_are_parted_by_repair(name, tmp_path, capsys):
    scene = coincident(name)
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(layout_to_dict(scene)))
    assert main(["check", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)["scenes"][0]
    n = len(scene.objects)
    assert len(doc["pairs"]) == n * (n - 1) // 2 and min(p["depth_cm"] for p in doc["pairs"]) > 0.2

    records = tmp_path / "completions.jsonl"
    text = completion_text(build_hierarchy(scene))
    records.write_text(json.dumps({"prompt": "", "completion": text}) + "\n")
    assert main(["reward", str(records), "--json"]) == 0
    (reward,) = json.loads(capsys.readouterr().out)["rewards"]
    assert reward < 0  # colliding: −min(0.01·E_pen, 50), never the clean +50

    out = tmp_path / "repaired.json"
    assert main(["repair", str(path), "-o", str(out)]) == 0
    capsys.readouterr()
    after = load_layout(json.loads(out.read_text()))
    score = PhysicsEngine().score([after])
    assert max((d for _, _, d in score.pairs[0]), default=0.0) <= 0.1  # no pair deeper than 1 mm
    for i, a in enumerate(after.objects):
        for b in after.objects[i + 1:]:
            assert footprint_overlap(a, b) <= 0.05, (a.instance_id, b.instance_id)
