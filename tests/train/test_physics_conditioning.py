"""Physics-conditioned SFT (``model.physics_conditioned``): the records' measured physics
(``physcene data measure``) ends each SFT prompt, every generation path asks for a collision-free
layout, and the constraint reads the conditioned prompt's object list as before."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from physcene.config import load_config
from physcene.ctrc import with_physics
from physcene.ctrc.prompts import PHYSICS_LABEL
from physcene.train.constrained.grammar import listed_instance_ids
from physcene.train.generate import generate, generate_with, input_format, load_for_generation, render_prompt
from physcene.train.models import read_run_info
from physcene.train.records import model_prompt, training_dataset

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


def _measured(records, free=(True, False)):
    return [{**r, "reference_physics": {"collision_free": free[k % len(free)], "deepest_cm": 0.0}}
            for k, r in enumerate(records)]


def test_sft_prompts_state_the_layouts_physics_and_generation_asks_for_collision_free(records):
    measured = _measured(records[:2])
    assert model_prompt(measured[0], None) == records[0]["prompt"]
    assert model_prompt(measured[0], "reference").endswith(f"\n{PHYSICS_LABEL}collision-free")
    assert model_prompt(measured[1], "reference").endswith(f"\n{PHYSICS_LABEL}colliding")
    assert model_prompt(measured[1], "requested") == with_physics(records[1]["prompt"])
    rows = training_dataset(measured, chat_format=False, physics="reference")
    assert rows[1]["prompt"] == model_prompt(measured[1], "reference")
    assert rows[1]["completion"] == records[1]["completion"]
    missing = r"record 'train-00000' has no reference_physics.*physcene data measure"
    with pytest.raises(ValueError, match=missing):
        training_dataset(records[:1], chat_format=False, physics="reference")
    with pytest.raises(ValueError, match="physics 'clean'"):
        model_prompt(measured[0], "clean")
    assert training_dataset(records[:1], chat_format=False, physics="requested")[0]["prompt"] == \
        with_physics(records[0]["prompt"])  # generation and RL need no measured records


def test_the_constraint_reads_a_conditioned_prompts_object_list(records):
    for r in records:
        assert listed_instance_ids(with_physics(r["prompt"])) == listed_instance_ids(r["prompt"])
        assert listed_instance_ids(with_physics(r["prompt"], False)) == listed_instance_ids(r["prompt"])


def test_a_conditioned_sft_checkpoint_asks_for_collision_free_layouts_when_it_generates(records, tmp_path):
    from physcene.train.sft import run_sft

    data = tmp_path / "train.jsonl"
    data.write_text("".join(json.dumps(r) + "\n" for r in _measured(records)))
    overrides = [f"data.train={data}", f"output_dir={tmp_path / 'run'}", "sft.global_batch_size=2",
                 "sft.per_device_batch_size=2", "sft.max_steps=1", "sft.max_length=8192"]
    out = run_sft(load_config("train_tiny", [*overrides, "model.physics_conditioned=true"]))
    info = read_run_info(out)
    assert info["physics_conditioned"] is True
    assert input_format(info) == {"chat_format": False, "physics": True}
    model, tokenizer, _ = load_for_generation(out, device="cpu")
    assert render_prompt(tokenizer, "P", False, True) == with_physics("P")
    prompts = [r["prompt"] for r in records[:2]]
    got = generate(out, prompts, max_new_tokens=6, batch_size=2, device="cpu", constrained=True)
    asked = generate_with(model, tokenizer, [with_physics(p) for p in prompts], max_new_tokens=6,
                          batch_size=2, constrained=True)
    assert got == asked
    from physcene.generation.model import model_completions  # the `model:` generator, one at a time

    one = [with_physics(prompts[0])]
    assert model_completions(out, prompts[:1], max_new_tokens=6, device="cpu", progress=False) == \
        generate_with(model, tokenizer, one, max_new_tokens=6, batch_size=1, constrained=True)
    plain = run_sft(load_config("train_tiny", [*overrides, f"output_dir={tmp_path / 'plain'}"]))
    assert read_run_info(plain)["physics_conditioned"] is False


def test_physcene_data_measure_writes_each_records_measured_physics(tmp_path, capsys):
    """The field agrees with the split's own measure (per-scene penetrating pairs) on a synthesised split."""
    from physcene.data.benchmark import synthesize
    from physcene.eval.metrics import measure_reference
    from physcene.layout import load_layout
    from physcene.physics import PhysicsEngine

    records = list(synthesize("test", n=6))
    src = tmp_path / "test.jsonl"
    src.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "measured.jsonl.gz"
    cli = [sys.executable, "-m", "physcene.cli", "data", "measure"]
    done = subprocess.run([*cli, str(src), "--out", str(out), "--device", "cpu", "--quiet"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    from physcene.train.records import load_records

    measured = load_records(str(out))
    assert [r["id"] for r in measured] == [r["id"] for r in records]
    pairs = measure_reference([load_layout(r["layout"]) for r in records], PhysicsEngine(device="cpu"))
    assert [r["reference_physics"]["collision_free"] for r in measured] == \
        [n == 0 for n in pairs["per_scene_pairs"]]
    assert all((r["reference_physics"]["deepest_cm"] > 0) != r["reference_physics"]["collision_free"]
               for r in measured)
    assert f"{sum(n == 0 for n in pairs['per_scene_pairs'])} collision-free" in done.stdout
    # bad input: one error line and exit status 2 (in this process: the command's checks come first)
    from physcene.cli import main

    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps({"id": "x", "prompt": "p"}) + "\n")
    assert main(["data", "measure", str(bad), "--out", str(tmp_path / "o.jsonl")]) == 2
    assert f"{bad}:1: a record needs a 'layout'" in capsys.readouterr().err
    assert main(["data", "measure", str(src), "--out", str(src)]) == 2
    assert "is the records file itself" in capsys.readouterr().err
