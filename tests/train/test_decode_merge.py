"""LoRA merged for decoding (physcene.train.decode.merge, ``pada.merge_adapters``): one matmul per
adapted projection, the unmerged policy's logits and greedy ids, the trained weights untouched, each
call reading the adapters as they are then, the model given back as it was."""

from __future__ import annotations

import pytest
import torch
from peft import LoraConfig, get_peft_model

from physcene.train.constrained import CTRCConstraint
from physcene.train.decode import fast_generate, lora_projections, merged_lora
from physcene.train.generate import generate_token_ids
from physcene.train.models import build_scratch_model

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py

TARGETS = ["q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj"]


def _policy(tokenizer, tiny_arch, *, seed: int = 3, **lora) -> torch.nn.Module:
    """A tiny Qwen3 with LoRA adapters on every projection whose B is not zero (PEFT starts B at zero,
    which would make a merged model equal to its base whatever the merge did)."""
    base = build_scratch_model(tiny_arch, tokenizer, seed=seed)
    model = get_peft_model(base, LoraConfig(r=4, lora_alpha=8, lora_dropout=0.1, target_modules=TARGETS,
                                            **lora))
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lora_B" in name:
                param.copy_(torch.randn(param.shape, generator=generator) * 0.2)
    return model.eval()


def _linear_calls(model, ids) -> int:
    """``aten::linear`` calls in one forward of ``model`` (the profiler's count of the projections'
    matmuls)."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof, torch.no_grad():
        model(input_ids=ids)
    return sum(e.count for e in prof.key_averages() if e.key == "aten::linear")


def test_each_adapted_projection_runs_one_matmul_with_the_unmerged_logits(tokenizer, tiny_arch):
    model = _policy(tokenizer, tiny_arch)
    projections = lora_projections(model)
    assert len(projections) == len(TARGETS) * tiny_arch["num_hidden_layers"]
    ids = torch.randint(5, 300, (3, 17), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        unmerged = model(input_ids=ids).logits
    unmerged_calls = _linear_calls(model, ids)
    with merged_lora(model) as merged_count, torch.no_grad():
        merged = model(input_ids=ids).logits
        merged_calls = _linear_calls(model, ids)
    assert merged_count == len(projections)
    # every projection: base + lora_A + lora_B (3 linears) -> one
    assert unmerged_calls - merged_calls == 2 * len(projections)
    assert torch.allclose(merged, unmerged, atol=1e-4, rtol=1e-4)
    assert (merged - unmerged).abs().max() > 0  # the merged path ran (float32 rounds it otherwise)
    assert all("forward" not in vars(m) for m in projections)  # given back


def test_merged_greedy_ids_equal_hf_generate_on_the_unmerged_policy(records, tokenizer, tiny_arch):
    """Float32: the merged fast decoder writes the unmerged policy's greedy ids (HF static generate
    through PEFT's LoRA layers), with and without the CTRC constraint."""
    model = _policy(tokenizer, tiny_arch)
    prompts = [records[0]["prompt"], records[1]["prompt"][:300], records[2]["prompt"][:400]]
    for constrained in (False, True):
        kwargs = dict(max_new_tokens=32, batch_size=3, constrained=constrained)
        reference = generate_token_ids(model, tokenizer, prompts, cache="static", **kwargs)
        tokenizer.padding_side = "left"
        enc = tokenizer(prompts, return_tensors="pt", padding=True, add_special_tokens=False)
        constraint = CTRCConstraint(tokenizer, prompts) if constrained else None
        result = fast_generate(model, enc["input_ids"], enc["attention_mask"], max_new_tokens=32,
                               eos=[tokenizer.eos_token_id], pad=tokenizer.pad_token_id,
                               constraint=constraint, merge_lora=True)
        cut = [row[:row.index(tokenizer.eos_token_id) + 1] if tokenizer.eos_token_id in row else row
               for row in reference]
        assert result.tokens == cut


def test_the_trained_weights_are_untouched_and_each_call_reads_the_current_adapters(tokenizer, tiny_arch):
    """Base weights bitwise as they were after merged calls (PEFT's merge/unmerge round trip would not
    give bf16 weights back); an adapter changed between calls (an optimizer step) is what the next
    call decodes with, from the same decoding buffers (a captured CUDA graph reads them)."""
    model = _policy(tokenizer, tiny_arch).to(torch.bfloat16)
    projections = lora_projections(model)
    before = {name: p.detach().clone() for name, p in model.named_parameters() if "lora_" not in name}
    ids = torch.randint(5, 300, (2, 9), generator=torch.Generator().manual_seed(1))
    with merged_lora(model):
        buffers = [m._physcene_decoding_weight.data_ptr() for m in projections]
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lora_A" in name:
                param.mul_(-1.5)  # a step that changes every adapter
    with torch.no_grad():
        expected = model(input_ids=ids).logits.float()
    with merged_lora(model), torch.no_grad():
        merged = model(input_ids=ids).logits.float()
    assert [m._physcene_decoding_weight.data_ptr() for m in projections] == buffers
    assert torch.allclose(merged, expected, atol=0.1, rtol=0.05)
    for name, param in model.named_parameters():
        if name in before:
            assert torch.equal(param, before[name]), name


def test_training_after_a_merged_call_trains_the_adapters(tokenizer, tiny_arch):
    """The patched forward lives only for the call: a training forward afterwards goes through the LoRA
    layers again and gives the adapters gradients."""
    model = _policy(tokenizer, tiny_arch)
    ids = torch.randint(5, 300, (2, 9), generator=torch.Generator().manual_seed(2))
    mask = torch.ones_like(ids)
    fast_generate(model, ids, mask, max_new_tokens=4, eos=[tokenizer.eos_token_id],
                  pad=tokenizer.pad_token_id, merge_lora=True)
    model.train()
    model(input_ids=ids, labels=ids).loss.backward()
    grads = [p.grad for name, p in model.named_parameters() if "lora_A" in name]
    assert grads and all(g is not None and g.abs().sum() > 0 for g in grads)


def test_variants_and_models_without_adapters_are_left_as_they_are(tokenizer, tiny_arch):
    """DoRA (another merge) is not merged; a model without adapters decodes as it is."""
    dora = _policy(tokenizer, tiny_arch, use_dora=True)
    assert lora_projections(dora) == []
    plain = build_scratch_model(tiny_arch, tokenizer, seed=3).eval()
    with merged_lora(plain) as merged:
        assert merged == 0


def test_merge_adapters_needs_the_fast_decoder(tmp_path):
    from physcene.config import load_config
    from physcene.train.pada import pada_arguments

    cfg = load_config("train_tiny", [f"output_dir={tmp_path}", "pada.cache=fast", "pada.merge_adapters=true"])
    assert pada_arguments(cfg, "pada").merge_adapters
    cfg = load_config("train_tiny", [f"output_dir={tmp_path}", "pada.cache=static",
                                     "pada.merge_adapters=true"])
    with pytest.raises(ValueError, match="pada.merge_adapters"):
        pada_arguments(cfg, "pada")
