"""Sampling under the CTRC constraint: the warpers ``generate`` applies, the vocabulary's token index,
and the rejection draw that samples exactly the allowed part of the warped distribution."""

from __future__ import annotations

import bisect
import functools
import os
import weakref

import torch
from transformers import GenerationConfig, LogitsProcessorList, PreTrainedTokenizerBase

from physcene.train.constrained.grammar import Rule, _compiled, token_may_end_anchor

__all__ = ["TokenIndex", "rejection_draw", "sampling_warpers", "vocabulary"]


def rejection_draw(constraint, rules: dict[int, Rule | None], input_ids: torch.LongTensor,
                   scores: torch.FloatTensor) -> torch.FloatTensor:
    """Sampling by rejection: each unfinished row's tokens in the order of one draw without
    replacement from its warped distribution (Gumbel-top-k: the warped scores plus Gumbel noise,
    sorted), checked in that order; the first allowed one is exactly a sample of the distribution
    restricted to the allowed tokens, and it is mostly the first, so a row costs about one check.
    A row whose ``redraws`` first tokens are all refused samples afresh among the allowed tokens
    of the whole vocabulary. Each row comes back with only its chosen token(s) finite, so the
    sampler that follows picks it."""
    rows = list(rules)
    if len(rows) == scores.shape[0]:  # no row finished yet: no gather
        warped = constraint.warpers(input_ids, scores.float())
    else:
        index = torch.tensor(rows).to(scores.device, non_blocking=True)
        warped = constraint.warpers(input_ids[index], scores[index].float())
    uniform = torch.rand_like(warped).clamp_(min=torch.finfo(warped.dtype).tiny)
    gumbel = -(-uniform.log()).log()  # Gumbel(0, 1)
    k = min(constraint.redraws, warped.shape[-1])
    order = (warped + gumbel).topk(k, dim=-1).indices.tolist()
    chosen_rows, chosen_tokens, exhausted = [], [], []
    for b, tokens in zip(rows, order):
        for n, t in enumerate(tokens):
            if constraint.allowed_tokens(b, rules[b], [t]):
                if n:
                    constraint.stats.masked_steps += 1
                    constraint.stats.refused_draws += n
                    constraint.stats.overruled[b].append(constraint.seen)
                chosen_rows.append(b)
                chosen_tokens.append(t)
                break
        else:
            constraint.stats.masked_steps += 1
            constraint.stats.refused_draws += k
            constraint.stats.overruled[b].append(constraint.seen)
            exhausted.append(b)
    out = torch.full_like(scores, float("-inf"))
    done = [b for b in range(scores.shape[0]) if b not in rules]  # finished rows: as they were
    if done:
        out[done] = scores[done]
    if chosen_rows:  # one host-to-device copy of the (row, token) pairs
        chosen = tuple(torch.tensor([chosen_rows, chosen_tokens]).to(scores.device, non_blocking=True))
        out[chosen] = scores[chosen]
    # one device-to-host copy of their finite masks, not a sync per row
    finite = torch.isfinite(scores[exhausted]).cpu() if exhausted else []
    for b, finite_row in zip(exhausted, finite):
        allowed = constraint.allowed_in_vocabulary(b, rules[b], scores, finite_row)
        if allowed:
            out[b, allowed] = scores[b, allowed]
        else:  # nothing continues the rule: leave the row as it was, to the parser
            out[b] = scores[b]
    return out



def sampling_warpers(config: GenerationConfig) -> LogitsProcessorList | None:
    """The warpers ``generate`` applies after the logits processors when ``config`` samples
    (temperature, top-k, top-p, min-p, in transformers' order), for :class:`CTRCConstraint`'s draws;
    None when ``config`` is greedy or uses a warper not rebuilt here (typical-p, epsilon, eta, top-h:
    the constraint then checks candidates within its margin instead)."""
    from transformers.generation.logits_process import (
        MinPLogitsWarper,
        TemperatureLogitsWarper,
        TopKLogitsWarper,
        TopPLogitsWarper,
    )

    if not config.do_sample or (config.num_beams or 1) > 1:
        return None
    if ((config.typical_p is not None and config.typical_p < 1.0) or config.epsilon_cutoff
            or config.eta_cutoff or getattr(config, "top_h", None) is not None):
        return None
    warpers = LogitsProcessorList()
    if config.temperature is not None and config.temperature != 1.0:
        warpers.append(TemperatureLogitsWarper(config.temperature))
    if config.top_k is not None and config.top_k != 0:
        warpers.append(TopKLogitsWarper(top_k=config.top_k))
    if config.top_p is not None and config.top_p < 1.0:
        warpers.append(TopPLogitsWarper(top_p=config.top_p))
    if config.min_p is not None:
        warpers.append(MinPLogitsWarper(min_p=config.min_p))
    return warpers


class TokenIndex:
    """The vocabulary's token texts by text, in sorted order and as a trie, to find the tokens that fit
    a rule without checking every token of the vocabulary."""

    def __init__(self, texts: list[str]):
        self.texts = texts  # by token id
        # whether a token's text may end an anchor after some text (may_end_anchor); another only
        # after a text that ends with "Place"
        self.may_end = [token_may_end_anchor(text) for text in texts]
        self.by_text: dict[str, list[int]] = {}
        for t, text in enumerate(texts):
            if text:  # special tokens ("") fit no rule
                self.by_text.setdefault(text, []).append(t)
        self.sorted = sorted(self.by_text)
        self.longest = max(map(len, self.sorted), default=0)
        # The compressed trie in preorder: its nodes are the texts and the branch points (the common
        # prefix of two texts next in sorted order); sorted, each node's subtree is the run of nodes
        # after it that start with it, and ``past[i]`` is the first node after node i's subtree.
        branches = {os.path.commonprefix(pair) for pair in zip(self.sorted, self.sorted[1:])}
        self.trie = sorted(branches.union(self.sorted) - {""})
        self.past = [len(self.trie)] * len(self.trie)
        path: list[int] = []  # the nodes above the current one
        for i, prefix in enumerate(self.trie):
            while path and not prefix.startswith(self.trie[path[-1]]):
                self.past[path.pop()] = i
            path.append(i)
        # many rows share a rule's pattern and text so far (a number array's start, a key), and a
        # row that exhausts its draws mostly does so again at its next step
        self.regex_candidates = functools.lru_cache(maxsize=1024)(self._regex_candidates)

    def prefixes_of(self, text: str) -> list[int]:
        """The tokens whose text is a non-empty prefix of ``text``."""
        return [t for n in range(1, min(len(text), self.longest) + 1) for t in self.by_text.get(text[:n], ())]

    def starting_with(self, text: str) -> list[int]:
        """The tokens whose text starts with ``text`` (non-empty)."""
        out = []
        for i in range(bisect.bisect_left(self.sorted, text), len(self.sorted)):
            if not self.sorted[i].startswith(text):
                break
            out.extend(self.by_text[self.sorted[i]])
        return out

    def literal_candidates(self, rule: Rule | None) -> list[int] | None:
        """A superset of the tokens that :meth:`Rule.admits` under the literal ``rule`` (``choices``):
        those whose text is a prefix of what is left of a choice, or (unless the rule is ``closed``)
        runs past its end; None where the rule is not literal or any token may fit."""
        if rule is None or rule.pattern is None or not rule.choices:
            return None
        out: set[int] = set()
        for choice in rule.choices:
            if not choice.startswith(rule.partial):
                if not rule.closed and rule.partial.startswith(choice):
                    after = rule.after_choice()
                    if after is None:
                        return None  # past the choice already: the rule admits any text
                    out.update(self.regex_candidates(rule.partial[len(choice):], after).tolist())
                continue
            rest = choice[len(rule.partial):]
            if not rest:
                return None
            out.update(self.prefixes_of(rest))
            if not rule.closed:
                out.update(self.starting_with(rest))
        return sorted(out)

    def _regex_candidates(self, partial: str, pattern: str) -> torch.Tensor:
        """The tokens (ascending ids) whose text the regex rule ``Rule(partial, pattern)`` can still
        continue with (its pattern alone, without the ordered extents :meth:`Rule.admits` adds).
        A walk of the trie: a node whose prefix the pattern cannot continue prunes its whole subtree,
        exactly, as no longer text can continue a partial match that failed. Under a number's or a
        relation's rule that is ~140 checks (mostly the single characters the pattern refuses at once)
        instead of one per token (1,314 in the 4,096-token BPE of the benchmark's 32 records)."""
        fits = _compiled(pattern).fullmatch
        trie, past, out = self.trie, self.past, []
        i = 0
        while i < len(trie):
            if fits(partial + trie[i], partial=True) is None:
                i = past[i]
            else:
                out.extend(self.by_text.get(trie[i], ()))
                i += 1
        return torch.tensor(sorted(out), dtype=torch.long)


def vocabulary(tokenizer: PreTrainedTokenizerBase) -> TokenIndex:
    """The :class:`TokenIndex` of the tokenizer's token texts ("" for special tokens, which no rule
    allows), built once per tokenizer object (two tokenizers trained in one process have no path and
    may have the same size, yet different vocabularies) and again when its size changes."""
    cached = _VOCABULARIES.get(tokenizer)
    if cached is None or len(cached.texts) != len(tokenizer):
        special = set(tokenizer.all_special_ids)
        texts = ["" if i in special else tokenizer.decode([i]) for i in range(len(tokenizer))]
        cached = _VOCABULARIES[tokenizer] = TokenIndex(texts)
    return cached


_VOCABULARIES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
