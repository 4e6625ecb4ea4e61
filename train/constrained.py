"""CTRC-constrained decoding: a ``LogitsProcessor`` that keeps a completion inside the CTRC grammar.

A language model writes a CTRC completion token by token; a small one (``small``: 27 M parameters,
trained from scratch) loses count of what it has placed and repeats an instance id, or writes a
number like ``10.0.141``: the whole layout then fails to parse (the 2 x H200 ablation: 79 % of test
outputs repeated an id). :class:`CTRCConstraint` masks the logits at the few places where the
format, or the prompt's **Object List**, decides what may come next, and leaves every other token
(positions, sizes, descriptions, the plan's wording) to the model:

| where (anchor in the text)          | what must follow (up to the next anchor)                      |
| ----------------------------------- | ------------------------------------------------------------- |
| plan line ``\\nN. Place``            | an id from the Object List not yet placed in the plan          |
| end of a plan line (``.``)           | ``\\nN+1. Place`` while ids are left, else the layout's start |
| ``"instance_id":``                  | ``root_zone`` first, then an id of the list not yet in the layout, |
|                                     | then the entry's next key                                     |
| ``"category":``                     | that id's category (``3_tissue_box_0`` -> ``tissue_box``)      |
| ``"parent_id":``                    | ``root_zone`` or an id placed earlier in the layout           |
| ``"relation_type":``                | ``near`` for a table-level object, else ``in`` / ``on``; then  |
|                                     | the description (free text, one JSON string)                  |
| ``"relative_bbox":`` / ``"bbox":``  | six JSON numbers (no leading zero, <= 4 integer digits), each  |
|                                     | ``relative_bbox`` max above its min; the root's ``bbox``: the  |
|                                     | prompt's **item_placement_zone** (a copy, not a choice)        |
| ``"relative_rotation_deg":``        | one number, then the next entry while ids are left, else the  |
|                                     | end of the objects array                                      |
| ``"item_placement_zone":``          | the prompt's zone (else four JSON numbers, max above min), ``}`` |
|                                     | and the end of text                                           |

Ids follow the MesaTask naming the data uses (``physcene.data.synth``): ``<index of the category in the
Object List>_<category>_<copy>``. A prompt without an Object List gets only the number grammar and the
``root_zone``/``near`` rules; one without an **item_placement_zone** leaves the zone to the model (the
2 x H200 ``small`` SFT model wrote a wrong zone in 512 of 512 anchor prompts, median 7.6 cm off: it
has not learnt to copy numbers from its prompt). The mask is the model's own distribution restricted
to what is allowed: under greedy decoding it changes nothing unless the model's first choice breaks
the format (then the best allowed token wins); under sampling the allowed tokens among the ``top_k``
most likely keep their relative probabilities.

Why not a grammar library (``xgrammar``, ``outlines``, ``lm-format-enforcer``): a JSON schema can
restrict ``instance_id`` to the listed ids, but "each id exactly once" and "a parent placed before
its child" are not context-free in any compact form, and those are what a small model gets wrong.
The rules here are a regular expression per anchor, matched with ``regex``'s partial matching
(already a transformers dependency) against the text since the anchor.
"""

from __future__ import annotations

import bisect
import functools
import json
import math
import re
import time
from collections.abc import Sequence
from typing import NamedTuple

import regex
import torch
from transformers import GenerationConfig, LogitsProcessor, LogitsProcessorList, PreTrainedTokenizerBase

from physcene.ctrc import (
    BOX_EXTENTS,
    ENTRY_SEPARATOR,
    LAYOUT_HEADER,
    MAX_DECIMALS,
    OBJECTS_CLOSE,
    OBJECTS_OPEN,
)
from physcene.layout import category_from_instance
from physcene.scene import TABLE

__all__ = ["CTRCConstraint", "Rule", "active_rule", "constraint_rule", "last_anchor", "listed_instance_ids",
           "prompt_zone", "sampling_warpers"]

_OBJECT_LIST = re.compile(r"\*\*Object List\*\*: ([^\n]*)")
_ZONE = re.compile(r"\*\*item_placement_zone\*\*: (\[[^\]\n]*\])")
_LIST_ITEM = re.compile(r"\s*([^,()]+?) \((\d+)\)")
# A JSON number the parser accepts: no leading zero (JSON); at most 4 integer digits (100 m: a
# tabletop is a few metres) keeps even a deep stack of relative offsets under MAX_ABS_CM (1e5 cm); at
# most MAX_DECIMALS (8) decimals keeps a model from writing digits forever (the data has DECIMALS = 5).
_INTEGER_DIGITS = 4
_NUMBER = rf"-?(?:0|[1-9]\d{{0,{_INTEGER_DIGITS - 1}}})(?:\.\d{{1,{MAX_DECIMALS}}})?"
_ARRAY_LENGTH = {"relative_bbox": 6, "bbox": 6, "item_placement_zone": 4}
# (min, max) index pairs of an array whose max must exceed its min (physcene.ctrc refuses a
# non-positive extent); the root's "bbox" is the zone with a zero height, so it has none.
_ORDERED = {"relative_bbox": BOX_EXTENTS, "item_placement_zone": BOX_EXTENTS[:2]}
# The key that follows each constrained key in an entry (physcene.ctrc.encode's order).
_NEXT_KEY = {"instance_id": "category", "category": "parent_id", "parent_id": "relation_type",
             "relation_type": "description", "relative_bbox": "relative_rotation_deg", "bbox": "z_rotation"}
# The last of these in the text decides the rule in force (group "key": a JSON key; "step": a plan
# step's number; "line": a finished plan line's number).
_ANCHOR = re.compile(
    r'"(?P<key>instance_id|category|parent_id|relation_type|relative_bbox|bbox|item_placement_zone|'
    r'relative_rotation_deg|z_rotation)":'
    r"|\n(?P<step>\d+)\. Place(?![^\n.]*\.)"
    r"|\n(?P<line>\d+)\. Place [^\n.]*\.")
# The completion's fixed text, as physcene.ctrc.completion_text writes it: the layout's start up to the
# root entry's instance_id; what follows an object entry's closing brace: the next entry up to its
# instance_id (whose own rule follows), or the end of the objects array up to the zone's key.
_LAYOUT_START = "\n\n" + LAYOUT_HEADER + "\n" + OBJECTS_OPEN + '{"layer": 0, "instance_id":'
_LAYER = r"[1-9]\d{0,3}"
_NEXT_ENTRY = regex.escape(ENTRY_SEPARATOR + '{"layer": ') + _LAYER + regex.escape(', "instance_id":')
_END_OF_OBJECTS = regex.escape(OBJECTS_CLOSE)
_ROOT_KEYS = ', "type": "zone", "bbox":'  # after the root's instance_id (plain text)
_DESCRIPTION = r' "(?:[^"\\\x00-\x1f]|\\(?:["\\/bfnrt]|u[0-9a-fA-F]{4})){0,300}"'  # one JSON string, one line
_TAIL = 600  # characters searched for the last anchor: longer than any constrained segment


class Rule(NamedTuple):
    """What the next tokens must continue: ``partial`` (the text since the anchor) + the new text must
    stay a prefix of ``pattern``, and numbers at ``ordered`` (min, max) positions of its JSON array
    must leave room for max > min. ``pattern`` None: the completion is finished; only EOS may follow.
    ``choices``: the rule is one of these literal strings, then anything (the next anchor's rule), or
    nothing after it when ``closed`` (the completion's last text): a prefix test stands in for
    ``pattern``, so no regex is compiled per set of ids left."""

    partial: str
    pattern: str | None
    ordered: tuple[tuple[int, int], ...] = ()
    choices: tuple[str, ...] = ()
    closed: bool = False

    def admits(self, added: str) -> bool:
        if self.pattern is None:
            return False
        text = self.partial + added
        if self.choices:
            return any(c.startswith(text) or (not self.closed and text.startswith(c)) for c in self.choices)
        if _compiled(self.pattern).fullmatch(text, partial=True) is None:
            return False
        return not self.ordered or _extents_possible(text, self.ordered)


class _Core(NamedTuple):
    pattern: str
    ordered: tuple[tuple[int, int], ...] = ()
    then_eos: bool = False  # once the pattern is complete the completion ends
    choices: tuple[str, ...] = ()  # literal alternatives instead of ``pattern`` (see Rule)

    def prefix_rule(self, partial: str) -> Rule:
        """The :class:`Rule` of this core after ``partial``: its pattern, then anything (the next
        anchor's rule takes over) unless the completion ends with it."""
        pattern = self.pattern if self.then_eos else self.pattern + r"[\s\S]*"
        return Rule(partial, pattern, self.ordered, self.choices, closed=self.then_eos)

    def complete(self, partial: str) -> int | None:
        """Where the rule's text ends if ``partial`` starts with all of it, else None."""
        if self.choices:
            return next((len(c) for c in self.choices if partial.startswith(c)), None)
        done = _compiled(self.pattern).match(partial)
        return None if done is None else done.end()


def _literal(*strings: str, then_eos: bool = False) -> _Core:
    """A rule that is one of ``strings`` (plain text, no regex), the completion's end if ``then_eos``."""
    return _Core("", then_eos=then_eos, choices=strings)


def _extents_possible(text: str, pairs) -> bool:
    """Whether the JSON number array that ``text`` starts (`` [1.5, 2``) can still end with every
    max above its min: a finished max must exceed its min, a max being written must be able to."""
    m = re.match(r"\s*\[([^\]]*)(\]?)", text)
    if m is None:
        return True
    values = [v.strip() for v in m.group(1).split(",")]
    n_done = len(values) if m.group(2) else len(values) - 1  # the last one is still being written
    for lo, hi in pairs:
        if lo == n_done == len(values) - 1 and values[lo] and not values[lo].startswith("-"):
            if float(values[lo].rstrip(".")) >= _largest(""):  # a min no max can exceed (9999.99999999)
                return False
            continue
        if lo >= n_done or hi > n_done or hi >= len(values):
            continue
        low = float(values[lo])
        if hi < n_done:
            if not float(values[hi]) > low:
                return False
        elif not _largest(values[hi]) > low:
            return False
    return True


def _largest(prefix: str) -> float:
    """The largest number of the grammar (``_NUMBER``: at most ``_INTEGER_DIGITS`` integer digits and
    ``MAX_DECIMALS`` decimals) that starts with ``prefix``. A max must be able to exceed its min by a
    number that can still be written: a least upper bound would let ``1.06386999`` (eight decimals)
    through after a min of ``1.06386999`` and leave no token that continues the box."""
    negative = prefix.startswith("-")
    digits = prefix[1:] if negative else prefix
    whole, dot, fraction = digits.partition(".")
    if negative:  # the fewest digits: "-" -> -0, "-1." -> -1.0, "-12" -> -12
        return -float(f"{whole or 0}.{fraction or 0}")
    if not dot and whole != "0":  # more integer digits may follow (none after a leading 0)
        whole += "9" * (_INTEGER_DIGITS - len(whole))
    return float(f"{whole}.{fraction}{'9' * (MAX_DECIMALS - len(fraction))}")


def listed_instance_ids(prompt: str) -> list[str] | None:
    """The instance ids a CTRC prompt's **Object List** implies, in list order; None without a list.

    ``napkin (1), vase (2)`` -> ``["1_napkin_0", "2_vase_0", "2_vase_1"]`` (MesaTask naming, spaces in
    a category become ``_``).
    """
    m = _OBJECT_LIST.search(prompt)
    if m is None:
        return None
    items = _LIST_ITEM.findall(m.group(1))
    if not items:
        return None
    return [f"{k}_{name.strip().replace(' ', '_')}_{j}" for k, (name, n) in enumerate(items, 1)
            for j in range(int(n))]


def prompt_zone(prompt: str) -> list[float] | None:
    """The prompt's **item_placement_zone** ``[xmin, xmax, ymin, ymax]`` (cm), or None without a
    well-formed one (four finite numbers, max above min)."""
    m = _ZONE.search(prompt)
    if m is None:
        return None
    try:
        zone = [float(v) for v in json.loads(m.group(1))]
    except (ValueError, TypeError):
        return None
    if len(zone) != 4 or not all(math.isfinite(v) for v in zone) or zone[1] <= zone[0] or zone[3] <= zone[2]:
        return None
    return zone


def _alternatives(strings: Sequence[str]) -> str:
    """A regex group of the literal ``strings`` (relation types; id choices are literal rules)."""
    return "(?:" + "|".join(regex.escape(s) for s in strings) + ")"


def constraint_rule(text: str, listed: Sequence[str] | None,
                    zone: Sequence[float] | None = None) -> Rule | None:
    """The :class:`Rule` the next token of a completion prefix must keep, or None. ``listed``: the
    prompt's ids (:func:`listed_instance_ids`); ``zone``: its placement zone (:func:`prompt_zone`).

    None: nothing constrains the next token (free text, a finished segment, or a prefix that already
    broke the rule: the parser will reject it; no mask can repair it).
    """
    found = last_anchor(text, listed, zone)
    return None if found is None else active_rule(text[found[0]:], found[1])


def active_rule(partial: str, core: _Core | None, within: bool = False) -> Rule | None:
    """The rule of ``core`` (from :func:`last_anchor`) while ``partial``, the text since its anchor, is
    inside it; EOS only once a rule that ends the completion is complete; else None. ``within``: the
    caller already knows ``partial`` continues the rule (its last token was checked against it)."""
    if core is None:
        return None
    end = core.complete(partial)
    if end is not None:  # the segment is complete
        return Rule(partial, None) if core.then_eos and end == len(partial) else None
    return core.prefix_rule(partial) if within or _within(partial, core) else None


def _within(partial: str, core: _Core | None) -> bool:
    """Whether ``partial``, the text since an anchor, can still continue into that anchor's rule."""
    return core is None or core.prefix_rule("").admits(partial)


def last_anchor(text: str, listed: Sequence[str] | None,
                zone: Sequence[float] | None = None) -> tuple[int, _Core | None] | None:
    """(position in ``text`` where its last anchor ends, the rule of what must follow it or None).

    None: no anchor in the last ``_TAIL`` characters. The rule stays valid until the next anchor, so
    a decoder need not look for one again until a token that can end an anchor arrives.
    """
    tail = text[-_TAIL:]
    anchors = list(_ANCHOR.finditer(tail))
    if not anchors:
        return None
    anchor = anchors[-1]
    position = len(text) - len(tail) + anchor.end()
    return position, _core(text[:position], anchor, listed, zone)


def _core(text: str, anchor, listed: Sequence[str] | None, zone: Sequence[float] | None) -> _Core | None:
    """The rule of ``anchor``, the last anchor of ``text`` (which ends with it)."""
    in_plan = LAYOUT_HEADER not in text  # the anchor lies in the plan
    key = anchor.group("key")
    if anchor.group("step") is not None or anchor.group("line") is not None:
        if not in_plan or not listed:
            return None
        placed = set(re.findall(r"\n\d+\. Place (\S+?)[ .]", text))
        left = [i for i in listed if i not in placed]
        if anchor.group("step") is not None:
            return _literal(*(f" {i}{end}" for i in left for end in " .")) if left else None
        if left:
            return _literal(f"\n{int(anchor.group('line')) + 1}. Place ")
        return _literal(_LAYOUT_START)
    if zone is not None and key in ("bbox", "item_placement_zone"):  # given by the prompt: copy it
        if key == "bbox":  # the root entry: the zone with a zero height
            return _literal(" " + _json_numbers([*zone, 0.0, 0.0]) + _key_text(_NEXT_KEY[key]))
        return _literal(" " + _json_numbers(zone) + "\n}\n", then_eos=True)
    if key in _ARRAY_LENGTH:
        n = _ARRAY_LENGTH[key]
        core = r" \[" + _NUMBER + f"(?:, {_NUMBER}){{{n - 1}}}\\]"
        if key == "item_placement_zone":  # the layout's last value: its brace, then EOS
            return _Core(core + r"\n\}\n", _ORDERED[key], then_eos=True)
        return _Core(core + _key(_NEXT_KEY[key]), _ORDERED.get(key, ()))
    if key in ("relative_rotation_deg", "z_rotation"):
        core = " " + _NUMBER + r"\}"
        if listed is not None:
            placed = set(re.findall(r'"instance_id": "([^"]*)"', text))
            core += _NEXT_ENTRY if any(i not in placed for i in listed) else _END_OF_OBJECTS
        return _Core(core)
    ids = re.findall(r'"instance_id": "([^"]*)"', text)
    follow = _key_text(_NEXT_KEY[key])
    if key == "instance_id":
        if not ids:
            return _literal(f' "{TABLE}"' + _ROOT_KEYS)
        if listed is None:
            return None
        allowed = [i for i in listed if i not in ids]
    elif key == "category":
        if not ids or ids[-1] == TABLE:
            return None
        allowed = [category_from_instance(ids[-1])]
    elif key == "parent_id":
        allowed = [TABLE, *[i for i in ids[:-1] if i != TABLE]]
    else:  # relation_type, then the free description: a regex (two patterns in all: near / in, on)
        parents = re.findall(r'"parent_id": "([^"]*)"', text)
        if not parents:
            return None
        allowed = ["near"] if parents[-1] == TABLE else ["in", "on"]
        return _Core(' "' + _alternatives(allowed) + '"' + regex.escape(follow) + _DESCRIPTION
                     + _key("relative_bbox"))
    if not allowed:
        return None
    return _literal(*(f' "{i}"' + follow for i in allowed))


def _json_numbers(values: Sequence[float]) -> str:
    """``[0.0, 132.9, ...]`` as physcene.ctrc writes a layout's numbers (JSON floats)."""
    return json.dumps([float(v) + 0.0 for v in values])


def _key_text(name: str) -> str:
    """``, "name":``: one key of an entry, after the previous value."""
    return f', "{name}":'


def _key(name: str) -> str:
    """The regex of :func:`_key_text`."""
    return regex.escape(_key_text(name))


@functools.lru_cache(maxsize=4096)
def _compiled(pattern: str):
    return regex.compile(pattern)


_UNSET = object()


_STEP_LINE = re.compile(r"\n\d+\. Place")


def _may_end_anchor(text: str, added: str) -> bool:
    """Whether appending ``added`` to ``text`` can complete an anchor: a key's ``":``, a plan step's
    ``Place`` (also one split over tokens), or the ``.`` that ends a plan line: only on a line that
    starts ``N. Place``, so a layout's decimal points (most of its ``.``) start no search."""
    if ":" in added or "Place" in text[-5:] + added or "\n" in added:
        return True
    dot = added.find(".")
    if dot < 0:
        return False
    line = text.rfind("\n", 0, len(text) + dot)
    return line >= 0 and _STEP_LINE.match(text, line) is not None


class CTRCConstraint(LogitsProcessor):
    """Restrict each row's next token to what keeps its completion a valid CTRC prefix (module docstring).

    ``prompts``: the CTRC prompt of every row of the batch, in batch order (their Object Lists give the
    ids). Pass one instance per ``generate`` call: it keeps each row's text between steps.
    ``top_k``: candidates checked per constrained row (the full vocabulary when none of them is allowed).
    ``greedy``: only the best token matters, so a row whose first choice is allowed is left as it is.
    ``margin``: sampling checks only the candidates whose score is within ``margin`` of the row's best
    (12: a probability ratio of 6e-6, so the mass left out is negligible), which keeps the regex work
    per step near one check per row where the model is sure of its next token, as it mostly is.
    ``warpers``: for sampling, the warpers ``generate`` applies after this processor (temperature,
    top-k, top-p, min-p: :func:`sampling_warpers`). Given, each row's token is drawn here by rejection
    (:meth:`_draw`): an exact sample of the allowed part of the distribution at about one check per
    row and step, instead of checking every candidate within ``margin``; ``redraws`` tokens of the
    draw are checked before the whole vocabulary is.
    """

    def __init__(self, tokenizer: PreTrainedTokenizerBase, prompts: Sequence[str], *, top_k: int = 32,
                 greedy: bool = True, margin: float = 12.0, warpers: LogitsProcessorList | None = None,
                 redraws: int = 8):
        self.token_index = _vocabulary(tokenizer)
        self.token_text = self.token_index.texts
        self.eos = tokenizer.eos_token_id
        self.listed = [listed_instance_ids(p) for p in prompts]
        self.zones = [prompt_zone(p) for p in prompts]
        self.texts = [""] * len(prompts)
        # each row's last anchor (position, rule regex): looked for again only when a token that can
        # end an anchor arrives (_may_end_anchor), so a step costs O(1) regex work per row
        self.anchors: list = [_UNSET] * len(prompts)
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
        self.masked_steps = 0  # rows x steps where the model's choice (greedy) or draw was overruled
        # each row's completion positions where the token is the constraint's, not the model's: its
        # first choice (greedy) or draw was refused, or (sampling without warpers) a likely candidate
        # was masked. PADA leaves them out of the policy loss, like tool output (pada.mask_overruled).
        self.overruled: list[list[int]] = [[] for _ in prompts]
        self.refused_draws = 0  # sampling by rejection (warpers): drawn tokens refused
        self.seconds = 0.0  # host time spent in __call__ (the constraint's cost inside generate)
        # of self.seconds, on a GPU: the wait for the step's forward to finish, which the first read
        # of the device's tensors does in any case; the rest is the constraint's host work
        self.wait_seconds = 0.0
        self.vocabulary_scans = 0  # rows whose allowed set was looked for in the whole vocabulary
        self.scan_seconds = 0.0  # of self.seconds, the time in those scans (one check per token)
        self.indexed_scans = 0  # of the scans, those of a literal rule: only the tokens that fit its text

    def _allowed(self, row: int, rule: Rule | None, candidates) -> list[int]:
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
        if not _may_end_anchor(text, added):
            return True
        full = text + added
        found = last_anchor(full, self.listed[row], self.zones[row])
        self.ahead[row][added] = found
        if found is None or found[0] <= len(text):  # no anchor ends inside the new token
            return True
        position, core = found
        return _within(full[position:], core)

    def __call__(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        start = time.perf_counter()
        if scores.is_cuda:  # the rows' texts are read on the host anyway: wait for this step's forward
            torch.cuda.current_stream(scores.device).synchronize()  # here, and count it apart
            self.wait_seconds += time.perf_counter() - start
        try:
            return self._restrict(input_ids, scores)
        finally:
            self.seconds += time.perf_counter() - start

    def _restrict(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        rules = self._advance(input_ids)
        if not rules:
            return scores
        if self.warpers is not None:
            return self._draw(rules, input_ids, scores)
        keep: dict[int, list[int]] = {}
        rows = list(rules)
        if self.greedy:  # only rows whose first choice breaks their rule need more candidates
            best = scores.argmax(dim=-1).tolist()
            rows = [b for b in rows if not self._allowed(b, rules[b], [best[b]])]
        if rows:
            k = min(self.top_k, scores.shape[-1])
            values, top = scores[rows].float().topk(k, dim=-1)
            values, top = values.tolist(), top.tolist()
            for b, candidates, v in zip(rows, top, values):
                floor = v[0] - self.margin if not self.greedy else -math.inf
                candidates = [t for t, x in zip(candidates, v) if x > floor]
                allowed = self._allowed(b, rules[b], candidates)
                if rules[b] is None and not self.greedy and len(allowed) == len(candidates):
                    continue  # sampling in free text: every likely candidate is fine
                # greedy: the first choice broke the rule; sampling: a likely candidate is refused
                overruled = self.greedy or len(allowed) < len(candidates)
                if not allowed:
                    allowed = self._allowed_in_vocabulary(b, rules[b], scores)
                if allowed:  # else: nothing in the vocabulary continues the rule; leave it to the parser
                    keep[b] = allowed
                    if overruled:
                        self.overruled[b].append(self.seen)
        if not keep:
            return scores
        self.masked_steps += len(keep)
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
            added = ""
            for t in ids:
                if t == self.eos:
                    self.finished[b] = True
                    break
                added += self.token_text[t]
            if self.finished[b]:
                continue
            searched = self.anchors[b] is _UNSET or _may_end_anchor(self.texts[b], added)
            self.texts[b] += added
            admitted, self.admitted[b] = self.admitted[b], set()
            ahead, self.ahead[b] = self.ahead[b], {}
            if searched:
                found = ahead.get(added, _UNSET)
                self.anchors[b] = (last_anchor(self.texts[b], self.listed[b], self.zones[b])
                                   if found is _UNSET else found)
            found = self.anchors[b]
            if found is None:
                rules[b] = None
            else:
                partial = self.texts[b][found[0]:]
                rules[b] = active_rule(partial, found[1], within=not searched and partial in admitted)
        return rules

    def _allowed_in_vocabulary(self, row: int, rule: Rule | None, scores: torch.Tensor,
                               finite_row: torch.Tensor | None = None) -> list[int]:
        """The allowed tokens of the whole vocabulary, less what other processors ruled out (-inf;
        ``finite_row``: the row's finite mask already on the host, else it is copied here).
        Under a literal rule (a copied zone, an id, the layout's start: where a small model that will
        not copy exhausts its draws) only the tokens whose text fits one of its strings are checked
        (:meth:`_TokenIndex.literal_candidates`: the same allowed set, from ~10 checks instead of one
        per token of the vocabulary)."""
        start = time.perf_counter()
        if finite_row is None:
            finite_row = torch.isfinite(scores[row]).cpu()
        candidates = self.token_index.literal_candidates(rule)
        if candidates is None:
            finite = finite_row.nonzero().flatten().tolist()
        else:
            self.indexed_scans += 1
            kept = finite_row[candidates].tolist() if candidates else []
            finite = [t for t, ok in zip(candidates, kept) if ok]
        allowed = self._allowed(row, rule, finite)
        self.vocabulary_scans += 1
        self.scan_seconds += time.perf_counter() - start
        return allowed

    def _draw(self, rules: dict[int, Rule | None], input_ids: torch.LongTensor,
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
            warped = self.warpers(input_ids, scores.float())
        else:
            index = torch.tensor(rows).to(scores.device, non_blocking=True)
            warped = self.warpers(input_ids[index], scores[index].float())
        uniform = torch.rand_like(warped).clamp_(min=torch.finfo(warped.dtype).tiny)
        gumbel = -(-uniform.log()).log()  # Gumbel(0, 1)
        k = min(self.redraws, warped.shape[-1])
        order = (warped + gumbel).topk(k, dim=-1).indices.tolist()
        chosen_rows, chosen_tokens, exhausted = [], [], []
        for b, tokens in zip(rows, order):
            for n, t in enumerate(tokens):
                if self._allowed(b, rules[b], [t]):
                    if n:
                        self.masked_steps += 1
                        self.refused_draws += n
                        self.overruled[b].append(self.seen)
                    chosen_rows.append(b)
                    chosen_tokens.append(t)
                    break
            else:
                self.masked_steps += 1
                self.refused_draws += k
                self.overruled[b].append(self.seen)
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
            allowed = self._allowed_in_vocabulary(b, rules[b], scores, finite_row)
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


class _TokenIndex:
    """The vocabulary's token texts by text and in sorted order, to find the tokens that fit a
    literal rule without checking every token."""

    def __init__(self, texts: list[str]):
        self.texts = texts  # by token id
        self.by_text: dict[str, list[int]] = {}
        for t, text in enumerate(texts):
            if text:  # special tokens ("") fit no rule
                self.by_text.setdefault(text, []).append(t)
        self.sorted = sorted(self.by_text)
        self.longest = max(map(len, self.sorted), default=0)

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
                    return None  # past the choice already: the rule admits any text
                continue
            rest = choice[len(rule.partial):]
            if not rest:
                return None
            out.update(self.prefixes_of(rest))
            if not rule.closed:
                out.update(self.starting_with(rest))
        return sorted(out)


def _vocabulary(tokenizer: PreTrainedTokenizerBase) -> _TokenIndex:
    """The :class:`_TokenIndex` of the tokenizer's token texts ("" for special tokens, which no rule
    allows), built once per vocabulary."""
    key = (type(tokenizer).__name__, getattr(tokenizer, "name_or_path", ""), len(tokenizer))
    cached = _VOCABULARIES.get(key)
    if cached is None:
        special = set(tokenizer.all_special_ids)
        texts = ["" if i in special else tokenizer.decode([i]) for i in range(len(tokenizer))]
        cached = _VOCABULARIES[key] = _TokenIndex(texts)
    return cached


_VOCABULARIES: dict[tuple, _TokenIndex] = {}
