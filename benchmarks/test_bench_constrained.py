"""Host cost of CTRC-constrained decoding per decoding step (train/constrained.py).

    python -m pytest benchmarks/test_bench_constrained.py --benchmark-enable -q -s

128 synthetic training completions are replayed whole through one :class:`CTRCConstraint` token by
token (the scores favour each row's true next token, then EOS, as a model that has learned the format
would), so a round is what the processor adds to ``generate`` for a 128-row greedy batch: the plan
(mostly free text) and the layout (almost all of it under a rule). Printed: ms per step.
"""

from __future__ import annotations

import time

import torch
from physcene.train.constrained import CTRCConstraint
from physcene.train.tokenizer import build_tokenizer

from physcene.data import synthesize

ROWS = 128


def test_constrained_decoding_step_cost(benchmark):
    records = list(synthesize("train", ROWS, seed=5))
    tokenizer = build_tokenizer([r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]],
                                vocab_size=4096)
    ids = [tokenizer(r["completion"], add_special_tokens=False)["input_ids"] for r in records]
    steps = max(len(i) for i in ids) + 1  # every row to its EOS
    eos = tokenizer.eos_token_id
    tokens = torch.tensor([i + [eos] * (steps - len(i)) for i in ids])
    prompt = torch.full((ROWS, 8), tokenizer.pad_token_id)
    rows = torch.arange(ROWS)

    def replay():
        processor = CTRCConstraint(tokenizer, [r["prompt"] for r in records])
        scores = torch.zeros(ROWS, len(tokenizer))
        for k in range(steps):
            scores.zero_()
            scores[rows, tokens[:, k]] = 1.0
            processor(torch.cat([prompt, tokens[:, :k]], 1), scores)
        return processor

    processor = benchmark.pedantic(replay, rounds=1, iterations=1)
    assert processor.masked_steps == 0  # the true continuation is never refused
    start = time.perf_counter()
    replay()
    per_step = (time.perf_counter() - start) / steps
    print(f"\nCTRCConstraint: {ROWS} rows x {steps} steps, {1e3 * per_step:.2f} ms per step")
