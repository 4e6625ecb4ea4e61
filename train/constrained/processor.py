"""The CTRC constraint as a transformers ``LogitsProcessor``: each row's text, its rule in force, and
the mask (or, when sampling, the draw) that keeps the row inside it. Its counters are one
:class:`ConstraintStats`."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from transformers import LogitsProcessor, LogitsProcessorList, PreTrainedTokenizerBase

from physcene.ctrc.grammar import PLACE
from physcene.train.constrained.grammar import (
    Rule,
    active_rule,
    anchor_core,
    entered_rule,
    find_anchor,
    last_anchor,
    listed_instance_ids,
    may_end_anchor,
    prompt_zone,
    within_rule,
)
from physcene.train.constrained.sampling import rejection_draw, vocabulary

__all__ = ["CTRCConstraint", "ConstraintStats"]

_UNSET = object()  # a row whose last anchor was never looked for


@dataclass
class ConstraintStats:
    """What a :class:`CTRCConstraint` did inside one ``generate`` call (PADA logs them per round)."""

    masked_steps: int = 0
    """Rows x steps where the model's choice (greedy) or draw was overruled."""
    overruled: list[list[int]] = field(default_factory=list)
    """Each row's completion positions where the token is the constraint's, not the model's: its
    first choice (greedy) or draw was refused, or (sampling without warpers) a likely candidate was
    masked. PADA leaves them out of the policy loss, like tool output (pada.mask_overruled)."""
    refused_draws: int = 0
    """Sampling by rejection (warpers): drawn tokens refused."""
    seconds: float = 0.0
    """Host time spent in ``__call__`` (the constraint's cost inside generate), s."""
    wait_seconds: float = 0.0
    """Of ``seconds``, on a GPU: the wait for the step's forward to finish, which the first read of the
    device's tensors does in any case; the rest is the constraint's host work, s."""
    vocabulary_scans: int = 0
    """Rows whose allowed set was looked for in the whole vocabulary."""
    scan_seconds: float = 0.0
    """Of ``seconds``, the time in those scans (one check per token), s."""
    indexed_scans: int = 0
    """Of the scans, those of a literal rule: only the tokens that fit its text."""
    trie_scans: int = 0
    """Of the scans, those of a regex rule through the vocabulary's trie (:attr:`CTRCConstraint.scan`)."""


class CTRCConstraint(LogitsProcessor):
    """Restrict each row's next token to what keeps its completion a valid CTRC prefix (the rules:
    :mod:`physcene.train.constrained`).

    ``prompts``: the CTRC prompt of every row of the batch, in batch order (their Object Lists give the
    ids). Pass one instance per ``generate`` call: it keeps each row's text between steps.
    ``top_k``: candidates checked per constrained row (the full vocabulary when none of them is allowed).
    ``greedy``: only the best token matters, so a row whose first choice is allowed is left as it is.
    ``margin``: sampling checks only the candidates whose score is within ``margin`` of the row's best
    (12: a probability ratio of 6e-6, so the mass left out is negligible), which keeps the regex work
    per step near one check per row where the model is sure of its next token, as it mostly is.
    ``warpers``: for sampling, the warpers ``generate`` applies after this processor (temperature,
    top-k, top-p, min-p: :func:`~physcene.train.constrained.sampling.sampling_warpers`). Given, each
    row's token is drawn here by rejection (:func:`~physcene.train.constrained.sampling.rejection_draw`):
    an exact sample of the allowed part of the distribution at about one check per row and step,
    instead of checking every candidate within ``margin``; ``redraws`` tokens of the
    draw are checked before the whole vocabulary is. ``follow_plan``: the layout writes the objects in
    the order of the completion's own plan, each under the parent and with the relation its step names
    (:func:`~physcene.train.constrained.grammar.planned_entries`); False leaves order and parents to the
    model within the list's ids and the earlier entries.
    """

    def __init__(self, tokenizer: PreTrainedTokenizerBase, prompts: Sequence[str], *, top_k: int = 32,
                 greedy: bool = True, margin: float = 12.0, warpers: LogitsProcessorList | None = None,
                 redraws: int = 8, follow_plan: bool = True):
        self.tokenizer = tokenizer
        self.prompts = list(prompts)
        self.token_index = vocabulary(tokenizer)
        self.token_text = self.token_index.texts
        self.may_end = self.token_index.may_end  # per token: whether it may end an anchor
        self.eos = tokenizer.eos_token_id
        self.listed = [listed_instance_ids(p) for p in prompts]
        self.zones = [prompt_zone(p) for p in prompts]
        self.follow_plan = bool(follow_plan)
        self.texts = [""] * len(prompts)
        # each row's last anchor (position, rule regex): looked for again only when a token that can
        # end an anchor arrives (_may_end_anchor), so a step costs O(1) regex work per row
        self.anchors: list = [_UNSET] * len(prompts)
        # each row's anchor in force as (position, match groups) where the short step found it: a search
        # that finds it again reuses its rule (None: found by the general step, not kept)
        self.anchor_keys: list = [None] * len(prompts)
        # each row's texts since its anchor that the last step found inside the anchor's rule (the
        # tokens it allowed): the next step need not match the rule again for the one that came
        self.admitted: list[set[str]] = [set() for _ in prompts]
        # each row's last anchors of text + token, found by the last step's check of a token that can
        # end an anchor: the next step takes the one for the token that came instead of searching again
        self.ahead: list[dict[str, tuple | None]] = [{} for _ in prompts]
        self.seen = 0  # completion tokens consumed (all rows advance together)
        self.finished = [False] * len(prompts)
        self.top_k = int(top_k)
        self.greedy = bool(greedy)
        self.margin = float(margin)
        self.prompt_length: int | None = None
        self.warpers = None if greedy else warpers
        self.redraws = int(redraws)
        self.stats = ConstraintStats(overruled=[[] for _ in prompts])

    def settings(self) -> dict:
        """The keyword arguments that build a constraint of the same rules for other prompts (a worker
        process's share of the rows: :mod:`physcene.train.decode.shards`)."""
        return {"top_k": self.top_k, "greedy": self.greedy, "margin": self.margin, "warpers": self.warpers,
                "redraws": self.redraws, "follow_plan": self.follow_plan}

    def allowed_tokens(self, row: int, rule: Rule | None, candidates) -> list[int]:
        """The ``candidates`` that keep ``row`` inside its ``rule`` (None: free text) and inside the
        rule of any anchor the token itself completes (a token like ``":**`` ends a key and breaks its
        value in one step; checking only the old rule would let the value run free)."""
        if rule is not None and rule.pattern is None:  # the completion is finished: EOS only
            return [t for t in candidates if t == self.eos]
        texts = self.token_text
        out = []
        for t in candidates:
            added = texts[t]
            if rule is None:
                if not added:  # EOS or a special token in free text: the model's choice
                    out.append(t)
                    continue
            elif not added or not rule.admits(added):
                continue
            if self._next_rule_holds(row, added):
                out.append(t)
                if rule is not None:
                    self.admitted[row].add(rule.partial + added)
        return out

    def _next_rule_holds(self, row: int, added: str) -> bool:
        text = self.texts[row]
        if not may_end_anchor(text, added):
            return True
        full = text + added
        found = last_anchor(full, self.listed[row], self.zones[row], self.follow_plan)
        self.ahead[row][added] = found
        if found is None or found[0] <= len(text):  # no anchor ends inside the new token
            return True
        position, core = found
        return within_rule(full[position:], core)

    def __call__(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        start = time.perf_counter()
        if scores.is_cuda:  # the rows' texts are read on the host anyway: wait for this step's forward
            torch.cuda.current_stream(scores.device).synchronize()  # here, and count it apart
            self.stats.wait_seconds += time.perf_counter() - start
        try:
            return self._restrict(input_ids, scores)
        finally:
            self.stats.seconds += time.perf_counter() - start

    def _restrict(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        rules = self._advance(input_ids)
        if not rules:
            return scores
        if self.warpers is not None:
            return rejection_draw(self, rules, input_ids, scores)
        keep: dict[int, list[int]] = {}
        rows = list(rules)
        if self.greedy:  # only rows whose first choice breaks their rule need more candidates
            best = scores.argmax(dim=-1).tolist()
            rows = [b for b in rows if not self.allowed_tokens(b, rules[b], [best[b]])]
        if rows:
            k = min(self.top_k, scores.shape[-1])
            values, top = scores[rows].float().topk(k, dim=-1)
            values, top = values.tolist(), top.tolist()
            for b, candidates, v in zip(rows, top, values):
                floor = v[0] - self.margin if not self.greedy else -math.inf
                candidates = [t for t, x in zip(candidates, v) if x > floor]
                allowed = self.allowed_tokens(b, rules[b], candidates)
                if rules[b] is None and not self.greedy and len(allowed) == len(candidates):
                    continue  # sampling in free text: every likely candidate is fine
                # greedy: the first choice broke the rule; sampling: a likely candidate is refused
                overruled = self.greedy or len(allowed) < len(candidates)
                if not allowed:
                    allowed = self.allowed_in_vocabulary(b, rules[b], scores)
                if allowed:  # else: nothing in the vocabulary continues the rule; leave it to the parser
                    keep[b] = allowed
                    if overruled:
                        self.stats.overruled[b].append(self.seen)
        if not keep:
            return scores
        self.stats.masked_steps += len(keep)
        mask = torch.zeros(scores.shape, dtype=torch.bool)  # True: masked out
        for b, allowed in keep.items():
            mask[b] = True
            mask[b, allowed] = False
        return scores.masked_fill(mask.to(scores.device), float("-inf"))

    def _advance(self, input_ids: torch.LongTensor) -> dict[int, Rule | None]:
        """Append each row's new tokens to its text; the rule in force for every unfinished row
        (None: free text)."""
        if self.prompt_length is None:
            self.prompt_length = input_ids.shape[1]
        if input_ids.shape[0] != len(self.texts):
            raise ValueError(f"CTRCConstraint built for {len(self.texts)} prompts, got a batch of "
                             f"{input_ids.shape[0]} rows")
        # Only the columns not seen yet (one per decoding step): converting the whole history every
        # step would cost O(length) per step.
        new = input_ids[:, self.prompt_length + self.seen:].tolist()
        self.seen = input_ids.shape[1] - self.prompt_length
        rules: dict[int, Rule | None] = {}
        for b, ids in enumerate(new):
            if self.finished[b]:
                continue
            rule = self.advance_row(b, ids)
            if not self.finished[b]:
                rules[b] = rule
        return rules

    def advance_free_text(self, b: int, token: int) -> bool:
        """The common step of a row in free text (no anchor in force): when ``token`` is not EOS and
        cannot end an anchor, it is allowed and appended here (True; the row stays in free text) at
        one anchor test instead of :meth:`allowed_tokens` + :meth:`advance_row`; else False."""
        if self.anchors[b] is not None or token == self.eos:
            return False
        added = self.token_text[token]
        if added and may_end_anchor(self.texts[b], added):
            return False
        self._append(b, added)
        return True

    def _append(self, b: int, added: str) -> None:
        """Append ``added`` to row ``b``'s text without an anchor search (the caller keeps or sets the
        row's anchor): the last step's look-ahead and admitted texts no longer apply."""
        self.texts[b] += added
        if self.admitted[b]:
            self.admitted[b] = set()
        if self.ahead[b]:
            self.ahead[b] = {}

    def advance_within_rule(self, b: int, rule: Rule, token: int) -> Rule | None | bool:
        """The common step of a row under a rule: when ``rule`` admits ``token`` and the token cannot
        end an anchor, it is appended here and the rule then in force returned (None: the rule's text
        is complete, free text follows), at one partial match instead of :meth:`allowed_tokens` +
        :meth:`advance_row`, which come to the same rule; a token that may end an anchor at one anchor
        search (:meth:`_advance_across_anchor`); else False (nothing changed: the caller takes the
        general path, which also counts and repairs a refusal)."""
        added = self.token_text[token]
        if rule.pattern is None or not added or token == self.eos:
            return False
        if self.may_end[token] or self.texts[b].endswith(PLACE):
            if may_end_anchor(self.texts[b], added):
                return self._advance_across_anchor(b, rule, added)
        # the rule's partial is the text since its anchor (advance_row made it so): no slice of the text
        after = rule.after(added, self.anchors[b][1])
        if after is not False:
            self._append(b, added)
        return after

    def _advance_across_anchor(self, b: int, rule: Rule, added: str) -> Rule | None | bool:
        """The step of :meth:`advance_within_rule` for a token that may end an anchor: where ``rule``
        admits it and it keeps inside the rule of any anchor it ends, it is appended and the rule then
        in force returned, at one anchor search (what :meth:`allowed_tokens` + :meth:`advance_row`
        decide with two); else False (nothing changed)."""
        if not rule.admits(added):
            return False
        text = self.texts[b]
        full = text + added
        match = find_anchor(full)
        key = None if match is None else (match[0], match[1].groups())
        if key is None:
            found = None
        elif key == self.anchor_keys[b]:  # the anchor in force: its rule is a function of the same text
            found = self.anchors[b]
        else:
            found = (match[0], anchor_core(full, match, self.listed[b], self.zones[b], self.follow_plan))
        if found is None:
            after = None
        elif found[0] > len(text):  # the token ends an anchor: its text must continue the anchor's rule
            after = entered_rule(full[found[0]:], found[1])
            if after is False:
                return False
        else:
            after = active_rule(full[found[0]:], found[1])
        self._append(b, added)
        self.anchors[b], self.anchor_keys[b] = found, key
        return after

    def advance_row(self, b: int, ids: Sequence[int]) -> Rule | None:
        """Append row ``b``'s new token ``ids`` to its text; the rule then in force (None: free text, or
        the row has just finished: ``finished[b]``). The fast decoder
        (:mod:`physcene.train.decode`) calls it per row, for the rows whose token it has accepted."""
        added = ""
        for t in ids:
            if t == self.eos:
                self.finished[b] = True
                return None
            added += self.token_text[t]
        searched = self.anchors[b] is _UNSET or may_end_anchor(self.texts[b], added)
        self.texts[b] += added
        admitted, self.admitted[b] = self.admitted[b], set()
        ahead, self.ahead[b] = self.ahead[b], {}
        if searched:
            self.anchor_keys[b] = None
            found = ahead.get(added, _UNSET)
            self.anchors[b] = (last_anchor(self.texts[b], self.listed[b], self.zones[b], self.follow_plan)
                               if found is _UNSET else found)
        found = self.anchors[b]
        if found is None:
            return None
        partial = self.texts[b][found[0]:]
        return active_rule(partial, found[1], within=not searched and partial in admitted)

    scan = "trie"
    """How :meth:`allowed_in_vocabulary` finds a regex rule's candidates: "trie" (a walk of the
    vocabulary's trie that prunes every token under a prefix the rule refuses) or "brute" (every
    token checked: the reference the benchmark compares it with)."""

    def allowed_in_vocabulary(self, row: int, rule: Rule | None, scores: torch.Tensor,
                               finite_row: torch.Tensor | None = None) -> list[int]:
        """The allowed tokens of the whole vocabulary (ascending ids), less what other processors
        ruled out (-inf; ``finite_row``: the row's finite mask already on the host, else it is copied
        here). Only the tokens that can fit the rule are checked: under a literal rule (a copied zone,
        an id, the layout's start: where a small model that will not copy exhausts its draws) those
        whose text fits one of its strings (:meth:`TokenIndex.literal_candidates`), under a regex rule
        (numbers, a relation and its description) those its pattern can continue
        (:meth:`TokenIndex.regex_candidates`, cached per pattern and text so far): the same allowed set
        as one check per token of the vocabulary, which took most of a noisy model's PADA step."""
        start = time.perf_counter()
        if finite_row is None:
            finite_row = torch.isfinite(scores[row]).cpu()
        candidates = None
        if rule is not None and rule.pattern is not None:
            if rule.choices:
                candidates = self.token_index.literal_candidates(rule)
                self.stats.indexed_scans += candidates is not None
            elif self.scan == "trie":
                candidates = self.token_index.regex_candidates(rule.partial, rule.pattern)
                self.stats.trie_scans += 1
        if candidates is None:
            finite = finite_row.nonzero().flatten().tolist()
        else:
            candidates = torch.as_tensor(candidates, dtype=torch.long)
            finite = candidates[finite_row[candidates]].tolist()
        allowed = self.allowed_tokens(row, rule, finite)
        self.stats.vocabulary_scans += 1
        self.stats.scan_seconds += time.perf_counter() - start
        return allowed
