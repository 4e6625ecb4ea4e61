"""The ``ctrc`` tokenizer kind (train/tokenizer.py): the same text in fewer tokens, every string back
exactly, the format's units as single tokens, and the CTRC constraint and the training config work with it.
(tests/train/test_constrained.py runs the constraint's own tests with both kinds.)"""

import json

import pytest
import torch

from physcene.commands.bench.tokens import completion_tokens, fuzz_texts, round_trips, token_counts
from physcene.config import load_config
from physcene.ctrc import ParseError, parse
from physcene.ctrc.grammar import ENTRY_KEYS, LAYOUT_OPEN, key_text
from physcene.data import synthesize
from physcene.train.constrained import CTRCConstraint
from physcene.train.models import load_tokenizer, prepare_model_and_tokenizer, tokenizer_settings
from physcene.train.tokenizer import KINDS, build_tokenizer


@pytest.fixture(scope="module")
def train_texts():
    return [t for r in synthesize("train", 24, seed=1) for t in (r["prompt"], r["completion"])]


@pytest.fixture(scope="module")
def references():
    return list(synthesize("test", 6, seed=0))


@pytest.fixture(scope="module")
def tokenizers(train_texts):
    return {kind: build_tokenizer(train_texts, vocab_size=4096, kind=kind) for kind in KINDS}


def test_references_and_fuzzed_text_round_trip(tokenizers, references):
    """decode(encode(text)) is the text for the test split's prompts and completions, random bytes,
    unicode up to U+10FFFF and CTRC-like punctuation soup; token by token the completion's texts add up
    to it (the constraint keeps each row's text as the sum of its tokens' texts)."""
    tok = tokenizers["ctrc"]
    texts = [t for r in references for t in (r["prompt"], r["completion"])]
    fuzz = fuzz_texts(150, seed=4) + ["", " ", "\n\n", "<|endoftext|>", "-0.000001", "1e-05", "😀 ü 漢字"]
    assert round_trips(tok, texts) == []
    assert round_trips(tok, fuzz) == []
    for r in references:
        ids = tok(r["completion"], add_special_tokens=False)["input_ids"]
        assert "".join(tok.decode([i]) for i in ids) == r["completion"]


def test_fewer_tokens_per_object_than_the_digit_bpe(tokenizers, references):
    """The same references: the digit-level BPE spends 180 tokens per object here (trained on 24
    records), the ctrc kind 64 (x0.36); trained on 1,500 records and counted on the whole test split:
    175 and 57 (docs/training.md)."""
    bpe = token_counts(tokenizers["bpe"], references)["tokens_per_object"]
    ctrc = token_counts(tokenizers["ctrc"], references)["tokens_per_object"]
    assert ctrc < 72
    assert ctrc < 0.42 * bpe


def test_format_units_are_single_tokens(tokenizers, references):
    """The pre-tokenizer cuts the text into the format's units (keys with their quotes, the runs between
    entries, names, numbers as integer part + point and three digits + the rest), and the frequent ones
    are one token each: every key of every reference completion sits inside one token."""
    tok = tokenizers["ctrc"]
    units = [u for u, _ in tok.backend_tokenizer.pre_tokenizer.pre_tokenize_str(
        '"description": "Red mug.", "relative_bbox": [40.00637, -3.39774, 0.0], '
        '"relative_rotation_deg": 12.5},\n    {"layer": 2, "instance_id": "10_picture_frame_0"')]
    text_units = [tok.backend_tokenizer.decoder.decode([u]) for u in units]
    assert text_units == [
        '"', "description", '": "', "Red mug", ".", '", "relative_bbox": [', "40", ".006", "37", ", -3",
        ".397", "74", ", 0", ".0", '], "relative_rotation_deg": ', "12", ".5", '},\n    {"layer": ', "2",
        ', "instance_id": "', "10", "_picture_frame_", "0", '"']
    for r in references:
        ids = tok(r["completion"], add_special_tokens=False)["input_ids"]
        pieces = [tok.decode([i]) for i in ids]
        for key in ENTRY_KEYS[1:]:
            assert sum(key_text(key) in p for p in pieces) == r["completion"].count(key_text(key)), key
        assert "." + LAYOUT_OPEN + '{"layer": ' in pieces
        assert pieces.count("root_zone") == r["completion"].count("root_zone")


def test_the_units_come_from_the_grammar(monkeypatch):
    """A key renamed in physcene.ctrc.grammar is a unit under its new name (no second list of keys)."""
    import physcene.train.tokenizer as module

    text = '", "yaw_deg": 12.5}'
    assert [u for u, _ in module._pre_tokenizer("ctrc").pre_tokenize_str(text)][0] == '",Ġ"'
    monkeypatch.setattr(module, "ENTRY_KEYS", (*ENTRY_KEYS[:-1], "yaw_deg"))
    assert [u for u, _ in module._pre_tokenizer("ctrc").pre_tokenize_str(text)][0] == '",Ġ"yaw_deg":Ġ'


def test_sft_feeds_the_completion_in_fewer_tokens(tokenizers, references):
    """The completion tokens TRL's SFT sees (prompt + completion + EOS less the shared prefix)."""
    r = references[0]
    for tok in tokenizers.values():
        n = completion_tokens(tok, r["prompt"], r["completion"])
        assert n == len(tok(r["completion"], add_special_tokens=False)["input_ids"]) + 1  # + EOS
    assert completion_tokens(tokenizers["ctrc"], r["prompt"], r["completion"]) \
        < 0.6 * completion_tokens(tokenizers["bpe"], r["prompt"], r["completion"])


def test_unknown_kind_is_one_clear_error(train_texts):
    with pytest.raises(ValueError, match="model.tokenizer.kind must be one of bpe, ctrc, got 'wordpiece'"):
        build_tokenizer(train_texts[:2], vocab_size=512, kind="wordpiece")


def test_tiny_config_with_the_ctrc_kind_saves_and_decodes_constrained(tmp_path, train_texts, references):
    """``model.tokenizer.kind=ctrc`` on the tiny config: the tokenizer saved with the run loads back as
    the same vocabulary, the constraint passes a reference completion unchanged token by token, and
    HF generate runs under it on the tiny model."""
    cfg = load_config("train_tiny", ["model.tokenizer.kind=ctrc"])
    assert tokenizer_settings(cfg.model) == {"vocab_size": 384, "kind": "ctrc"}
    assert tokenizer_settings(load_config("train_tiny").model)["kind"] == "bpe"
    model, tok = prepare_model_and_tokenizer(cfg, texts=train_texts, out_dir=tmp_path)
    loaded = load_tokenizer(tmp_path / "tokenizer")
    r = min(references, key=lambda r: len(r["completion"]))
    ids = tok(r["completion"], add_special_tokens=False)["input_ids"]
    assert loaded(r["completion"], add_special_tokens=False)["input_ids"] == ids
    assert len(ids) < len(build_tokenizer(train_texts, vocab_size=384)(r["completion"])["input_ids"])

    proc = CTRCConstraint(loaded, [r["prompt"]])
    prompt = torch.full((1, 3), loaded.pad_token_id)
    for k, t in enumerate([*ids, loaded.eos_token_id]):
        scores = torch.randn(1, len(loaded))
        scores[0, t] = 50.0
        out = proc(torch.cat([prompt, torch.tensor([ids[:k]], dtype=torch.long)], 1), scores)
        assert out[0, t] == 50.0, repr(proc.texts[0][-60:])
    assert proc.stats.masked_steps == 0
    assert not isinstance(parse(proc.texts[0]), ParseError)

    from physcene.train.generate import generate_token_ids

    rows = generate_token_ids(model.eval(), loaded, [x["prompt"] for x in references[:2]], max_new_tokens=16,
                              batch_size=2, constrained=True)
    assert len(rows) == 2 and all(0 < len(row) <= 16 for row in rows)


def test_bench_tokens_reports_both_kinds(capsys):
    """``physcene bench tokens``: tokens per object, characters, vocabulary and the round trip per kind;
    an unknown kind is one error on stderr."""
    from physcene.cli import main

    args = ["bench", "tokens", "--config", "tiny", "--train", "synth:train:8", "--n", "3", "--fuzz", "12",
            "--vocab-size", "2048"]
    assert main([*args, "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["target"] == "tokens" and r["references"] == 3 and r["train_records"] == 8
    assert r["objects"] > 0 and r["chars_per_object"] > 100
    bpe, ctrc = r["kinds"]["bpe"], r["kinds"]["ctrc"]
    assert bpe["round_trip_failures"] == ctrc["round_trip_failures"] == 0 and bpe["round_trip_texts"] == 18
    assert bpe["tokens_per_object_ratio"] == 1.0 and ctrc["tokens_per_object_ratio"] < 0.6
    assert ctrc["vocab_size"] <= 2048
    assert main([*args, "--kinds", "ctrc", "wordpiece"]) == 2
    assert "--kinds wordpiece" in capsys.readouterr().err
