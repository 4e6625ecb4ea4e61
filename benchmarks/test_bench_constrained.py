"""Host cost of CTRC-constrained decoding per decoding step (train/constrained.py).

    python -m pytest benchmarks/test_bench_constrained.py --benchmark-enable -q -s

128 synthetic training completions are replayed through one :class:`CTRCConstraint` token by token
(the scores favour each row's true next token, as a model that has learned the format would), so a
round is what the processor adds to ``generate`` for a 128-row greedy batch over the first
``STEPS`` tokens. Printed: ms per step and the share of row-steps inside a constrained segment.
"""

from __future__ import annotations

import time

import torch
from physcene.train.constrained import CTRCConstraint
from physcene.train.tokenizer import build_tokenizer

from physcene.data import synthesize

ROWS, STEPS = 128, 600


def test_constrained_decoding_step_cost(benchmark):
    records = list(synthesize("train", ROWS, seed=5))
    tokenizer = build_tokenizer([r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]],
                                vocab_size=4096)
    ids = [tokenizer(r["completion"], add_special_tokens=False)["input_ids"] for r in records]
    steps = min(STEPS, min(len(i) for i in ids))
    tokens = torch.tensor([i[:steps] for i in ids])
    prompt = torch.full((ROWS, 8), tokenizer.pad_token_id)
    favourite = [torch.nn.functional.one_hot(tokens[:, k], len(tokenizer)).float() for k in range(steps)]

    def replay():
        processor = CTRCConstraint(tokenizer, [r["prompt"] for r in records])
        for k in range(steps):
            processor(torch.cat([prompt, tokens[:, :k]], 1), favourite[k])
        return processor

    processor = benchmark.pedantic(replay, rounds=3, iterations=1)
    assert processor.masked_steps == 0  # the true continuation is never refused
    start = time.perf_counter()
    replay()
    per_step = (time.perf_counter() - start) / steps
    print(f"\nCTRCConstraint: {ROWS} rows x {steps} steps, {1e3 * per_step:.2f} ms per step")
