"""KV-cache modes of batched generation (issue 8): dynamic == static greedy ids, the cache knob reaches
``model.generate`` from generate_with, anchors, eval and PADA, and ``physcene bench generate`` runs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from datasets import Dataset

from physcene.config import load_config
from physcene.train.generate import (
    CACHE_MODES,
    cache_generate_kwargs,
    generate_token_ids,
    generate_with,
)
from physcene.train.models import TrainingSetupError, build_scratch_model, count_parameters
from physcene.train.tokenizer import build_tokenizer

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


@pytest.fixture(scope="module")
def model(tokenizer, tiny_arch):
    return build_scratch_model(tiny_arch, tokenizer, seed=3).eval()


def _prompts(records, tokenizer) -> list[str]:
    """Three CTRC prompts of different token lengths (one shortened) -> real left padding."""
    prompts = [records[0]["prompt"], records[1]["prompt"][:300], records[2]["prompt"]]
    lengths = {len(tokenizer(p, add_special_tokens=False)["input_ids"]) for p in prompts}
    assert len(lengths) == 3
    return prompts


@pytest.mark.parametrize("min_new", [None, 12])
def test_static_cache_gives_the_dynamic_cache_greedy_ids(model, tokenizer, records, min_new):
    prompts = _prompts(records, tokenizer)
    # batch_size 2 over 3 prompts: a padded batch of 2, then a batch of 1 reusing the static cache size
    out = {cache: generate_token_ids(model, tokenizer, prompts, max_new_tokens=12, batch_size=2,
                                     cache=cache, min_new_tokens=min_new)
           for cache in ("dynamic", "static")}
    assert out["static"] == out["dynamic"]
    assert all(len(row) == 12 for row in out["dynamic"])
    # the same ids one prompt at a time (no padding): left padding does not change greedy output
    single = [generate_token_ids(model, tokenizer, [p], max_new_tokens=12, cache="dynamic",
                                 min_new_tokens=min_new)[0] for p in prompts]
    assert single == out["dynamic"]
    if min_new is not None:
        assert all(tokenizer.eos_token_id not in row for row in out["dynamic"])
    else:  # generate_with is the decode of the same ids
        texts = generate_with(model, tokenizer, prompts, max_new_tokens=12, batch_size=2, cache="static")
        assert texts == [tokenizer.decode(r, skip_special_tokens=True) for r in out["dynamic"]]


@pytest.mark.cuda  # static_compile: torch.compile takes ~10-20 s per graph on 2 CPU cores; checked on CUDA
def test_static_compile_gives_the_dynamic_ids_on_cuda(tokenizer, records, tiny_arch):
    model = build_scratch_model(tiny_arch, tokenizer, seed=3).cuda().eval()
    prompts = _prompts(records, tokenizer)
    out = {cache: generate_token_ids(model, tokenizer, prompts, max_new_tokens=16, batch_size=2, cache=cache,
                                     min_new_tokens=16) for cache in CACHE_MODES}
    assert out["static"] == out["dynamic"] and out["static_compile"] == out["dynamic"]


def test_cache_kwargs_and_bad_names():
    assert cache_generate_kwargs("dynamic") == {"cache_implementation": "dynamic"}
    static = cache_generate_kwargs("static", max_cache_len=100)
    assert static == {"cache_implementation": "static", "max_cache_len": 100, "disable_compile": True}
    compiled = cache_generate_kwargs("static_compile", "cpu")
    assert compiled["cache_implementation"] == "static" and compiled["disable_compile"] is False
    assert compiled["compile_config"]._compile_all_devices  # an explicit request is honoured on CPU
    with pytest.raises(TrainingSetupError, match="'paged'"):
        cache_generate_kwargs("paged")


class _Recorder:
    """Stands in for ``model.generate``: records its keyword arguments, returns prompt + 3 pad ids."""

    def __init__(self, model, pad: int):
        self.calls, self.model, self.pad = [], model, pad

    def __call__(self, input_ids, attention_mask, **kwargs):
        self.calls.append(kwargs)
        return torch.cat([input_ids, torch.full((input_ids.shape[0], 3), self.pad)], 1)


def test_the_cache_knob_reaches_model_generate(model, tokenizer, records, monkeypatch):
    prompts = _prompts(records, tokenizer)
    rec = _Recorder(model, tokenizer.pad_token_id)
    monkeypatch.setattr(model, "generate", rec)
    generate_with(model, tokenizer, prompts, max_new_tokens=7, batch_size=2, cache="static")
    longest = max(len(tokenizer(p, add_special_tokens=False)["input_ids"]) for p in prompts)
    assert len(rec.calls) == 2
    for kw in rec.calls:  # one cache size for every batch: no reallocation, no recompilation
        assert kw["cache_implementation"] == "static" and kw["disable_compile"] is True
        assert kw["max_cache_len"] == longest + 7 and kw["max_new_tokens"] == 7
    with pytest.raises(TrainingSetupError, match="generation cache 'turbo'"):  # 'fast' is a mode now
        generate_with(model, tokenizer, prompts, cache="turbo")


def test_anchors_cache_reaches_generate_with(tmp_path, monkeypatch, model, tokenizer):
    import physcene.train.anchors as anchors
    from physcene.train.anchors import run_anchors

    seen = []

    def fake_generate_token_ids(model, tokenizer, prompts, **kw):
        seen.append(kw)
        return [tokenizer("not a layout", add_special_tokens=False)["input_ids"] + [tokenizer.eos_token_id]
                for _ in prompts]

    monkeypatch.setattr(anchors, "load_for_generation", lambda path, **kw: (model, tokenizer, {}))
    monkeypatch.setattr(anchors, "generate_token_ids", fake_generate_token_ids)
    cfg = load_config("train_tiny", [f"output_dir={tmp_path}", "anchors.n_records=2",
                                     "anchors.cache=static_compile", "anchors.constrained=true",
                                     "data.train=synth:train:2"])
    rows = [json.loads(line) for line in Path(run_anchors(cfg)).read_text().splitlines()]
    assert seen and seen[0]["cache"] == "static_compile" and seen[0]["constrained"] is True
    assert [r["sft_completion"] for r in rows] == ["not a layout"] * 2
    assert [r["sft_truncated"] for r in rows] == [False, False]


def test_eval_cache_reaches_the_model_generator(monkeypatch):
    import physcene.train.generate as train_generate
    from physcene.commands.eval import model_generators
    from physcene.eval.harness import generate, load_benchmark

    items = load_benchmark("test", n=1, progress=False)
    seen = {}

    def fake_generate(path, prompts, **kw):
        seen.update(kw)
        return ["not a layout"] * len(prompts)

    monkeypatch.setattr(train_generate, "generate", fake_generate)
    cfg = load_config("eval", ["generator=model:runs/x", "cache=static", "constrained=true"])
    generate(items, "model:runs/x", progress=False, generators=model_generators(cfg))
    assert seen["cache"] == "static" and seen["constrained"] is True
    assert seen["follow_plan"] is True and seen["do_sample"] is False  # eval.yaml: greedy, the plan followed
    cfg = load_config("eval", ["generator=model:runs/x", "follow_plan=false", "temperature=0.7", "seed=3"])
    generate(items, "model:runs/x", progress=False, generators=model_generators(cfg))
    assert seen["follow_plan"] is False and seen["do_sample"] is True
    assert seen["temperature"] == 0.7 and seen["seed"] == 3
    assert load_config("eval").cache == "dynamic" and load_config("eval").constrained is False
    for name in ("tiny", "qwen3_vl_8b"):
        cfg = load_config(f"train_{name}")
        assert cfg.eval.cache == cfg.anchors.cache == cfg.pada.cache == "dynamic"
    small = load_config("train_small")  # the fast decoder (physcene.train.decode) for all three
    assert small.eval.cache == small.anchors.cache == "fast"  # greedy: HF's ids
    assert small.pada.cache == "fast+fused+cudnn"  # sampled groups: the fastest setting


def test_pada_cache_reaches_trl_generation_config(tmp_path, tokenizer, tiny_arch):
    from physcene.train.pada import PADAConfig, PADATrainer, pada_arguments

    cfg = load_config("train_tiny", [f"output_dir={tmp_path}"])
    assert pada_arguments(cfg, "pada").cache_implementation is None
    for cache, compiled in (("static", False), ("static_compile", True)):
        overrides = [f"output_dir={tmp_path}", f"pada.cache={cache}"]
        args = pada_arguments(load_config("train_tiny", overrides), "pada")
        assert args.cache_implementation == "static" and args.generation_compile is compiled
    with pytest.raises(TrainingSetupError, match="'bogus'"):
        pada_arguments(load_config("train_tiny", ["pada.cache=bogus"]), "pada")
    model = build_scratch_model(tiny_arch, tokenizer)
    args = PADAConfig(output_dir=str(tmp_path), num_generations=2, per_device_train_batch_size=2,
                      max_completion_length=8, use_cpu=True, report_to="none", beta=0.0,
                      cache_implementation="static", generation_compile=True)
    trainer = PADATrainer(model, reward_funcs=[lambda prompts, completions, **kw: [0.0] * len(prompts)],
                          args=args, processing_class=tokenizer, train_dataset=Dataset.from_list(
                              [{"prompt": p, "anchor": ""} for p in ("a pen", "a pen and a long ruler")]))
    g = trainer.generation_config
    assert g.cache_implementation == "static" and g.disable_compile is False and g.compile_config is not None
    # one cache size for the run (no recompile as longer batches come): longest prompt + completion
    longest = len(tokenizer("a pen and a long ruler", add_special_tokens=False)["input_ids"])
    assert g.max_cache_len == longest + 8


def test_bench_generate_runs_at_tiny_sizes(capsys, tmp_path):
    from physcene.cli import main

    out = tmp_path / "generate.json"
    assert main(["bench", "generate", "--config", "tiny", "--batch", "2", "--tokens", "8", "--repeat", "1",
                 "--variants", "dynamic", "static", "--json", "--out", str(out)]) == 0
    r = json.loads(capsys.readouterr().out)
    assert json.loads(out.read_text()) == r  # the file after the last variant = the printed figures
    assert r["target"] == "generate" and r["batch"] == 2 and r["tokens"] == 8 and r["reference"] == "dynamic"
    for name in ("dynamic", "static"):
        v = r["variants"][name]
        assert v["equal"] and v["equal_rows"] == 1.0 and v["first_diff_step"] is None
        assert v["ms_per_step"] > 0 and v["tokens_per_s"] == pytest.approx(16 / v["seconds"])
    assert main(["bench", "generate", "--config", "tiny", "--batch", "0"]) == 2
    assert "--batch 0" in capsys.readouterr().err


def test_bench_generate_decodes_through_lora_adapters_merged_or_not(capsys):
    """``--lora R``: the rows decode through random adapters, a ``@merged`` variant with them merged
    (every adapted projection), and in float32 both write the unmerged HF reference's ids."""
    from physcene.cli import main

    assert main(["bench", "generate", "--config", "tiny", "--batch", "2", "--tokens", "8", "--repeat", "1",
                 "--lora", "4", "--variants", "static", "fast", "fast@merged", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["variants"]["fast"]["merged_projections"] == 0
    assert r["variants"]["fast@merged"]["merged_projections"] == 7 * 2  # 7 projections x 2 layers
    assert all(v["equal"] for v in r["variants"].values())
    assert main(["bench", "generate", "--config", "tiny", "--variants", "static@merged"]) == 2
    assert "@merged" in capsys.readouterr().err


def test_bench_generate_times_a_trained_checkpoint(capsys, tmp_path, tiny_arch):
    """``--model``: the checkpoint's own weights and tokenizer (not random ones of --config); the fast
    decoder's greedy ids equal HF's on it; a missing folder is one error naming it."""
    from physcene.cli import main
    from physcene.data import synthesize

    records = list(synthesize("train", n=8, seed=4))
    tokenizer = build_tokenizer([t for r in records for t in (r["prompt"], r["completion"])], vocab_size=400)
    build_scratch_model(tiny_arch, tokenizer, seed=5).save_pretrained(tmp_path / "ckpt")
    tokenizer.save_pretrained(tmp_path / "ckpt")
    assert main(["bench", "generate", "--model", str(tmp_path / "ckpt"), "--batch", "2", "--tokens", "6",
                 "--repeat", "1", "--variants", "static", "fast", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["model"] == str(tmp_path / "ckpt") and r["parameters"] == count_parameters(
        build_scratch_model(tiny_arch, tokenizer, seed=5))
    assert r["variants"]["fast"]["equal"] and r["variants"]["fast"]["path"] == "eager"
    missing = str(tmp_path / "nowhere")
    assert main(["bench", "generate", "--model", missing, "--batch", "2", "--tokens", "2"]) != 0
    assert "nowhere" in capsys.readouterr().err


def test_bench_generate_needs_no_warp():
    """The decoding benchmark (and the CLI's parser) load no physics: a GPU host without Warp runs it."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['warp'] = None\n"
            "from physcene.cli import main\n"
            "sys.exit(main(['bench', 'generate', '--config', 'tiny', '--batch', '1', '--tokens', '2', "
            "'--repeat', '1', '--variants', 'fast']))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "fast" in done.stdout


def test_bench_generate_agreement_compares_rows_up_to_their_eos():
    """`--until-eos`: what follows a row's EOS (padding, or tokens a forced run kept writing) is not
    compared; the first differing step is the first position where the cut rows differ."""
    from physcene.commands.bench.generate import _agreement

    reference = [[5, 6, 2, 9, 9], [5, 6, 7, 2, 0], [5, 6, 7, 8, 8]]
    ids = [[5, 6, 2, 1, 1], [5, 4, 7, 2, 0], [5, 6, 7, 8, 3]]
    cut = _agreement(ids, reference, eos=2)
    assert cut["equal_rows"] == pytest.approx(1 / 3) and cut["first_diff_step"] == 1
    assert cut["first_diff_step_median"] == 4  # rows 2 and 3 differ at steps 1 and 4
    whole = _agreement(ids, reference)
    assert whole["equal_rows"] == 0.0 and whole["first_diff_step"] == 1
