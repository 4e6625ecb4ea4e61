"""physcene.train.analysis.plan_following: the study decodes one checkpoint with the layout's order and
parents free and taken from its plan, and measures how each row's layouts relate to their plans."""

from __future__ import annotations

import gzip
import json
import os
import subprocess
import sys

import pytest
import torch

from physcene.ctrc import completion_text
from physcene.data import synthesize
from physcene.eval.harness import load_benchmark
from physcene.train.analysis import plan_following as study
from physcene.train.models import build_scratch_model
from physcene.train.tokenizer import build_tokenizer

ARCH = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
            num_key_value_heads=1, head_dim=16, max_position_embeddings=8192)


def test_the_references_keep_their_plans_and_a_shuffled_layout_does_not():
    items = load_benchmark("test", n=4, progress=False)
    prompts = [it.prompt for it in items]
    texts = [completion_text(it.reference) for it in items]
    agreement = study.plan_agreement(prompts, texts)
    assert agreement["order_kept"] == 1.0 and agreement["parent_kept"] == 1.0
    assert agreement["scenes_with_plan"] == 4 and 0.0 < agreement["on_table"] <= 1.0
    # the first two table-level entries of a layout swapped: the order is not the plan's any more
    swapped = [_swap_first_two_table_entries(t) for t in texts]
    assert study.plan_agreement(prompts, swapped)["order_kept"] == 0.0
    assert study.plan_agreement(prompts, ["not a layout"] * 4)["on_table"] is None


def _swap_first_two_table_entries(text: str) -> str:
    lines = text.split("\n")
    a, b = [k for k, line in enumerate(lines) if '"relation_type": "near"' in line][:2]
    lines[a], lines[b] = lines[b], lines[a]
    return "\n".join(lines)


def _tiny_checkpoint(folder):
    """A random tiny model with a tokenizer trained on 6 synthetic records, saved to ``folder``."""
    torch.set_num_threads(1)
    records = list(synthesize("train", n=6, seed=2))
    tokenizer = build_tokenizer([t for r in records for t in (r["prompt"], r["completion"])], vocab_size=320)
    build_scratch_model(ARCH, tokenizer, seed=1).save_pretrained(folder)
    tokenizer.save_pretrained(folder)


def test_the_study_decodes_twice_and_scores_every_row(tmp_path, monkeypatch):
    """The rows, their columns and files, with the decoding stubbed: free, the 'model' swaps two
    table-level entries of the reference; told to follow its plan, it writes the reference. (What the
    constraint does under follow_plan is tests/train/test_constrained.py's.)"""
    _tiny_checkpoint(tmp_path / "ckpt")
    items = load_benchmark("test", n=3, progress=False)
    references = {it.prompt: completion_text(it.reference) for it in items}
    calls = []

    def decode(model, tokenizer, prompts, **kw):
        calls.append(kw)
        texts = [references[p] for p in prompts]
        return texts if kw["follow_plan"] else [_swap_first_two_table_entries(t) for t in texts]

    monkeypatch.setattr(study, "generate_with", decode)
    out = tmp_path / "study.json"
    argv = ["plan_following", str(tmp_path / "ckpt"), "--n", "3", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    study.main()
    assert [(c["constrained"], c["follow_plan"], c["do_sample"]) for c in calls] == [(True, False, False),
                                                                                  (True, True, False)]
    result = json.loads(out.read_text())
    rows = {r["name"]: r for r in result["rows"]}
    assert list(rows) == ["reference", "sft", "sft+plan"] and result["n"] == 3
    for row in rows.values():
        assert {"scr", "acr", "floating", "shrunk", "out_of_zone", "parse_rate", "judge_avg"} <= set(row)
        assert (tmp_path / "study" / row["layouts"].split("/")[-1]).is_file()
        assert row["parse_rate"] == 1.0
    assert rows["sft"]["order_kept"] == 0.0 and rows["sft+plan"]["order_kept"] == 1.0
    assert rows["sft+plan"]["scr"] == rows["reference"]["scr"]  # the same layouts, scored alike


def test_the_study_decodes_only_the_rows_asked_for(tmp_path, monkeypatch):
    """``--rows sft+plan`` decodes once, with the plan followed; an unknown row is refused by name."""
    _tiny_checkpoint(tmp_path / "ckpt")
    items = load_benchmark("test", n=2, progress=False)
    references = {it.prompt: completion_text(it.reference) for it in items}
    calls = []

    def decode(model, tokenizer, prompts, **kw):
        calls.append(kw["follow_plan"])
        return [references[p] for p in prompts]

    monkeypatch.setattr(study, "generate_with", decode)
    out = tmp_path / "study.json"
    argv = ["plan_following", str(tmp_path / "ckpt"), "--n", "2", "--rows", "sft+plan", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    study.main()
    assert calls == [True]
    assert [r["name"] for r in json.loads(out.read_text())["rows"]] == ["reference", "sft+plan"]
    with pytest.raises(ValueError, match="plan_free"):
        study.run(str(tmp_path / "ckpt"), n=2, out=tmp_path / "x.json", rows=("plan_free",))


def _stub_decode(monkeypatch, items):
    """The decoding stubbed as in the test above: free, two table-level entries swapped; planned, the
    reference."""
    references = {it.prompt: completion_text(it.reference) for it in items}

    def decode(model, tokenizer, prompts, **kw):
        texts = [references[p] for p in prompts]
        return texts if kw["follow_plan"] else [_swap_first_two_table_entries(t) for t in texts]

    monkeypatch.setattr(study, "generate_with", decode)


def _main(monkeypatch, *argv):
    monkeypatch.setattr(sys, "argv", ["plan_following", *map(str, argv)])
    study.main()


def test_a_decode_on_one_machine_is_scored_on_another_as_one_run_scores_it(tmp_path, monkeypatch, capsys):
    """--decode-only writes each row's completions and the decoding's settings and scores nothing;
    --completions scores them into the rows one run gives; a decode of other scenes is refused by name."""
    _tiny_checkpoint(tmp_path / "ckpt")
    _stub_decode(monkeypatch, load_benchmark("test", n=3, progress=False))
    _main(monkeypatch, tmp_path / "ckpt", "--n", 3, "--out", tmp_path / "one.json")
    _main(monkeypatch, tmp_path / "ckpt", "--n", 3, "--decode-only", "--device", "cpu",
          "--out", tmp_path / "decoded.json")
    decoded = tmp_path / "decoded"
    assert not (tmp_path / "decoded.json").exists()
    assert sorted(p.name for p in decoded.iterdir()) == ["decoding.json", "sft.completions.jsonl.gz",
                                                         "sft_plan.completions.jsonl.gz"]
    assert json.loads((decoded / "decoding.json").read_text())["rows"] == ["sft", "sft+plan"]
    _main(monkeypatch, "--completions", decoded, "--n", 3, "--out", tmp_path / "two.json")

    def rows(name):
        return [{k: v for k, v in r.items() if k != "layouts"}
                for r in json.loads((tmp_path / name).read_text())["rows"]]

    assert rows("two.json") == rows("one.json") and len(rows("one.json")) == 3
    two = json.loads((tmp_path / "two.json").read_text())
    assert len(two["commands"]) == 2 and "--decode-only" in two["commands"][0]
    _main(monkeypatch, "--completions", decoded, "--n", 3, "--rows", "sft", "--out", tmp_path / "sft.json")
    alone = json.loads((tmp_path / "sft.json").read_text())["rows"]
    assert [r["name"] for r in alone] == ["reference", "sft"]
    for argv, message in ((("--n", 4), "no completion for scene"), (("--n", 3, "--seed", 1), "seed 1"),
                          (("--n", 2), "a draw of another n")):
        capsys.readouterr()
        with pytest.raises(SystemExit):
            _main(monkeypatch, "--completions", decoded, *argv, "--out", tmp_path / "x.json")
        assert message in capsys.readouterr().err
    (decoded / "sft.completions.jsonl.gz").unlink()
    with pytest.raises(SystemExit):
        _main(monkeypatch, "--completions", decoded, "--n", 3, "--out", tmp_path / "x.json")
    assert "no sft.completions.jsonl.gz" in capsys.readouterr().err
    both = (tmp_path / "ckpt", "--completions", decoded)
    for argv in (both, ("--completions", decoded, "--decode-only"), ()):
        with pytest.raises(SystemExit):  # a model and a decode's completions at once, or neither
            _main(monkeypatch, *argv, "--out", tmp_path / "x.json")
        assert "give a model checkpoint to decode, or --completions DIR" in capsys.readouterr().err


def test_a_decode_only_run_needs_no_warp(tmp_path):
    """A GPU host without Warp decodes: --decode-only on a real (tiny) model in a process where
    ``import warp`` fails writes the completions."""
    _tiny_checkpoint(tmp_path / "ckpt")
    fake = tmp_path / "site" / "warp"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('no Warp on this host')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path / "site"),
                                                                      os.environ.get("PYTHONPATH")]))}
    cmd = [sys.executable, "-m", "physcene.train.analysis.plan_following", str(tmp_path / "ckpt"), "--n", "2",
           "--max-new-tokens", "24", "--rows", "sft+plan", "--decode-only", "--out", str(tmp_path / "d.json")]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    records = gzip.decompress((tmp_path / "d" / "sft_plan.completions.jsonl.gz").read_bytes()).splitlines()
    assert len(records) == 2 and all(isinstance(json.loads(r)["completion"], str) for r in records)
    probe = subprocess.run([sys.executable, "-c", "import warp"], env=env, capture_output=True, text=True)
    assert probe.returncode != 0 and "no Warp on this host" in probe.stderr
