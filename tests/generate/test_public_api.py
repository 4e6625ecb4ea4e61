"""The public API of ``physcene`` (``__all__``), examples/quickstart.py and examples/completions.jsonl."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import physcene
from physcene.cli import main

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "office_table.layout.json"


def test_all_names_the_api_and_keeps_what_it_exported():
    assert {"TABLE", "Scene", "SceneError", "SceneObject", "Zone", "__version__"} <= set(physcene.__all__)
    api = ("load_layout", "save_layout", "check", "repair", "reward", "generate", "render", "export")
    assert set(api) <= set(physcene.__all__)
    assert all(callable(getattr(physcene, name)) for name in api)


def test_import_physcene_stays_light():
    code = "import sys, physcene; print(sorted(m for m in ('torch', 'warp', 'trimesh') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert out.stdout.strip() == "[]"


def test_stage_packages_stay_importable_and_callable():
    """``physcene.reward`` / ``physcene.export`` are the stage packages and the API functions at once."""
    import physcene.export as export_module
    from physcene.reward import PhysicsReward

    assert physcene.reward.PhysicsReward is PhysicsReward
    assert {"glb", "mjcf", "urdf"} <= set(export_module.FORMATS)
    assert physcene.reward(["not a layout"]) == [-100.0]


def test_layout_round_trip_check_and_repair_name_objects_by_id(tmp_path):
    scene = physcene.load_layout(EXAMPLE)
    assert physcene.load_layout(physcene.save_layout(scene, tmp_path / "layout.json")).ids() == scene.ids()
    report = physcene.check(scene)
    ids = set(scene.ids())
    assert report["pairs"] and all({p["a"], p["b"]} <= ids for p in report["pairs"])
    assert set(report["floating"]) <= ids and report["collision_free"] is False
    fixed, repair_report = physcene.repair(scene)
    assert physcene.check(fixed)["collision_free"] and repair_report["max_displacement_cm"] > 0
    image = physcene.render(fixed, tmp_path / "fixed.png", size=(160, 120))
    assert image.shape == (120, 160, 3) and (tmp_path / "fixed.png").is_file()


def test_reward_scores_the_example_completions(capsys):
    assert main(["reward", str(ROOT / "examples" / "completions.jsonl"), "--json"]) == 0
    rewards = json.loads(capsys.readouterr().out)["rewards"]
    assert len(rewards) == 5 and rewards[:2] == [50.0, 50.0] and rewards[-1] == -100.0
    assert all(r < 0 for r in rewards[2:4])


def test_the_quickstart_runs(tmp_path):
    env = {"PYTHONPATH": str(ROOT), "PATH": "", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(ROOT / "examples" / "quickstart.py"), str(tmp_path)],
                         capture_output=True, text=True, cwd=ROOT, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "repaired: []" in out.stdout and "'a': '4_mug_0', 'b': '4_mug_1'" in out.stdout
    assert (tmp_path / "layout.json").is_file() and (tmp_path / "desk.png").is_file()
    assert (tmp_path / "mjcf" / "scene.xml").is_file()
