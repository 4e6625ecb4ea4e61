"""``physcene bench train8b`` at the tiny size on CPU: each stage runs its steps and writes the figures
the GPU table is filled from (the 8B size itself runs on GPUs: docs/training.md)."""

from __future__ import annotations

import json

import pytest

from physcene.cli import main


@pytest.mark.parametrize("stage", ["sft", "pada", "generate"])
def test_bench_train8b_at_tiny_size_writes_its_figures(stage, tmp_path, capsys):
    out = tmp_path / f"{stage}.json"
    assert main(["bench", "train8b", "--stage", stage, "--size", "tiny", "--steps", "1", "--seq-len", "48",
                 "--completion-len", "4", "--batch", "4", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert (result["stage"], result["size"], result["gpus"]) == (stage, "tiny", 1)
    assert 0 < result["vision_frozen"] < result["params"]
    [gpu] = result["per_gpu"]
    assert gpu["fits"] and len(gpu["figures"]) == 1 and result["median_step_s"] > 0
    parts = {"sft": {"loss"}, "pada": {"generate_s", "reward_s", "update_s"},
             "generate": {"s_per_scene"}}[stage]
    assert parts <= set(gpu["figures"][0])
    if stage == "sft":
        assert gpu["tokens_per_step_per_gpu"] == 4 * 48
    if stage == "pada":
        assert gpu["G"] == 4 and gpu["lora"] == {"r": 16, "alpha": 32}
        # the step is its three parts (plus the batch's tokenisation)
        f = gpu["figures"][0]
        assert f["generate_s"] + f["reward_s"] + f["update_s"] <= f["step_s"]
    assert "train8b" in capsys.readouterr().out
