"""An RL adapter on a host other than its training host: the base its ``adapter_config.json`` names is
that host's path. ``load_for_generation(..., base=...)`` merges the adapter (a run's final one or a
``checkpoint-N``) into the base it is given, checked against the digest the run recorded; without it a
missing base is one error that says to pass it."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from peft import LoraConfig, get_peft_model

from physcene.artifacts import checkpoint_digest
from physcene.train.generate import load_for_generation
from physcene.train.models import RUN_INFO, TrainingSetupError, build_scratch_model, load_model

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


@pytest.fixture
def carried(tmp_path, tokenizer, tiny_arch):
    """(checkpoint-3 of an RL run whose base was at train_host/base, that base moved to here/base, the
    logits of the merged adapter on the training host)."""
    base_dir = tmp_path / "train_host" / "base"
    build_scratch_model(tiny_arch, tokenizer, seed=1).save_pretrained(base_dir)
    tokenizer.save_pretrained(base_dir)
    lora = LoraConfig(r=4, lora_alpha=8, target_modules=["q_proj", "v_proj"])
    model = get_peft_model(load_model(base_dir, dtype="float32"), lora)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lora_B" in name:
                param.normal_(0, 0.2)
    ckpt = tmp_path / "run" / "checkpoint-3"
    model.save_pretrained(ckpt)
    tokenizer.save_pretrained(ckpt)
    (tmp_path / "run" / RUN_INFO).write_text(json.dumps({"base_sha256": checkpoint_digest(base_dir)}))
    ids = torch.tensor([tokenizer("layout:")["input_ids"]])
    trained, _, _ = load_for_generation(ckpt, device="cpu")
    logits = trained(input_ids=ids).logits
    moved = tmp_path / "here" / "base"
    shutil.move(str(base_dir), moved)
    return ckpt, moved, ids, logits


def test_a_carried_adapter_loads_on_the_base_it_is_given(carried):
    ckpt, base, ids, logits = carried
    model, _, _ = load_for_generation(ckpt, device="cpu", base=base)
    torch.testing.assert_close(model(input_ids=ids).logits, logits)


def test_without_its_base_the_error_says_to_pass_it(carried):
    ckpt, _, _, _ = carried
    with pytest.raises(TrainingSetupError, match=r"checkpoint-3: a LoRA adapter on the base .*train_host/"
                                                 r"base', which is not here; pass the base it was"):
        load_for_generation(ckpt, device="cpu")


def test_a_base_of_another_digest_is_refused(carried, tmp_path, tokenizer, tiny_arch):
    ckpt, _, _, _ = carried
    other = tmp_path / "other"
    build_scratch_model(tiny_arch, tokenizer, seed=2).save_pretrained(other)
    tokenizer.save_pretrained(other)
    with pytest.raises(TrainingSetupError, match="checkpoint-3 was trained on a base with sha256 .*: pass "
                                                 "the base it was trained on"):
        load_for_generation(ckpt, device="cpu", base=other)
    with pytest.raises(TrainingSetupError, match="has no config.json"):
        load_for_generation(ckpt, device="cpu", base=tmp_path)


def test_the_anchor_likelihood_tool_takes_the_base(carried, records, tmp_path, monkeypatch):
    """`python -m physcene.train.analysis.anchor_likelihood ANCHORS NAME=ADAPTER --base BASE`: the carried
    adapter's held-out anchor NLL, on the base given."""
    from physcene.train.analysis import anchor_likelihood
    from physcene.train.anchors import anchor_nll
    from physcene.train.records import write_records

    ckpt, base, _, _ = carried
    held = tmp_path / "held.jsonl"
    write_records([dict(r, anchor=r["completion"]) for r in records[:2]], held)
    out = tmp_path / "nll.json"
    monkeypatch.setattr("sys.argv", ["anchor_likelihood", str(held), f"pada@3={ckpt}", "--base", str(base),
                                     "--max-length", "64", "--out", str(out)])
    anchor_likelihood.main()
    anchors = [dict(r, anchor=r["completion"]) for r in records[:2]]
    expected = anchor_nll(ckpt, anchors, base=base, max_length=64)
    assert json.loads(out.read_text())["models"]["pada@3"]["nll"] == pytest.approx(expected["nll"])


def test_anchors_decode_a_carried_adapter_on_the_base_they_are_given(carried, tmp_path, monkeypatch):
    """`physcene train anchors anchors.model=CHECKPOINT anchors.base=BASE`: anchors refreshed from an RL
    policy decode with the adapter merged into the base given; without it the one error says to pass it."""
    import physcene.train.anchors as anchors
    from physcene.config import load_config

    ckpt, base, ids, logits = carried
    seen = []

    def generate(model, tokenizer, prompts, **kw):  # the model the anchors decode with, then no layout
        seen.append(model(input_ids=ids).logits)
        return [tokenizer("not a layout", add_special_tokens=False)["input_ids"] + [tokenizer.eos_token_id]
                for _ in prompts]

    monkeypatch.setattr(anchors, "generate_token_ids", generate)
    overrides = [f"output_dir={tmp_path / 'refresh'}", "anchors.n_records=2", "data.train=synth:train:2",
                 f"anchors.model={ckpt}"]
    with pytest.raises(TrainingSetupError, match="pass the base it was trained on"):
        anchors.run_anchors(load_config("train_tiny", overrides))
    out = anchors.run_anchors(load_config("train_tiny", [*overrides, f"anchors.base={base}"]))
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    torch.testing.assert_close(seen[0], logits)
    assert [r["sft_completion"] for r in rows] == ["not a layout"] * 2


def test_an_adapter_kept_without_its_tokenizer_reads_its_bases(carried):
    """A curve point kept as adapter weights and config only (an artifact leaves the rest of an earlier
    checkpoint out) loads with its base's tokenizer: LoRA does not change it."""
    ckpt, base, ids, logits = carried
    for name in ("tokenizer.json", "tokenizer_config.json"):
        (ckpt / name).unlink()
    model, tokenizer, _ = load_for_generation(ckpt, device="cpu", base=base)
    torch.testing.assert_close(model(input_ids=ids).logits, logits)
    assert tokenizer("layout:")["input_ids"] == ids[0].tolist() and tokenizer.padding_side == "left"
