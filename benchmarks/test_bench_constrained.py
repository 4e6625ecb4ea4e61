"""Host cost of CTRC-constrained decoding per decoding step (train/constrained/).

    python -m pytest benchmarks/test_bench_constrained.py --benchmark-enable -q -s

Synthetic training completions are replayed whole through one :class:`CTRCConstraint` token by token,
so a round is what the processor adds to ``generate`` for one batch: the plan (mostly free text) and
the layout (almost all of it under a rule). Printed: ms per step, for

- ``greedy`` (anchors, evaluation; 128 rows): the scores favour each row's true next token, then EOS,
  as a model that has learned the format would;
- ``candidates`` and ``draw`` (PADA's sampling, 64 rows as one GPU's group of a 2-GPU step): the true
  token's logit is 0 and every other token's is drawn from N(-18, 2), so the true token holds ~99.9 %
  of the mass and ~5 others lie within the candidate margin of 12, as a trained model's tail does.
  ``candidates`` checks every token within the margin; ``draw`` draws one and checks it (rejection).

Each round starts with an empty cache of compiled rule patterns, as a PADA step with new prompts does.
"""

from __future__ import annotations

import time

import pytest
import torch
from transformers import LogitsProcessorList

from physcene.data import synthesize
from physcene.train import constrained
from physcene.train.constrained import CTRCConstraint
from physcene.train.tokenizer import build_tokenizer

MODES = {"greedy": (128, {"greedy": True}), "candidates": (64, {"greedy": False}),
         "draw": (64, {"greedy": False, "warpers": LogitsProcessorList()})}


@pytest.mark.parametrize("mode", list(MODES))
def test_constrained_decoding_step_cost(benchmark, mode):
    rows, kwargs = MODES[mode]
    records = list(synthesize("train", rows, seed=5))
    tokenizer = build_tokenizer([r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]],
                                vocab_size=4096)
    ids = [tokenizer(r["completion"], add_special_tokens=False)["input_ids"] for r in records]
    steps = max(len(i) for i in ids) + 1  # every row to its EOS
    eos = tokenizer.eos_token_id
    tokens = torch.tensor([i + [eos] * (steps - len(i)) for i in ids])
    prompt = torch.full((rows, 8), tokenizer.pad_token_id)
    index = torch.arange(rows)
    vocab = len(tokenizer)
    greedy = kwargs["greedy"]

    def replay():
        constrained.grammar._compiled.cache_clear()  # cold, as for the new prompts of every PADA step
        torch.manual_seed(0)
        processor = CTRCConstraint(tokenizer, [r["prompt"] for r in records], **kwargs)
        gen = torch.Generator().manual_seed(0)
        for k in range(steps):
            if greedy:
                scores = torch.zeros(rows, vocab)
                scores[index, tokens[:, k]] = 1.0
            else:
                scores = torch.randn(rows, vocab, generator=gen) * 2.0 - 18.0
                scores[index, tokens[:, k]] = 0.0
            processor(torch.cat([prompt, tokens[:, :k]], 1), scores)
        return processor

    processor = benchmark.pedantic(replay, rounds=1, iterations=1)
    if greedy:
        assert processor.stats.masked_steps == 0  # the true continuation is never refused
    start = time.perf_counter()
    processor = replay()
    per_step = (time.perf_counter() - start) / steps
    print(f"\nCTRCConstraint {mode}: {rows} rows x {steps} steps, {1e3 * per_step:.2f} ms per step "
          f"(of which in the processor {1e3 * processor.stats.seconds / steps:.2f}); rows x steps overruled "
          f"{processor.stats.masked_steps}; vocabulary scans {processor.stats.vocabulary_scans} "
          f"({1e3 * processor.stats.scan_seconds / steps:.2f} ms per step)")
