"""The CTRC constraint's host work beside the GPU: each row's token of step t checked against its rule
while the GPU computes step t + 1 (:class:`~physcene.train.decode.loop.FastDecoder`), with the
constraint's own rules and choices (:class:`~physcene.train.constrained.CTRCConstraint`).

The decisions are the processor's: greedy keeps the model's first choice when it is allowed, else
the best allowed token (of the top ``top_k``, else of the vocabulary); sampling takes the first
allowed token of one draw without replacement from the warped distribution (Gumbel-top-k, drawn on
the GPU), else samples afresh among the allowed tokens of the vocabulary (from a generator seeded by
the call's ``seed``, the row and the position: the same draw whichever process checks the row). Only
the step's token and its first candidates come to the host each step; a row's logits only when those
are all refused.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from physcene.train.constrained import CTRCConstraint

__all__ = ["OverlappedConstraint", "exponential_race"]


def exponential_race(probs: torch.Tensor, generator: torch.Generator) -> int:
    """One token drawn from ``probs`` (1-d, non-negative, not all 0): the index of the largest
    ``probs / q`` with ``q ~ Exp(1)`` drawn per token from ``generator`` (the exponential race: token
    ``i`` wins with probability ``probs[i] / sum(probs)``). It is the draw ``torch.multinomial(probs, 1,
    generator=generator)`` makes (the same random numbers, in the same order), without its checks of
    the distribution, which read three scalars back from the tensor."""
    q = torch.empty_like(probs).exponential_(1, generator=generator)
    return int(torch.div(probs, q).argmax())


class OverlappedConstraint:
    """Each row's accepted tokens under ``constraint`` (one per row and step the decoder ran for it);
    a row is done at its EOS or after ``max_new_tokens`` tokens. ``warpers``: the sampling warpers
    (None: greedy)."""

    def __init__(self, constraint: CTRCConstraint, *, max_new_tokens: int, eos: list[int], warpers=None,
                 seed: int = 0, rows: list[int] | None = None):
        self.constraint = constraint
        self.seed = int(seed)
        # each row's index in the whole batch (a worker's share of the rows: physcene.train.decode.shards)
        self.row_ids = list(range(len(constraint.texts))) if rows is None else list(rows)
        self.max_new_tokens = int(max_new_tokens)
        self.eos = set(eos) | {constraint.eos}
        self.warpers = warpers
        rows = len(constraint.texts)
        self.accepted: list[list[int]] = [[] for _ in range(rows)]
        self.finished = [False] * rows
        self.rules = [constraint.advance_row(b, []) for b in range(rows)]
        self.open = rows
        self.generator = torch.Generator()  # reseeded for each fresh draw (_redraw)

    def done(self) -> bool:
        """Every row has its EOS or its ``max_new_tokens`` tokens."""
        return self.open == 0

    def tokens(self) -> list[list[int]]:
        return [list(row) for row in self.accepted]

    def check(self, tokens: list[int], candidates: list[list[int]], skip: set[int],
              logits_row: Callable[[int], torch.Tensor]) -> dict[int, int]:
        """Accept one token per open row not in ``skip`` (rows whose step was speculative on a refused
        token): the decoder's ``tokens[b]`` when the rule allows it, else the constraint's choice
        (``candidates[b]``: the row's next best / next drawn tokens, -1 past the finite ones;
        ``logits_row(b)``: the row's logits, read only when those are refused). Returns the rows whose
        token was replaced, with their tokens."""
        start = time.perf_counter()
        stats = self.constraint.stats
        corrections: dict[int, int] = {}
        free_text, within_rule = self.constraint.advance_free_text, self.constraint.advance_within_rule
        rules, accepted, finished, longest = self.rules, self.accepted, self.finished, self.max_new_tokens
        for b, token in enumerate(tokens):
            if finished[b] or b in skip:
                continue
            rule = rules[b]
            # most rows: free text, or a token the rule in force admits (one that ends an anchor too,
            # at one anchor search); a refused one takes the general path below
            if rule is None:
                kept = free_text(b, token)
            else:
                ruled = within_rule(b, rule, token)
                kept = ruled is not False
                if kept:
                    rules[b] = ruled
            if kept:
                accepted[b].append(token)
                if len(accepted[b]) >= longest:
                    self._finish(b)
                continue
            chosen = self._choose(b, token, [t for t in candidates[b] if t >= 0], logits_row)
            if chosen != token:
                corrections[b] = chosen
            self.accepted[b].append(chosen)
            if chosen not in self.eos:
                self.rules[b] = self.constraint.advance_row(b, [chosen])
            if chosen in self.eos or len(self.accepted[b]) >= self.max_new_tokens:
                self._finish(b)
        stats.seconds += time.perf_counter() - start
        return corrections

    def _finish(self, b: int) -> None:
        self.finished[b] = True
        self.open -= 1
        self.constraint.finished[b] = True

    def _choose(self, b: int, token: int, candidates: list[int], logits_row) -> int:
        c, rule = self.constraint, self.rules[b]
        if rule is None and c.token_text[token] == "" or c.allowed_tokens(b, rule, [token]):
            return token  # the model's token (its first choice, or its draw) is allowed: most rows
        position = len(self.accepted[b])
        if self.warpers is not None:
            return self._redraw(b, token, candidates, logits_row, position)
        allowed = c.allowed_tokens(b, rule, [t for t in candidates if t != token])
        row = None
        if not allowed:
            row = logits_row(b).float()
            values, top = row.topk(min(c.top_k, row.shape[-1]))
            seen = set(candidates)
            rest = [t for t, v in zip(top.tolist(), values.tolist()) if v > float("-inf") and t not in seen]
            allowed = c.allowed_tokens(b, rule, rest)
        if not allowed:  # the row on the host once: its finite tokens, then the best allowed one
            host = row.cpu()
            allowed = c.allowed_in_vocabulary(b, rule, host[None], torch.isfinite(host))
            if allowed:  # the first of equal bests, as max() over the ascending ids
                allowed = [allowed[int(host[torch.tensor(allowed)].argmax())]]
        if not allowed:  # nothing in the vocabulary continues the rule: leave it to the parser
            return token
        c.stats.masked_steps += 1
        c.stats.overruled[b].append(position)
        return allowed[0]

    def _redraw(self, b: int, token: int, candidates: list[int], logits_row, position: int) -> int:
        """Sampling: the first allowed token of the row's draw order, else a fresh sample among the
        allowed tokens of the vocabulary (the processor's rejection draw)."""
        c, rule = self.constraint, self.rules[b]
        c.stats.masked_steps += 1
        c.stats.overruled[b].append(position)
        for n, t in enumerate([t for t in candidates if t != token][:c.redraws - 1], start=1):
            if c.allowed_tokens(b, rule, [t]):
                c.stats.refused_draws += n
                return t
        c.stats.refused_draws += min(len(candidates), c.redraws)
        # the row's logits come to the host once: the scan, the warpers and the draw run there (on a GPU
        # each would be a few launches and a wait, in the middle of the decoding steps)
        row = logits_row(b).cpu().float()
        allowed = c.allowed_in_vocabulary(b, rule, row[None], torch.isfinite(row))
        if not allowed:
            return token
        index = torch.tensor(allowed)
        restricted = torch.full_like(row, float("-inf")).index_copy_(0, index, row[index])
        probs = self.warpers(None, restricted[None])[0].softmax(dim=-1)
        # a draw of its own per (call, row, position): the same token however the rows are shared out
        self.generator.manual_seed(hash((self.seed, self.row_ids[b], position)) & (2**63 - 1))
        return exponential_race(probs, self.generator)
