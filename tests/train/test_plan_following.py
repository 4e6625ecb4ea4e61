"""physcene.train.analysis.plan_following: the study decodes one checkpoint with the layout's order and
parents free and taken from its plan, and measures how each row's layouts relate to their plans."""

from __future__ import annotations

import json
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
