"""The constraint's host check over worker processes (physcene.train.decode.shards,
``pada.constraint_workers``): the same tokens and counters as the check in the decoding process,
greedy and sampled, for any number of workers; a worker's failure is one error naming it."""

from __future__ import annotations

import pytest
import torch
from transformers import GenerationConfig

from physcene.train.constrained import CTRCConstraint, sampling_warpers
from physcene.train.decode import ShardedConstraint, constraint_pool, fast_generate
from physcene.train.decode.shards import ConstraintWorkerError
from physcene.train.models import build_scratch_model

pytestmark = pytest.mark.usefixtures("one_thread")  # fixtures: tests/train/conftest.py


@pytest.fixture(scope="module")
def model(tokenizer, tiny_arch):
    return build_scratch_model(tiny_arch, tokenizer, seed=5).eval()


def _rows(records, tokenizer, n: int):
    """``n`` rows of prompts of different lengths, each followed by a record's reference plan, which
    the constraint has seen as completion: the layout is left to a model of random weights, and the
    constraint writes most of it."""
    prompts, rows, plans = [], [], []
    for k in range(n):
        r = records[k % 3]
        plan_text = r["completion"].split("**Scene Layout:**")[0]
        plan = tokenizer(plan_text, add_special_tokens=False)["input_ids"]
        prompts.append(("Note. " * k) + r["prompt"])
        rows.append(tokenizer(prompts[-1], add_special_tokens=False)["input_ids"] + plan)
        plans.append(plan)
    width = max(map(len, rows))
    ids = torch.full((n, width), tokenizer.pad_token_id)
    mask = torch.zeros((n, width), dtype=torch.long)
    for b, row in enumerate(rows):
        ids[b, width - len(row):], mask[b, width - len(row):] = torch.tensor(row), 1
    return prompts, plans, ids, mask


def _decode(model, tokenizer, rows, *, workers: int, sampling: bool, seed: int = 0):
    prompts, plans, ids, mask = rows
    warpers = sampling_warpers(GenerationConfig(do_sample=True, temperature=1.5)) if sampling else None
    constraint = CTRCConstraint(tokenizer, prompts, greedy=not sampling, warpers=warpers)
    for b, plan in enumerate(plans):
        constraint.advance_row(b, plan)
    torch.manual_seed(seed)
    result = fast_generate(model, ids, mask, max_new_tokens=96, eos=[tokenizer.eos_token_id],
                           pad=tokenizer.pad_token_id, sampling=sampling, warpers=warpers,
                           constraint=constraint, constraint_workers=workers)
    return result, constraint.stats


@pytest.mark.parametrize("sampling", [False, True])
def test_workers_write_the_tokens_of_the_single_process_check(records, tokenizer, model, sampling):
    """Five rows (uneven shares), a random model whose draws the constraint often refuses: the tokens,
    the repairs, each row's overruled positions and the counters are the same with 0, 2 and 3
    workers."""
    rows = _rows(records, tokenizer, 5)
    reference, stats = _decode(model, tokenizer, rows, workers=0, sampling=sampling)
    assert stats.masked_steps > 0  # the constraint had work to do
    if sampling:
        assert stats.refused_draws > 0
    for workers in (2, 3):
        result, shared = _decode(model, tokenizer, rows, workers=workers, sampling=sampling)
        assert result.tokens == reference.tokens
        assert result.repairs == reference.repairs
        assert shared.overruled == stats.overruled
        assert (shared.masked_steps, shared.refused_draws, shared.vocabulary_scans) == \
            (stats.masked_steps, stats.refused_draws, stats.vocabulary_scans)


def test_a_seeded_sampled_round_depends_on_the_seed_not_on_the_workers(records, tokenizer, model):
    rows = _rows(records, tokenizer, 3)
    first, _ = _decode(model, tokenizer, rows, workers=2, sampling=True, seed=1)
    again, _ = _decode(model, tokenizer, rows, workers=0, sampling=True, seed=1)
    other, _ = _decode(model, tokenizer, rows, workers=2, sampling=True, seed=2)
    assert first.tokens == again.tokens != other.tokens


def test_a_failing_worker_is_one_error_that_carries_its_traceback(records, tokenizer):
    """Workers whose constraint cannot be built (a setting they do not take) raise in the main process
    with the first one's own traceback; every reply is read, so the pool serves the next round."""
    pool = constraint_pool(tokenizer, 2)
    prompts = [r["prompt"] for r in records[:2]]
    constraint = CTRCConstraint(tokenizer, prompts)
    constraint.settings = lambda: {"no_such_setting": 1}
    with pytest.raises(ConstraintWorkerError, match="(?s)worker 0 failed.*no_such_setting"):
        ShardedConstraint(constraint, max_new_tokens=4, eos=[tokenizer.eos_token_id], pool=pool)
    working = CTRCConstraint(tokenizer, prompts)
    sharded = ShardedConstraint(working, max_new_tokens=2, eos=[tokenizer.eos_token_id], pool=pool)
    assert not sharded.done()


def test_a_pada_step_samples_its_groups_with_constraint_workers(tmp_path, records, tokenizer, tiny_arch):
    """``pada.constraint_workers`` reaches the trainer: one constrained PADA step with two workers logs
    the constraint's counters; a count below 0 is refused by name."""
    from datasets import Dataset

    from physcene.config import load_config
    from physcene.train.pada import PADAConfig, PADATrainer, pada_arguments

    cfg = load_config("train_tiny", [f"output_dir={tmp_path}", "pada.cache=fast",
                                     "pada.constraint_workers=2"])
    assert pada_arguments(cfg, "pada").constraint_workers == 2
    with pytest.raises(ValueError, match="pada.constraint_workers"):
        pada_arguments(load_config("train_tiny", [f"output_dir={tmp_path}", "pada.constraint_workers=-1"]),
                       "pada")
    args = PADAConfig(output_dir=str(tmp_path / "run"), num_generations=2, per_device_train_batch_size=2,
                      max_completion_length=12, use_cpu=True, report_to="none", beta=0.0, anchor_alpha=0.0,
                      max_steps=1, fast_decode="fast", constrained_decoding=True, constraint_workers=2,
                      logging_steps=1, save_strategy="no")
    prompts = [records[0]["prompt"][:200], records[1]["prompt"][:260]]
    trainer = PADATrainer(build_scratch_model(tiny_arch, tokenizer, seed=3),
                          reward_funcs=[lambda prompts, completions, **kw: [0.0] * len(prompts)], args=args,
                          processing_class=tokenizer,
                          train_dataset=Dataset.from_list([{"prompt": p, "anchor": ""} for p in prompts]))
    trainer.train()
    logged = {k: v for entry in trainer.state.log_history for k, v in entry.items()}
    assert logged["time/constraint_s"] > 0 and "constraint/refused_draws" in logged


def _replay_bench(tmp_path, records, tokenizer, tiny_arch, n: int):
    """``benchmarks/constraint_replay.py`` as a module, a tiny checkpoint of random weights and a
    records file of ``n`` prompts for it."""
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "constraint_replay.py"
    spec = importlib.util.spec_from_file_location("constraint_replay", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    checkpoint = tmp_path / "ckpt"
    build_scratch_model(tiny_arch, tokenizer, seed=5).save_pretrained(checkpoint)
    tokenizer.save_pretrained(checkpoint)
    data = tmp_path / "records.jsonl"
    data.write_text("".join(json.dumps(r) + "\n" for r in records[:n]))
    return bench, checkpoint, data


def test_a_recorded_round_replays_equal_with_and_without_workers(tmp_path, records, tokenizer, tiny_arch):
    """``benchmarks/constraint_replay.py``: a round sampled under the constraint is recorded (every call
    of the check) and replayed on a fresh constraint, in this process and over two workers, each call
    returning what it returned when recorded; a replay whose check decides otherwise is caught."""
    import argparse

    replay, checkpoint, data = _replay_bench(tmp_path, records, tokenizer, tiny_arch, 4)
    trace = tmp_path / "trace.pt"
    replay.record(argparse.Namespace(model=str(checkpoint), records=str(data), levels=[], n=4,
                                     max_new_tokens=48, temperature=1.0, seed=0, cache="fast", device="cpu",
                                     out=str(trace)))
    recorded = torch.load(trace, weights_only=False)
    assert len(recorded["calls"]) > 10 and recorded["seed"] is not None
    for workers in (0, 2):
        (result,) = replay.replay_rounds(str(trace), 1, workers)
        assert result["differing_calls"] == 0 and result["same_tokens"] and not result["logits_not_recorded"]
    # `profile`: the check's functions by their own time, the constraint's own among them
    profiled = replay.profile(argparse.Namespace(trace=str(trace), top=10**6, json=str(tmp_path / "p.json")))
    assert profiled["equal_to_recording"] and 0.0 <= profiled["regex_matching_share"] < 1.0
    own = [f["own_s"] for f in profiled["functions"]]
    assert own == sorted(own, reverse=True)
    # the checks alone: the constraint built before them (its __init__, the vocabulary's index) is not in it
    assert not any(f["function"].startswith("processor.py") and "__init__" in f["function"]
                   for f in profiled["functions"])
    assert any("advance_row" in f["function"] or "advance_within_rule" in f["function"]
               for f in profiled["functions"])
    call = next(c for c in recorded["calls"] if c["tokens"])
    call["tokens"][0] = (call["tokens"][0] + 1) % len(tokenizer)  # a step the check never saw
    torch.save(recorded, trace)
    (result,) = replay.replay_rounds(str(trace), 1)
    assert not result["same_tokens"]


def test_streams_samples_one_round_under_each_reads_setting(tmp_path, records, tokenizer, tiny_arch, capsys):
    """``benchmarks/constraint_replay.py streams``: the same seeded round under both places of the
    check's logits reads, rounds timed apart; on a CPU (one stream) both write the same tokens, and
    the decoder's setting is given back afterwards."""
    import argparse
    import json

    from physcene.train.decode import FastDecoder

    bench, checkpoint, data = _replay_bench(tmp_path, records, tokenizer, tiny_arch, 3)
    out = tmp_path / "streams.json"
    summary = bench.streams(argparse.Namespace(
        model=str(checkpoint), records=str(data), levels=[], n=3, max_new_tokens=24, temperature=1.0, seed=0,
        cache="fast", device="cpu", rounds=2, json=str(out)))
    assert summary["same_tokens"] and FastDecoder.reads_stream is True
    assert [len(rows) for rows in summary["rounds"].values()] == [2, 2]
    assert all(r["steps"] > 0 and r["seconds"] > 0 for rows in summary["rounds"].values() for r in rows)
    assert json.loads(out.read_text())["median"].keys() == {"own stream", "decoding stream"}
    assert "same tokens: True" in capsys.readouterr().out


def test_the_exponential_race_draws_what_multinomial_draws():
    """A refused row's fresh draw (:func:`exponential_race`) is the token ``torch.multinomial`` draws
    from the same generator state, for dense and sparse distributions (most tokens refused), and its
    frequencies are the distribution's."""
    from physcene.train.decode.overlap import exponential_race

    g = torch.Generator().manual_seed(0)
    generator, reference = torch.Generator(), torch.Generator()
    counts = torch.zeros(8)
    for trial in range(300):
        logits = torch.randn(512, generator=g) * 3.0
        if trial % 2:  # a few allowed tokens, the rest -inf (probability 0)
            keep = torch.randperm(512, generator=g)[:3]
            logits = torch.full_like(logits, float("-inf")).index_copy_(0, keep, logits[keep])
        probs = logits.softmax(-1)
        seed = 1000 + trial
        generator.manual_seed(seed)
        reference.manual_seed(seed)
        token = exponential_race(probs, generator)
        assert token == int(torch.multinomial(probs, 1, generator=reference))
        assert probs[token] > 0
    p = torch.tensor([0.4, 0.3, 0.1, 0.1, 0.05, 0.05, 0.0, 0.0])
    for seed in range(4000):
        counts[exponential_race(p, generator.manual_seed(seed))] += 1
    assert counts[6:].sum() == 0
    assert ((counts / 4000 - p).abs() <= 4 * (p * (1 - p) / 4000).sqrt() + 1e-3).all(), counts


def test_a_refused_rows_fresh_draw_runs_nothing_on_its_logits_device(records, tokenizer):
    """A sampled row whose token and copied candidates are all refused reads its logits to the host once
    (``.cpu()``) and scans, warps and draws there: on a GPU no kernel and no further wait is queued in
    the middle of the decoding steps. The row's logits are handed over as a tensor that records every
    torch call made on it, and whose ``.cpu()`` is a plain tensor, as a device's host copy is."""
    from physcene.train.decode.overlap import OverlappedConstraint

    calls: list[str] = []

    class Logits(torch.Tensor):
        @classmethod
        def __torch_function__(cls, func, types, args=(), kwargs=None):
            calls.append(getattr(func, "__name__", str(func)))
            with torch._C.DisableTorchFunctionSubclass():
                out = func(*args, **(kwargs or {}))
            # the host copy is a plain tensor (on a CPU .cpu() returns the tensor itself)
            return out.as_subclass(torch.Tensor) if calls[-1] == "cpu" else out

    r = records[0]
    cut = r["completion"].index('"relation_type":') + len('"relation_type":')
    warpers = sampling_warpers(GenerationConfig(do_sample=True, temperature=0.7, top_k=0))
    constraint = CTRCConstraint(tokenizer, [r["prompt"]], greedy=False, warpers=warpers)
    check = OverlappedConstraint(constraint, max_new_tokens=4096, eos=[tokenizer.eos_token_id],
                                 warpers=warpers)
    for t in tokenizer(r["completion"][:cut], add_special_tokens=False)["input_ids"]:
        assert check.check([t], [[-1] * 8], set(), lambda b: None) == {}  # the reference text: all kept
    rule = check.rules[0]
    refused = [t for t in range(len(tokenizer)) if not constraint.allowed_tokens(0, rule, [t])][:9]
    logits = torch.randn(len(tokenizer), generator=torch.Generator().manual_seed(0)).as_subclass(Logits)
    corrections = check.check([refused[0]], [refused[1:]], set(), lambda b: logits)
    assert calls == ["cpu"]  # the one read; everything after it ran on the host copy
    (token,) = corrections.values()
    assert constraint.allowed_tokens(0, rule, [token]) and constraint.stats.refused_draws == 8
