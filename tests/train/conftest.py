"""Fixtures of the training tests: one torch thread, the tiny Qwen3 architecture of the generation
tests, 8 synthesised records and a tokenizer trained on them, a tiny random Qwen3-VL saved as a local
checkpoint."""

from __future__ import annotations

import pytest
import torch

from physcene.data import synthesize
from physcene.train.tokenizer import build_tokenizer


@pytest.fixture
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)  # two busy shared cores
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session")
def tiny_arch() -> dict:
    """The tiny from-scratch Qwen3 of the generation tests: hidden 48, 2 layers, 4 heads / 2 KV heads,
    head 12, MLP 96 (``build_scratch_model`` copies it; a test that changes a size passes
    ``{**tiny_arch, ...}``)."""
    return dict(hidden_size=48, intermediate_size=96, num_hidden_layers=2, num_attention_heads=4,
                num_key_value_heads=2, head_dim=12, max_position_embeddings=2048)


@pytest.fixture(scope="module")
def records():
    return list(synthesize("train", n=8))


@pytest.fixture(scope="module")
def tokenizer(records):
    texts = [r["prompt"] for r in records] + [r["completion"] for r in records]
    return build_tokenizer(texts, vocab_size=320)


@pytest.fixture(scope="session")
def qwen3_vl_checkpoint(tmp_path_factory):
    """A local Qwen3-VL checkpoint folder (``Qwen3VLForConditionalGeneration`` from ``Qwen3VLConfig``:
    hidden 64, 2 layers, 4 heads, 2 KV heads, head_dim 16, a 2-block vision tower with deepstack taps),
    a ChatML tokenizer trained on synthesised CTRC records and the processor files."""
    from physcene.train.qwen3_vl import tiny_qwen3_vl_checkpoint

    texts = [t for r in synthesize("train", 8, seed=0) for t in (r["prompt"], r["completion"])]
    return tiny_qwen3_vl_checkpoint(tmp_path_factory.mktemp("qwen3_vl") / "base", texts)
