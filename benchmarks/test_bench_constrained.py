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
- ``draw_unsure`` (a trained but imperfect model at temperature 1, as in real PADA runs): the others
  are drawn from N(-10, 2), so more than half of the mass lies off the true token; each row goes on
  with the token the processor let through (its own text, not the reference's), the first
  ``UNSURE_STEPS`` steps. Draws are often refused and rows exhaust them, so the vocabulary scans
  dominate: run with both :attr:`CTRCConstraint.scan` methods (the trie, every token checked), which
  must pick the same tokens.

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
from physcene.train.constrained.sampling import vocabulary
from physcene.train.tokenizer import build_tokenizer

MODES = {"greedy": (128, {"greedy": True}), "candidates": (64, {"greedy": False}),
         "draw": (64, {"greedy": False, "warpers": LogitsProcessorList()}),
         "draw_unsure": (64, {"greedy": False, "warpers": LogitsProcessorList()})}
UNSURE_STEPS = 600


@pytest.mark.parametrize("mode", list(MODES))
def test_constrained_decoding_step_cost(benchmark, mode):
    rows, kwargs = MODES[mode]
    records = list(synthesize("train", rows, seed=5))
    tokenizer = build_tokenizer([r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]],
                                vocab_size=4096)
    ids = [tokenizer(r["completion"], add_special_tokens=False)["input_ids"] for r in records]
    steps = max(len(i) for i in ids) + 1  # every row to its EOS
    unsure = mode == "draw_unsure"
    if unsure:
        steps = min(steps, UNSURE_STEPS)
    eos = tokenizer.eos_token_id
    tokens = torch.tensor([(i + [eos] * steps)[:steps] for i in ids])
    prompt = torch.full((rows, 8), tokenizer.pad_token_id)
    index = torch.arange(rows)
    vocab = len(tokenizer)
    greedy = kwargs["greedy"]

    def replay(scan: str = "trie"):
        constrained.grammar._compiled.cache_clear()  # cold, as for the new prompts of every PADA step
        vocabulary(tokenizer).regex_candidates.cache_clear()
        torch.manual_seed(0)
        processor = CTRCConstraint(tokenizer, [r["prompt"] for r in records], **kwargs)
        processor.scan = scan
        gen = torch.Generator().manual_seed(0)
        history = prompt
        for k in range(steps):
            if greedy:
                scores = torch.zeros(rows, vocab)
                scores[index, tokens[:, k]] = 1.0
            else:
                scores = torch.randn(rows, vocab, generator=gen) * 2.0 + (-10.0 if unsure else -18.0)
                scores[index, tokens[:, k]] = 0.0
            out = processor(history if unsure else torch.cat([prompt, tokens[:, :k]], 1), scores)
            if unsure:  # the row goes on with what the processor let through
                history = torch.cat([history, torch.multinomial(out.softmax(-1), 1, generator=gen)], 1)
        return processor, history

    processor, _ = benchmark.pedantic(replay, rounds=1, iterations=1)
    if greedy:
        assert processor.stats.masked_steps == 0  # the true continuation is never refused
    written = {}
    for scan in ("brute", "trie") if unsure else ("trie",):
        start = time.perf_counter()
        processor, written[scan] = replay(scan)
        per_step = (time.perf_counter() - start) / steps
        s = processor.stats
        print(f"\nCTRCConstraint {mode} (scan {scan}): {rows} rows x {steps} steps, {1e3 * per_step:.2f} ms "
              f"per step (of which in the processor {1e3 * s.seconds / steps:.2f}); rows x steps overruled "
              f"{s.masked_steps}; vocabulary scans {s.vocabulary_scans} ({s.indexed_scans} literal, "
              f"{s.trie_scans} trie; {1e3 * s.scan_seconds / steps:.2f} ms per step, {s.scan_seconds:.2f} s)")
    if unsure:  # the two scans allow the same tokens: the rows wrote the same text
        assert torch.equal(written["brute"], written["trie"])
