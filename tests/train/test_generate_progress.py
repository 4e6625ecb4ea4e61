"""The decode bar of :func:`physcene.train.generate.generate`: it counts every prompt as its batch is
decoded (HF ``generate`` and the fast decoder), stays off unless asked, and ``physcene eval`` asks for
it with a ``model:`` generator unless ``--quiet``."""

from __future__ import annotations

import pytest
from tqdm.std import tqdm as std_tqdm
from transformers.utils import logging as transformers_logging

import physcene.train.generate as train_generate
from physcene.train.models import build_scratch_model

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


class _Bar(std_tqdm):
    """tqdm that keeps what it was told: every bar made, the steps it advanced by, whether it closed."""

    made: list[_Bar] = []

    def __init__(self, *args, **kwargs):
        self.steps, self.closed = [], False
        super().__init__(*args, **kwargs)
        _Bar.made.append(self)

    def update(self, n=1):
        self.steps.append(n)
        return super().update(n)

    def close(self):
        self.closed = True
        super().close()


@pytest.fixture
def bars(monkeypatch):
    monkeypatch.setattr(_Bar, "made", [])
    monkeypatch.setattr(train_generate, "tqdm", _Bar)
    return _Bar.made


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, tokenizer, tiny_arch):
    """The tiny scratch model of the generation tests, saved as a plain checkpoint folder."""
    folder = tmp_path_factory.mktemp("progress") / "ckpt"
    build_scratch_model(tiny_arch, tokenizer, seed=3).save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    return folder


def _prompts(records) -> list[str]:
    return [r["prompt"][:200 + 40 * k] for k, r in enumerate(records[:5])]


@pytest.mark.parametrize("cache", ["dynamic", "fast"])
def test_the_bar_counts_every_prompt_over_its_batches(checkpoint, records, bars, capsys, cache):
    prompts = _prompts(records)
    out = train_generate.generate(checkpoint, prompts, max_new_tokens=3, batch_size=2, device="cpu",
                                  cache=cache, progress=True)
    assert len(out) == 5
    (bar,) = bars
    assert bar.total == 5 and bar.n == 5 and bar.steps == [2, 2, 1] and bar.closed
    err = capsys.readouterr().err
    assert "decode" in err and "5/5" in err


@pytest.mark.parametrize("cache", ["dynamic", "fast"])
def test_no_bar_unless_asked(checkpoint, records, bars, capsys, cache):
    prompts = _prompts(records)
    with_bar = train_generate.generate(checkpoint, prompts, max_new_tokens=3, batch_size=2, device="cpu",
                                       cache=cache, progress=True)
    capsys.readouterr()
    assert train_generate.generate(checkpoint, prompts, max_new_tokens=3, batch_size=2, device="cpu",
                                   cache=cache) == with_bar  # off by default: the ablation's call
    assert capsys.readouterr().err == ""  # transformers' "Loading weights" bar included
    assert bars[-1].disable and bars[-1].n == 0
    assert transformers_logging.is_progress_bar_enabled()  # its switch set back


def test_physcene_eval_asks_for_the_bar_unless_quiet(monkeypatch, tmp_path):
    import physcene.commands.eval as eval_command
    from physcene.cli import main
    from physcene.eval.harness import load_benchmark

    items = load_benchmark("test", n=2, progress=False)
    seen = []

    def fake_generate(path, prompts, **kw):
        seen.append(kw["progress"])
        return ["not a layout"] * len(prompts)

    def fake_evaluation(cfg, *, generators, **kw):  # the harness's call of the model generator only
        for run_model in generators.values():
            run_model(items)
        return {}, tmp_path / "report.md"

    monkeypatch.setattr(train_generate, "generate", fake_generate)
    monkeypatch.setattr(eval_command, "run_evaluation", fake_evaluation)
    base = ["eval", "--generator", "model:runs/x", "--out", str(tmp_path), "--json"]
    assert main(base) == 0
    assert main([*base, "--quiet"]) == 0
    assert seen == [True, False]
