"""``--generator model:PATH`` with a tiny checkpoint of the test fixtures (a scratch Qwen3 of 2 layers and
a BPE tokenizer trained on eight synthetic records, saved as ``physcene train`` saves them)."""

from __future__ import annotations

import pytest
import torch

from physcene.cli import main
from physcene.ctrc import completion_text
from physcene.data import synthesize
from physcene.layout import read_layout

ARCH = dict(hidden_size=48, intermediate_size=96, num_hidden_layers=2, num_attention_heads=4,
            num_key_value_heads=2, head_dim=12, max_position_embeddings=4096)
TEXT = "a desk with a laptop, a mug and a pen in the pen holder"


@pytest.fixture(autouse=True)
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny matmuls on two shared cores: threads only contend
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    from physcene.train.models import build_scratch_model
    from physcene.train.tokenizer import build_tokenizer

    records = list(synthesize("train", n=8))
    texts = [r["prompt"] for r in records] + [r["completion"] for r in records]
    tokenizer = build_tokenizer(texts, vocab_size=320)
    path = tmp_path_factory.mktemp("tiny")
    build_scratch_model(ARCH, tokenizer, seed=3).save_pretrained(path)
    tokenizer.save_pretrained(path)
    return path


def test_the_checkpoint_decodes_under_the_constraint_and_its_layouts_are_written(tmp_path, checkpoint,
                                                                                 monkeypatch, capsys):
    """The checkpoint is loaded and decoded for real; an untrained model writes no layout in a few
    tokens, so its decoded text is replaced by the plan's completion (what a trained model writes) to
    follow the layouts through parse, check and the files."""
    import physcene.train.generate as train_generate
    from physcene.generation import generate

    plans = [s.scene for s in generate(TEXT, n=2, render=False)]
    real = train_generate.generate_with
    calls = []

    def decode(model, tokenizer, prompts, **kw):
        calls.append((prompts, kw))
        texts = real(model, tokenizer, prompts, **{**kw, "max_new_tokens": 8})
        assert len(texts) == len(prompts) == 1
        return [completion_text(plans[len(calls) - 1])]

    monkeypatch.setattr(train_generate, "generate_with", decode)
    code = main(["generate", TEXT, "--generator", f"model:{checkpoint}", "--n", "2", "-o", str(tmp_path),
                 "--no-render"])
    assert code == 0 and len(calls) == 2
    prompt, kw = calls[0][0][0], calls[0][1]
    assert kw["constrained"] is True and kw["chat_format"] is False and kw["do_sample"] is True
    assert f"**Instruction**: {TEXT}" in prompt and "**Object List**:" in prompt
    assert "pen holder (1)" in prompt
    assert "model: 100%" in capsys.readouterr().err  # the progress bar
    for k, plan in enumerate(plans):
        scene = read_layout(tmp_path / f"sample_{k}" / "layout.json")
        assert sorted(scene.ids()) == sorted(plan.ids())
        assert (tmp_path / f"sample_{k}" / "reply.txt").read_text() == completion_text(plan)


def test_an_untrained_checkpoint_is_reported_not_raised(tmp_path, checkpoint, capsys):
    code = main(["generate", TEXT, "--generator", f"model:{checkpoint}", "-o", str(tmp_path), "--no-render",
                 "--quiet", "--max-new-tokens", "12"])
    out, err = capsys.readouterr()
    assert code == 1 and "sample 0: ERROR the model:" in out and "did not parse" in out
    assert "Traceback" not in err and (tmp_path / "sample_0" / "reply.txt").is_file()
