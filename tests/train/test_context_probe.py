"""physcene.train.analysis.context_probe: the two teacher-forced probes run on a checkpoint and measure what
they say (the zone's digits; a first box moved onto the second one)."""

from __future__ import annotations

import json
import sys

import pytest
import torch

from physcene.ctrc import parse
from physcene.data import synthesize
from physcene.train.analysis import context_probe as probe
from physcene.train.models import build_scratch_model
from physcene.train.tokenizer import build_tokenizer

ARCH = dict(hidden_size=48, intermediate_size=96, num_hidden_layers=2, num_attention_heads=4,
            num_key_value_heads=2, head_dim=12, max_position_embeddings=4096)


@pytest.fixture(scope="module")
def records():
    return [r for r in synthesize("train", n=6, seed=5) if r["level"] <= 3][:3]


def test_moving_the_first_box_onto_the_second_makes_them_overlap(records):
    edited = [probe.moved_onto_next(r["completion"]) for r in records]
    assert any(e is not None for e in edited)
    for r, e in zip(records, edited):
        if e is None:
            continue
        text, after, edited_after = e
        near = [o for o in parse(text).objects if o.parent == "root_zone"]
        assert near[0].center[:2] == pytest.approx(near[1].center[:2], abs=1e-3)  # one on the other
        assert text[edited_after:] == r["completion"][after:]  # only the first box changed


def test_probes_run_on_a_checkpoint(records, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    texts = [r["prompt"] for r in records] + [r["completion"] for r in records]
    tokenizer = build_tokenizer(texts, vocab_size=320)
    model = build_scratch_model(ARCH, tokenizer, seed=1)
    model.save_pretrained(tmp_path / "ckpt")
    tokenizer.save_pretrained(tmp_path / "ckpt")
    with open(tmp_path / "records.jsonl", "w") as fh:
        fh.writelines(json.dumps(r) + "\n" for r in records)
    out = tmp_path / "probe.json"
    argv = ["context_probe.py", str(tmp_path / "ckpt"), str(tmp_path / "records.jsonl"), "--n", "3",
            "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    probe.main()
    result = json.loads(out.read_text())
    assert result["zone"]["n"] == 3 and 0.0 < result["zone"]["digit_probability_median"] < 1.0
    assert result["neighbour"]["n"] >= 1 and 0 <= result["neighbour"]["raised"] <= result["neighbour"]["n"]
    # the digits probed are those of the zone's width and depth (an untrained model: far from certain)
    z = probe.zone_probe(probe._Scorer(str(tmp_path / "ckpt")), records[0])
    width_depth = [v for v in records[0]["completion"].split('"bbox": [')[1].split("]")[0].split(", ")][1:4:2]
    assert len(z["digit_probabilities"]) == sum(c.isdigit() for v in width_depth for c in v)


def test_a_vocabulary_without_digit_tokens_reports_no_digit_median(records, monkeypatch):
    """With whole numbers as single tokens (the ``ctrc`` tokenizer) no zone digit is probed: the median is
    None and the rest of the probes still report."""
    monkeypatch.setattr(probe, "zone_probe", lambda scorer, r: {"digit_probabilities": [], "nll": 2.0,
                                                                 "nll_bigger_zone": 3.0})
    monkeypatch.setattr(probe, "neighbour_probe", lambda scorer, r: {"nll": 2.0, "nll_moved_onto_next": 2.5})
    result = probe.probe(None, records)
    assert result["zone"] == {"n": 3, "digit_probability_median": None, "nll_change_bigger_zone": 0.5}
    assert result["neighbour"] == {"n": 3, "nll_change_moved_onto_next": 0.25, "raised": 3}
