"""Fixtures of the training tests: a tiny random Qwen3-VL saved as a local checkpoint."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def qwen3_vl_checkpoint(tmp_path_factory):
    """A local Qwen3-VL checkpoint folder (``Qwen3VLForConditionalGeneration`` from ``Qwen3VLConfig``:
    hidden 64, 2 layers, 4 heads, 2 KV heads, head_dim 16, a 2-block vision tower with deepstack taps),
    a ChatML tokenizer trained on synthesised CTRC records and the processor files."""
    from physcene.data import synthesize
    from physcene.train.qwen3_vl import tiny_qwen3_vl_checkpoint

    texts = [t for r in synthesize("train", 8, seed=0) for t in (r["prompt"], r["completion"])]
    return tiny_qwen3_vl_checkpoint(tmp_path_factory.mktemp("qwen3_vl") / "base", texts)
