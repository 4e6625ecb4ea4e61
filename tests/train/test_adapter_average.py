"""physcene.train.analysis.adapter_average: the mean of several LoRA checkpoints' merged models, written as
a full checkpoint that generation loads with its base's input format."""

from __future__ import annotations

import json

import pytest
import torch
from peft import LoraConfig, get_peft_model

from physcene.artifacts import checkpoint_digest
from physcene.train.analysis import adapter_average
from physcene.train.generate import load_for_generation
from physcene.train.models import RUN_INFO, build_scratch_model, load_model

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


@pytest.fixture
def run(tmp_path, tokenizer, tiny_arch):
    """(base folder, two LoRA checkpoints of one run on it with different random B's)."""
    base = tmp_path / "base"
    build_scratch_model(tiny_arch, tokenizer, seed=1).save_pretrained(base)
    tokenizer.save_pretrained(base)
    (base / RUN_INFO).write_text(json.dumps({"stage": "sft", "steps": 1250, "physics_conditioned": True,
                                             "chat_format": False}))
    ckpts = []
    for k in (1, 2):
        lora = LoraConfig(r=4, lora_alpha=8, target_modules=["q_proj", "v_proj"])
        model = get_peft_model(load_model(base, dtype="float32"), lora)
        torch.manual_seed(k)
        with torch.no_grad():
            for name, param in model.named_parameters():
                if "lora_B" in name:
                    param.normal_(0, 0.2)
        ckpt = tmp_path / "run" / f"checkpoint-{k}"
        model.save_pretrained(ckpt)
        tokenizer.save_pretrained(ckpt)
        ckpts.append(ckpt)
    (tmp_path / "run" / RUN_INFO).write_text(json.dumps({"base_sha256": checkpoint_digest(base)}))
    return base, ckpts


def test_the_average_is_the_mean_of_the_merged_models(run, tmp_path, capsys):
    base, ckpts = run
    out = tmp_path / "average"
    assert adapter_average.main([str(base), *map(str, ckpts), "--out", str(out)]) == 0
    assert "the mean of 2 merged checkpoints" in capsys.readouterr().out
    merged = [load_for_generation(c, device="cpu", dtype="float32", base=base)[0].state_dict() for c in ckpts]
    averaged, _, info = load_for_generation(out, device="cpu", dtype="float32")
    state = averaged.state_dict()
    q = "model.layers.0.self_attn.q_proj.weight"
    torch.testing.assert_close(state[q], (merged[0][q] + merged[1][q]) / 2)
    assert not torch.equal(merged[0][q], merged[1][q])  # the two adapters differ where the mean is read
    k = "model.layers.0.self_attn.k_proj.weight"  # not adapted: the base's
    torch.testing.assert_close(state[k], load_model(base, dtype="float32").state_dict()[k])
    # the base's input format, not its training record
    assert info["physics_conditioned"] is True and info["chat_format"] is False
    assert info["stage"] == "adapter_average" and "steps" not in info
    assert info["averaged"] == [str(c) for c in ckpts]


def test_a_folder_without_an_adapter_is_named(run, tmp_path, capsys):
    base, ckpts = run
    with pytest.raises(SystemExit):
        adapter_average.main([str(base), str(ckpts[0]), str(base), "--out", str(tmp_path / "x")])
    assert "not LoRA checkpoints (no adapter_config.json)" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
