"""Training resumes from the newest COMPLETE checkpoint; a run cut short in its final save says so."""

from __future__ import annotations

import json
import logging

import pytest
import torch
from transformers import Qwen3Config, Qwen3ForCausalLM, TrainerCallback
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR, get_last_checkpoint

from physcene.config import load_config
from physcene.ctrc import build_prompt, completion_text
from physcene.data.noisy import noisy_scenes
from physcene.train.checkpoints import checkpoint_problem, complete_checkpoints, last_complete_checkpoint
from physcene.train.models import RUN_INFO, TrainingSetupError, read_run_info
from physcene.train.records import write_records
from physcene.train.sft import run_sft


def _cut(path, keep: float = 0.5) -> None:
    """Truncate ``path`` to ``keep`` of its bytes (a write killed half way)."""
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep)])


@pytest.fixture(scope="module")
def tiny_model():
    config = Qwen3Config(vocab_size=64, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                         num_attention_heads=2, num_key_value_heads=1, head_dim=8)
    return Qwen3ForCausalLM(config)


def _checkpoint(root, step: int, model) -> None:
    """A checkpoint folder as the Trainer writes it: weights, optimizer, scheduler, RNG, state last."""
    folder = root / f"checkpoint-{step}"
    model.save_pretrained(folder)
    torch.save({"state": {}, "param_groups": []}, folder / "optimizer.pt")
    torch.save({"last_epoch": step}, folder / "scheduler.pt")
    torch.save({"python": 0}, folder / "rng_state.pth")
    (folder / "trainer_state.json").write_text(json.dumps({"global_step": step, "log_history": []}))


def test_truncated_newest_checkpoint_is_skipped(tmp_path, tiny_model, caplog):
    for step in (2, 4):
        _checkpoint(tmp_path, step, tiny_model)
    assert last_complete_checkpoint(tmp_path) == str(tmp_path / "checkpoint-4")
    _cut(tmp_path / "checkpoint-4" / "model.safetensors")
    assert get_last_checkpoint(str(tmp_path)) == str(tmp_path / "checkpoint-4")  # what crashed the resume
    with caplog.at_level(logging.WARNING, logger="physcene.train.checkpoints"):
        assert last_complete_checkpoint(tmp_path) == str(tmp_path / "checkpoint-2")
    assert "checkpoint-4" in caplog.text and "model.safetensors" in caplog.text


@pytest.mark.parametrize("damage", ["no_state", "bad_state", "cut_optimizer", "no_weights", "cut_header"])
def test_each_kind_of_incomplete_checkpoint_is_named(tmp_path, tiny_model, damage):
    _checkpoint(tmp_path, 1, tiny_model)
    folder = tmp_path / "checkpoint-1"
    assert checkpoint_problem(folder) is None
    if damage == "no_state":
        (folder / "trainer_state.json").unlink()
    elif damage == "bad_state":
        (folder / "trainer_state.json").write_text('{"global_step": 1, "log_hist')
    elif damage == "cut_optimizer":
        _cut(folder / "optimizer.pt", 0.9)
    elif damage == "no_weights":
        (folder / "model.safetensors").unlink()
    else:
        _cut(folder / "model.safetensors", 0.0001)  # inside the 8-byte length or the JSON header
    problem = checkpoint_problem(folder)
    named = {"no_state": "trainer_state", "bad_state": "trainer_state", "cut_optimizer": "optimizer.pt",
             "no_weights": "weights", "cut_header": "model.safetensors"}[damage]
    assert problem and named in problem
    assert last_complete_checkpoint(tmp_path) is None


def test_no_checkpoint_folder(tmp_path):
    assert last_complete_checkpoint(tmp_path / "missing") is None
    assert last_complete_checkpoint(tmp_path) is None
    assert complete_checkpoints(tmp_path / "missing") == complete_checkpoints(tmp_path) == []


def test_complete_checkpoints_in_step_order_without_incomplete_ones(tmp_path, tiny_model):
    """Every complete ``checkpoint-N`` oldest first, by step (10 after 4, not as text); one being
    written (no trainer_state.json yet) and one with a cut safetensors are left out."""
    assert PREFIX_CHECKPOINT_DIR == "checkpoint"  # the folder names checkpoints.py spells out
    for step in (4, 10, 12, 16):
        _checkpoint(tmp_path, step, tiny_model)
    (tmp_path / "checkpoint-12" / "trainer_state.json").unlink()
    _cut(tmp_path / "checkpoint-16" / "model.safetensors", 0.9)
    (tmp_path / "checkpoint-x").mkdir()
    (tmp_path / "checkpoint-7.json").write_text("{}")
    assert complete_checkpoints(tmp_path) == [tmp_path / "checkpoint-4", tmp_path / "checkpoint-10"]
    assert last_complete_checkpoint(tmp_path) == str(tmp_path / "checkpoint-10")


class _FirstStep(TrainerCallback):
    def __init__(self):
        self.begin = None

    def on_train_begin(self, args, state, control, **kwargs):
        self.begin = state.global_step


def test_sft_resumes_past_a_truncated_checkpoint(tmp_path, caplog):
    old = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny matmuls on shared cores: threads only contend
    try:
        scenes = noisy_scenes(8, n_objects=2, seed=0, noise_cm=3.0)
        write_records([{"id": f"s{k}", "scene_type": "office", "level": 1, "instruction": "Tidy the desk.",
                        "prompt": build_prompt("Tidy the desk.", "office", s.zone, s.objects),
                        "completion": completion_text(s)} for k, s in enumerate(scenes)],
                      tmp_path / "train.jsonl")
        cfg = load_config("train_tiny", [f"data.train={tmp_path / 'train.jsonl'}",
                                         f"output_dir={tmp_path / 'run'}", "sft.max_steps=4",
                                         "sft.save_steps=2", "sft.max_length=1024"])
        out = run_sft(cfg)
        assert sorted(p.name for p in out.glob("checkpoint-*")) == ["checkpoint-2", "checkpoint-4"]
        # Killed while writing checkpoint-4 and before the final save: half a checkpoint, half a model.
        _cut(out / "checkpoint-4" / "model.safetensors")
        _cut(out / "model.safetensors")
        (out / RUN_INFO).unlink()
        with pytest.raises(TrainingSetupError, match="has not finished"):
            read_run_info(out)  # what a later stage (anchors, PADA, eval) reads first
        first = _FirstStep()
        with caplog.at_level(logging.WARNING, logger="physcene.train.checkpoints"):
            run_sft(cfg, callbacks=[first])
        assert first.begin == 2  # resumed from checkpoint-2, not the cut checkpoint-4
        assert "skipping incomplete checkpoint" in caplog.text and "checkpoint-4" in caplog.text
        assert read_run_info(out)["steps"] == 4
        assert checkpoint_problem(out / "checkpoint-4") is None  # written again, whole
    finally:
        torch.set_num_threads(old)
