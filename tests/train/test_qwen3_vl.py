"""The paper's backbone class at tiny size on CPU: a random Qwen3-VL checkpoint (``conftest.py``) through
``physcene train sft`` (full fine-tune, vision tower frozen), ``train anchors``, ``train pada`` (LoRA
r 16 / α 32 on the language model's q, k, v, o, gate, up, down), ``eval`` and ``generate`` with
``--generator model:PATH``, all by the CLI with ``--config qwen3_vl_8b model.path=<checkpoint>``."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from physcene.cli import main

# The qwen3_vl_8b config made tiny: 4 records, 2 SFT steps, 1 PADA step of 2 prompts x G = 4,
# short lengths; fp32 on the CPU.
TINY = ["data.train=synth:train:4", "model.dtype=float32", "sft.max_steps=2", "sft.global_batch_size=2",
        "sft.per_device_batch_size=2", "sft.max_length=640", "sft.save_steps=100", "sft.logging_steps=1",
        "sft.gradient_checkpointing=false", "anchors.max_new_tokens=8", "anchors.batch_size=4",
        "anchors.tto=[steps=5]", "pada.max_steps=1", "pada.global_batch_size=8",
        "pada.per_device_batch_size=8", "pada.max_completion_length=8", "pada.save_steps=100",
        "pada.gradient_checkpointing=false", "pada.variant=pada_star", "eval.max_new_tokens=8"]


def _vision(path) -> dict:
    return {k: v for k, v in load_file(str(path / "model.safetensors")).items() if ".visual." in f".{k}"}


@pytest.fixture(scope="module")
def qwen3_vl_run(qwen3_vl_checkpoint, tmp_path_factory):
    """SFT then PADA* on the tiny Qwen3-VL (PADA* trains on the raw SFT output, which a 2-step model
    cannot make parse: the anchors file is written with the reference completions as anchors)."""
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("qwen3_vl_run")
    args = ["--config", "qwen3_vl_8b", f"model.path={qwen3_vl_checkpoint}", f"output_dir={out}", *TINY]
    assert main(["train", "sft", *args]) == 0
    assert main(["train", "anchors", *args]) == 0
    return out, args
