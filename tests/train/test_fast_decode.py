"""The fast decoder (``cache: fast``, physcene.train.decode) against HF ``generate``: equal greedy ids
on left-padded batches, with and without the CTRC constraint, for Qwen3 and a tiny Qwen3-VL;
sampling with a seed gives valid rows; dropout is off while it samples and back on afterwards."""

from __future__ import annotations

import pytest
import torch
from transformers import GenerationConfig, LogitsProcessorList

from physcene.train.constrained import CTRCConstraint, sampling_warpers
from physcene.train.decode import (
    FOLDED_ATTENTION,
    decoder_for,
    fast_generate,
    folded_gqa_attention,
    text_model,
)
from physcene.train.generate import generate_token_ids
from physcene.train.models import build_scratch_model

ARCH = dict(hidden_size=48, intermediate_size=96, num_hidden_layers=2, num_attention_heads=4,
            num_key_value_heads=2, head_dim=12, max_position_embeddings=4096)


pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


@pytest.fixture(scope="module")
def model(tokenizer):
    return build_scratch_model(ARCH, tokenizer, seed=3).eval()


def _left_padded(rows: list[list[int]], pad: int) -> tuple[torch.Tensor, torch.Tensor]:
    width = max(map(len, rows))
    ids = torch.full((len(rows), width), pad, dtype=torch.long)
    mask = torch.zeros((len(rows), width), dtype=torch.long)
    for b, row in enumerate(rows):
        ids[b, width - len(row):] = torch.tensor(row)
        mask[b, width - len(row):] = 1
    return ids, mask


def test_folded_attention_equals_the_repeated_kv_path():
    """Decoding-step attention: folding G query heads per KV head == sdpa over repeated K/V, masked."""
    torch.manual_seed(0)
    module = torch.nn.Module()
    module.num_key_value_groups, module.is_causal = 3, True
    q, k, v = torch.randn(2, 6, 1, 8), torch.randn(2, 2, 10, 8), torch.randn(2, 2, 10, 8)
    mask = torch.ones(2, 1, 1, 10, dtype=torch.bool)
    mask[0, ..., :4] = False  # a left-padded row
    ours, _ = folded_gqa_attention(module, q, k, v, mask, scaling=0.3)
    theirs = torch.nn.functional.scaled_dot_product_attention(
        q, k.repeat_interleave(3, 1), v.repeat_interleave(3, 1), attn_mask=mask, scale=0.3).transpose(1, 2)
    assert ours.shape == (2, 1, 6, 8)
    assert torch.allclose(ours, theirs, atol=1e-6)


@pytest.mark.parametrize("min_new", [0, 24])
def test_greedy_ids_equal_hf_generate(records, tokenizer, model, min_new):
    """Left-padded CTRC prompts, 40 new tokens: the fast path's ids are HF static generate's."""
    prompts = [records[0]["prompt"], records[1]["prompt"][:300], records[2]["prompt"],
               records[3]["prompt"][:500]]
    kwargs = dict(max_new_tokens=40, batch_size=4, min_new_tokens=min_new or None)
    assert (generate_token_ids(model, tokenizer, prompts, cache="fast", **kwargs)
            == generate_token_ids(model, tokenizer, prompts, cache="static", **kwargs))


def test_rows_stop_at_eos_as_in_hf_generate(model):
    """A row stops at its EOS (then padding, as generate pads), the others go on; equal ids."""
    torch.manual_seed(1)
    rows = [torch.randint(5, 300, (n,)).tolist() for n in (9, 3, 6)]
    ids, mask = _left_padded(rows, 0)
    reference = model.generate(input_ids=ids, attention_mask=mask, max_new_tokens=30, do_sample=False,
                               eos_token_id=7, pad_token_id=0)[:, ids.shape[1]:].tolist()
    eos = next(t for row in reference for t in row[:25] if t != 0)  # a token some row writes early
    reference = model.generate(input_ids=ids, attention_mask=mask, max_new_tokens=30, do_sample=False,
                               eos_token_id=eos, pad_token_id=0)[:, ids.shape[1]:].tolist()
    result = fast_generate(model, ids, mask, max_new_tokens=30, eos=[eos], pad=0)
    cut = [row[:row.index(eos) + 1] if eos in row else row for row in reference]
    assert result.tokens == cut
    assert any(len(row) < 30 for row in result.tokens)


def test_a_dropped_decoder_frees_its_cache_without_a_collector_pass(model):
    """A decoder nobody holds (one whose cache is over the size ``decoder_for`` keeps: each batch of a
    larger model's CPU decode makes one) frees its KV buffers when dropped, not at the garbage
    collector's next full pass: no reference cycle holds them (the cache's eager ``update`` once did,
    and a CPU decode grew by one cache per batch)."""
    import gc
    import weakref

    from physcene.train.decode import FastDecoder

    ids, mask = _left_padded([[5, 6, 7], [8, 9]], 0)
    decoder = FastDecoder(model, batch=2, length=16)
    decoder.generate(ids, mask, max_new_tokens=4, eos=[1], pad=0)
    buffers = [weakref.ref(t) for t in decoder.cache.keys + decoder.cache.values]
    cache = weakref.ref(decoder.cache)
    enabled = gc.isenabled()
    gc.disable()
    try:
        del decoder
        assert cache() is None and all(ref() is None for ref in buffers)
    finally:
        if enabled:
            gc.enable()


def _plan_prefixed(records, tokenizer, rows: int):
    """``rows`` copies of one record's prompt (different lengths: real left padding) followed by its
    reference plan, which the constraint has seen as completion: from there the layout is left to
    a model of random weights, and the constraint writes most of it."""
    r = records[0]
    plan = r["completion"].split("**Scene Layout:**")[0]
    prefix = tokenizer(plan, add_special_tokens=False)["input_ids"]
    prompts = [("Note. " * b) + r["prompt"] for b in range(rows)]
    ids, mask = _left_padded([tokenizer(p, add_special_tokens=False)["input_ids"] + prefix for p in prompts],
                             tokenizer.pad_token_id)
    return prompts, prefix, ids, mask


def _primed(tokenizer, prompts, prefix, **kwargs) -> CTRCConstraint:
    constraint = CTRCConstraint(tokenizer, prompts, **kwargs)
    for b in range(len(prompts)):
        constraint.advance_row(b, prefix)
    return constraint


def test_constrained_greedy_ids_equal_hf_generate_with_the_processor(records, tokenizer, model):
    """Under the CTRC constraint (which here overrules the model at most layout tokens): the fast
    path's greedy ids, its repairs included, are those of HF generate with the logits processor."""
    prompts, prefix, ids, mask = _plan_prefixed(records, tokenizer, 3)
    processor = CTRCConstraint(tokenizer, prompts)
    processor.prompt_length = ids.shape[1] - len(prefix)  # the plan is completion to the processor
    reference = model.generate(input_ids=ids, attention_mask=mask, max_new_tokens=64, do_sample=False,
                               eos_token_id=tokenizer.eos_token_id, pad_token_id=tokenizer.pad_token_id,
                               logits_processor=LogitsProcessorList([processor]))[:, ids.shape[1]:].tolist()
    constraint = _primed(tokenizer, prompts, prefix)
    result = fast_generate(model, ids, mask, max_new_tokens=64, eos=[tokenizer.eos_token_id],
                           pad=tokenizer.pad_token_id, constraint=constraint)
    assert result.tokens == reference
    assert result.repairs > 10  # the constraint acted, and each repair cost the row a step
    assert result.steps >= 64 - 1 + max(len(o) for o in constraint.stats.overruled) - 1
    assert constraint.stats.overruled == [[p - len(prefix) for p in o] for o in processor.stats.overruled]
    text = tokenizer.decode(prefix + result.tokens[0])
    assert "\"instance_id\": \"root_zone" in text  # the layout the constraint started


def test_sampling_with_a_seed_gives_valid_rows(records, tokenizer, model):
    """Sampling (temperature, top-k, top-p as TRL passes them), with and without the constraint: the
    same seed gives the same rows, a row's tokens are in the vocabulary, and under the constraint
    the text stays a valid CTRC prefix (each listed id once: it parses once closed)."""
    config = GenerationConfig(do_sample=True, temperature=0.9, top_k=50, top_p=0.95)
    warpers = sampling_warpers(config)
    prompts, prefix, ids, mask = _plan_prefixed(records, tokenizer, 3)
    runs = []
    for _ in range(2):
        torch.manual_seed(5)
        constraint = _primed(tokenizer, prompts, prefix, greedy=False, warpers=warpers)
        runs.append((fast_generate(model, ids, mask, max_new_tokens=48, eos=[tokenizer.eos_token_id],
                                   pad=tokenizer.pad_token_id, sampling=True, warpers=warpers,
                                   constraint=constraint), constraint))
    (first, constraint), (second, _) = runs
    assert first.tokens == second.tokens
    assert all(0 <= t < len(tokenizer) for row in first.tokens for t in row)
    assert len({tuple(row) for row in first.tokens}) > 1  # rows differ: sampled, not greedy
    for b, row in enumerate(first.tokens):
        assert constraint.texts[b] == tokenizer.decode(prefix + row, skip_special_tokens=True)
    torch.manual_seed(5)
    free = fast_generate(model, ids, mask, max_new_tokens=48, eos=[tokenizer.eos_token_id],
                         pad=tokenizer.pad_token_id, sampling=True, warpers=warpers)
    assert all(0 < len(row) <= 48 for row in free.tokens)


def test_dropout_is_off_while_sampling_and_restored(records, tokenizer):
    """A model in training mode (dropout 0.5 in attention): fast decoding sees eval mode and the
    folded attention, and gives the model back in training mode with its attention."""
    model = build_scratch_model({**ARCH, "attention_dropout": 0.5}, tokenizer, seed=3).train()
    seen = []
    hook = model.model.layers[0].self_attn.register_forward_hook(
        lambda module, args, out: seen.append((module.training, module.config._attn_implementation)))
    ids, mask = _left_padded([[5, 6, 7, 8], [9, 10]], tokenizer.pad_token_id)
    first = fast_generate(model, ids, mask, max_new_tokens=12, eos=[tokenizer.eos_token_id],
                          pad=tokenizer.pad_token_id)
    second = fast_generate(model, ids, mask, max_new_tokens=12, eos=[tokenizer.eos_token_id],
                           pad=tokenizer.pad_token_id)
    hook.remove()
    assert seen and all(not training for training, _ in seen)
    assert {name for _, name in seen} == {FOLDED_ATTENTION}
    assert first.tokens == second.tokens  # no dropout noise
    assert model.training and model.config._attn_implementation == "sdpa"


def test_tiny_qwen3_vl_greedy_ids_equal_hf_generate():
    """Qwen3-VL's text model (M-RoPE inside it) under the fast path: HF generate's greedy ids."""
    from transformers import Qwen3VLConfig, Qwen3VLForConditionalGeneration

    torch.manual_seed(0)
    config = Qwen3VLConfig(
        text_config=dict(vocab_size=256, hidden_size=64, intermediate_size=128, num_hidden_layers=2,
                         num_attention_heads=4, num_key_value_heads=2, head_dim=16,
                         max_position_embeddings=512,
                         rope_scaling={"rope_type": "default", "mrope_section": [2, 3, 3],
                                       "mrope_interleaved": True}),
        vision_config=dict(depth=1, hidden_size=32, intermediate_size=64, num_heads=2, out_hidden_size=64,
                           deepstack_visual_indexes=[]),
        image_token_id=250, video_token_id=251, vision_start_token_id=252)
    config.text_config._attn_implementation = "sdpa"
    model = Qwen3VLForConditionalGeneration(config).eval()
    assert text_model(model).config is model.config.text_config
    ids, mask = _left_padded([torch.randint(3, 240, (n,)).tolist() for n in (7, 3, 9)], 0)
    reference = model.generate(input_ids=ids, attention_mask=mask, max_new_tokens=24, do_sample=False,
                               eos_token_id=2, pad_token_id=0)[:, ids.shape[1]:].tolist()
    result = fast_generate(model, ids, mask, max_new_tokens=24, eos=[2], pad=0)
    assert result.tokens == [row[:row.index(2) + 1] if 2 in row else row for row in reference]


def test_pada_generates_with_the_fast_decoder(tmp_path, records, tokenizer):
    """``pada.cache: fast`` reaches the trainer and one PADA step samples its groups with the fast
    decoder, under the constraint (its counters logged) and without it (there with fused layers)."""
    from datasets import Dataset

    from physcene.config import load_config
    from physcene.train.pada import PADAConfig, PADATrainer, pada_arguments

    cfg = load_config("train_tiny", [f"output_dir={tmp_path}", "pada.cache=fast"])
    args = pada_arguments(cfg, "grpo")
    assert args.fast_decode == "fast" and args.cache_implementation is None
    fused_cfg = load_config("train_tiny", [f"output_dir={tmp_path}", "pada.cache=fast+fused"])
    fused = pada_arguments(fused_cfg, "grpo")
    assert fused.fast_decode == "fast+fused"
    for constrained, cache in ((True, "fast"), (False, "fast+fused")):
        model = build_scratch_model(ARCH, tokenizer, seed=3)
        args = PADAConfig(output_dir=str(tmp_path / str(constrained)), num_generations=2,
                          per_device_train_batch_size=2, max_completion_length=12, use_cpu=True,
                          report_to="none", beta=0.0, anchor_alpha=0.0, max_steps=1, fast_decode=cache,
                          constrained_decoding=constrained, logging_steps=1, save_strategy="no")
        prompts = [records[0]["prompt"][:200], records[1]["prompt"][:260]]
        trainer = PADATrainer(model, reward_funcs=[lambda prompts, completions, **kw: [0.0] * len(prompts)],
                              args=args, processing_class=tokenizer,
                              train_dataset=Dataset.from_list([{"prompt": p, "anchor": ""} for p in prompts]))
        trainer.train()
        logged = {k for entry in trainer.state.log_history for k in entry}
        assert "time/decode_graphs" in logged
        assert ("time/constraint_s" in logged) is constrained
        assert trainer.model.training  # given back in training mode


@pytest.mark.cuda
def test_cuda_graph_steps_equal_eager_steps_and_hf_generate(records, tokenizer):
    """On a GPU (float32): the replayed CUDA graphs give the eager steps' ids and HF generate's, with and
    without the constraint; sampling with a seed repeats; no fallback."""
    model = build_scratch_model(ARCH, tokenizer, seed=3).cuda().eval()
    prompts, prefix, ids, mask = _plan_prefixed(records, tokenizer, 4)
    ids, mask = ids.cuda(), mask.cuda()
    common = dict(max_new_tokens=160, eos=[tokenizer.eos_token_id], pad=tokenizer.pad_token_id)
    graphed = fast_generate(model, ids, mask, **common)
    assert graphed.graphs and graphed.fallback_reason is None
    assert graphed.tokens == fast_generate(model, ids, mask, graphs=False, **common).tokens
    reference = model.generate(input_ids=ids, attention_mask=mask, do_sample=False, max_new_tokens=160,
                               eos_token_id=tokenizer.eos_token_id, pad_token_id=tokenizer.pad_token_id)
    eos = tokenizer.eos_token_id
    cut = [row[:row.index(eos) + 1] if eos in row else row for row in reference[:, ids.shape[1]:].tolist()]
    assert graphed.tokens == cut
    processor = CTRCConstraint(tokenizer, prompts)
    processor.prompt_length = ids.shape[1] - len(prefix)
    reference = model.generate(input_ids=ids, attention_mask=mask, do_sample=False, max_new_tokens=160,
                               eos_token_id=eos, pad_token_id=tokenizer.pad_token_id,
                               logits_processor=LogitsProcessorList([processor]))
    constrained = fast_generate(model, ids, mask, constraint=_primed(tokenizer, prompts, prefix), **common)
    assert constrained.graphs and constrained.repairs > 0
    assert constrained.tokens == [row[:row.index(eos) + 1] if eos in row else row
                                  for row in reference[:, ids.shape[1]:].tolist()]
    warpers = sampling_warpers(GenerationConfig(do_sample=True, temperature=0.9, top_k=50, top_p=0.95))
    runs = []
    for _ in range(2):
        torch.manual_seed(11)
        runs.append(fast_generate(model, ids, mask, sampling=True, warpers=warpers, **common).tokens)
    assert runs[0] == runs[1]


@pytest.mark.cuda
def test_constrained_reads_wait_for_a_launch_that_captured(records, tokenizer, monkeypatch):
    """A graph capture runs its step for real first, rewriting both logits slots before it restores
    them: the constraint's reads, on a stream of their own, wait for every launch that captured (else
    a scan of step t's logits races the warm-up's writes), and the ids stay those of eager steps."""
    model = build_scratch_model(ARCH, tokenizer, seed=3).cuda().eval()
    prompts, prefix, ids, mask = _plan_prefixed(records, tokenizer, 4)
    ids, mask = ids.cuda(), mask.cuda()
    common = dict(max_new_tokens=160, eos=[tokenizer.eos_token_id], pad=tokenizer.pad_token_id)
    eager = fast_generate(model, ids, mask, graphs=False, constraint=_primed(tokenizer, prompts, prefix),
                          **common)
    waits, real = [], torch.cuda.Stream.wait_stream

    def wait_stream(stream, other):
        current = torch.cuda.current_stream()
        waits.append(stream != current and other == current)  # a side stream waits for the decoding one
        return real(stream, other)

    monkeypatch.setattr(torch.cuda.Stream, "wait_stream", wait_stream)
    decoder = decoder_for(model, ids.shape[0], ids.shape[1] + common["max_new_tokens"])
    before = decoder.warmups
    graphed = fast_generate(model, ids, mask, constraint=_primed(tokenizer, prompts, prefix), **common)
    assert graphed.graphs and graphed.tokens == eager.tokens
    captures = decoder.warmups - before
    assert captures > 0
    # each capture's warm-up stream, and the reads after it
    assert waits.count(True) == 2 * captures


def _decoding_step_inputs():
    """One GQA decoding step (2 query heads per KV head): module, q, k, v and a bool mask of written
    columns with row 1's first 5 columns unwritten."""
    torch.manual_seed(0)
    module = torch.nn.Module()
    module.num_key_value_groups, module.is_causal, module.training = 2, True, False
    q, k, v = torch.randn(3, 4, 1, 8), torch.randn(3, 2, 12, 8), torch.randn(3, 2, 12, 8)
    mask = torch.ones(3, 1, 1, 12, dtype=torch.bool)
    mask[1, ..., :5] = False
    return module, q, k, v, mask


def test_matmul_attention_agrees_with_sdpa(records, tokenizer, model):
    """The matmul decoding attention (float32 scores): the sdpa one's outputs to float32 rounding, and
    the same greedy ids on the tiny model in float32."""
    from physcene.train.decode import folded_matmul_attention

    module, q, k, v, mask = _decoding_step_inputs()
    ours, _ = folded_matmul_attention(module, q, k, v, mask, scaling=0.35)
    theirs, _ = folded_gqa_attention(module, q, k, v, mask, scaling=0.35)
    assert torch.allclose(ours, theirs, atol=1e-5)
    prompts = [records[0]["prompt"], records[1]["prompt"][:300]]
    kwargs = dict(max_new_tokens=24, batch_size=2)
    assert (generate_token_ids(model, tokenizer, prompts, cache="fast+matmul", **kwargs)
            == generate_token_ids(model, tokenizer, prompts, cache="fast", **kwargs))


def test_flex_attention_agrees_with_sdpa(records, tokenizer, model):
    """The FlexAttention decoding step: sdpa's outputs to float32 rounding under a bool mask of written
    columns and under the same mask as an additive bias, a per-query mask handed to sdpa, and the
    same greedy ids on the tiny model in float32 (with and without the CTRC constraint)."""
    from physcene.train.decode import flex_decode_attention

    module, q, k, v, mask = _decoding_step_inputs()
    mask[2, ..., 9:] = False
    theirs, _ = folded_gqa_attention(module, q, k, v, mask, scaling=0.35)
    ours, _ = flex_decode_attention(module, q, k, v, mask, scaling=0.35)
    assert ours.shape == theirs.shape == (3, 1, 4, 8) and torch.allclose(ours, theirs, atol=1e-5)
    bias = torch.zeros(mask.shape).masked_fill(~mask, torch.finfo(torch.float32).min)
    assert torch.allclose(flex_decode_attention(module, q, k, v, bias, scaling=0.35)[0], theirs, atol=1e-5)
    unmasked, _ = flex_decode_attention(module, q, k, v, None, scaling=0.35)
    assert torch.allclose(unmasked, folded_gqa_attention(module, q, k, v, None, scaling=0.35)[0], atol=1e-5)
    prompts = [records[0]["prompt"], records[1]["prompt"][:300]]
    for constrained in (False, True):
        kwargs = dict(max_new_tokens=24, batch_size=2, constrained=constrained)
        assert (generate_token_ids(model, tokenizer, prompts, cache="fast+flex", **kwargs)
                == generate_token_ids(model, tokenizer, prompts, cache="fast", **kwargs))


def test_fused_layers_keep_hf_generate_ids_and_are_restored(records, tokenizer, model):
    """``cache: fast+fused`` (the decoder layers compiled by inductor around the eager cache write and
    attention): HF static generate's greedy ids in float32 on the tiny model, with and without the CTRC
    constraint and with the flex attention; afterwards the layers run their own forward again."""
    from physcene.train.decode.fuse import decoder_layers

    prompts = [records[0]["prompt"], records[1]["prompt"][:300], records[2]["prompt"][:400]]
    for constrained in (False, True):
        kwargs = dict(max_new_tokens=32, batch_size=3, constrained=constrained)
        reference = generate_token_ids(model, tokenizer, prompts, cache="static", **kwargs)
        assert generate_token_ids(model, tokenizer, prompts, cache="fast+fused", **kwargs) == reference
    kwargs = dict(max_new_tokens=32, batch_size=3)
    reference = generate_token_ids(model, tokenizer, prompts, cache="static", **kwargs)
    for cache in ("fast+fused+flex", "fast+fused+cudnn"):  # on a CPU cudnn is the folded sdpa
        assert generate_token_ids(model, tokenizer, prompts, cache=cache, **kwargs) == reference
    assert all("forward" not in vars(layer) for layer in decoder_layers(text_model(model)))


@pytest.mark.cuda
def test_flex_attention_runs_inside_cuda_graphs(records, tokenizer):
    """On a GPU (float32): the compiled FlexAttention step and the fused layers are captured and
    replayed as CUDA graphs (no fallback) and give the eager sdpa steps' greedy ids on the tiny model
    (head_dim 16: the smallest compiled FlexAttention takes). The cuDNN decoding kernel (bf16 only)
    is captured too."""
    model = build_scratch_model({**ARCH, "head_dim": 16}, tokenizer, seed=3).cuda().eval()
    _, _, ids, mask = _plan_prefixed(records, tokenizer, 4)
    ids, mask = ids.cuda(), mask.cuda()
    common = dict(max_new_tokens=96, eos=[tokenizer.eos_token_id], pad=tokenizer.pad_token_id)
    flex = fast_generate(model, ids, mask, attention="flex", **common)
    assert flex.graphs and flex.fallback_reason is None
    eager = fast_generate(model, ids, mask, graphs=False, **common)
    assert flex.tokens == fast_generate(model, ids, mask, **common).tokens == eager.tokens
    for attention in ("sdpa", "flex"):  # the fused layers (inductor kernels) captured in the graphs too
        fused = fast_generate(model, ids, mask, attention=attention, fuse=True, **common)
        assert fused.graphs and fused.fallback_reason is None and fused.tokens == eager.tokens
    half = build_scratch_model({**ARCH, "head_dim": 16}, tokenizer, seed=3, dtype="bfloat16").cuda().eval()
    cudnn = fast_generate(half, ids, mask, attention="cudnn", fuse=True, **common)
    assert cudnn.graphs and cudnn.fallback_reason is None
    assert all(len(row) == 96 or row[-1] == tokenizer.eos_token_id for row in cudnn.tokens)


@pytest.mark.parametrize("switch, rows", [
    (["--joint-anchor-pass", "off", "on"], {"fast", "fast joint"}),
    # on a CPU (float32) the uncast row trains as the default: one more row of the same SWITCHES wiring
    pytest.param(["--adapter-input-cast", "on", "off"], {"fast", "fast uncast"}, marks=pytest.mark.slow),
    (["--constrained"], {"fast"}),
    # aot_eager: the compiled passes traced without generating kernels (inductor's compile takes minutes here)
    pytest.param(["--compile-update", "off", "on"], {"fast", "fast compiled"}, marks=pytest.mark.slow)])
def test_bench_pada_times_a_setting_beside_its_default(capsys, switch, rows):
    """``--joint-anchor-pass off on``, ``--adapter-input-cast on off`` and ``--compile-update off on``: one
    row each, in turn; ``--constrained``: the row's host check, of its generation."""
    import json

    from physcene.cli import main

    assert main(["bench", "pada", "--config", "tiny", "--tokens", "8", "--steps", "1", "--caches", "fast",
                 *switch, "--json", "--set", "pada.global_batch_size=4", "pada.per_device_batch_size=2",
                 "pada.num_generations=2", "pada.compile_backend=aot_eager"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["caches"]) == rows
    compiled = [n.endswith(" compiled") for n in r["caches"]]
    assert [v["compile_update"] for v in r["caches"].values()] == compiled
    assert all(v["steps_timed"] == 1 and v["update_s"] > 0 for v in r["caches"].values())
    # a CPU trains in float32: nothing to leave uncast (on a GPU's bf16 the uncast row says True)
    assert not any(v["adapter_inputs_uncast"] for v in r["caches"].values())
    for v in r["caches"].values():  # the constraint's host check, a part of the generation's time
        check = v["host_check_s"]
        assert 0 < check < v["generate_s"] if "--constrained" in switch else check == 0.0
        if "--constrained" in switch:  # where the check went: its scans of the vocabulary, its refusals
            assert 0 <= v["constraint_scan_s"] <= check and v["vocabulary_scans"] >= 0 <= v["refused_draws"]


@pytest.mark.slow
def test_bench_pada_times_whole_steps(capsys, tmp_path):
    """``physcene bench pada`` at tiny sizes: one timed step per cache, split into its parts, and the
    profiled step's tables, its figures written beside them first."""
    import json

    from physcene.cli import main

    assert main(["bench", "pada", "--config", "tiny", "--tokens", "8", "--steps", "1", "--caches", "fast",
                 "dynamic", "--merge-adapters", "off", "on", "--json", "--profile", str(tmp_path), "--set",
                 "pada.global_batch_size=4", "pada.per_device_batch_size=2", "pada.num_generations=2"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["target"] == "pada" and r["global_batch"] == 4 and r["num_generations"] == 2
    assert set(r["caches"]) == {"fast", "fast merged", "dynamic"}  # HF generate has nothing to merge
    for cache, path in (("fast", "eager"), ("fast merged", "eager"), ("dynamic", "hf_generate")):
        v = r["caches"][cache]
        assert v["path"] == path and v["steps_timed"] == 1 and v["seconds_per_step"] > 0
        assert (v["merged_projections"] > 0) is (cache == "fast merged")  # every adapted projection
        assert v["generate_s"] > 0 and v["update_s"] == pytest.approx(
            v["seconds_per_step"] - v["generate_s"] - v["reward_s"])
        parts = v["profile"]["parts"]
        assert {"training_step", "backward", "_generate_and_score_completions"} <= set(parts)
        name = "pada_" + cache.replace(" ", "_")
        assert "Operators by cpu self time" in (tmp_path / f"{name}.txt").read_text()
        # the step's figures were written before the (slow) tables
        figures = json.loads((tmp_path / f"{name}.json").read_text())
        assert figures["seconds_per_step"] == v["seconds_per_step"]
