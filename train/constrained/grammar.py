"""The rules of CTRC-constrained decoding: a regular expression per anchor of the completion, built
from :mod:`physcene.ctrc.grammar` (its keys, key order, number syntax, limits and the writer's
whitespace) and the prompt's **Object List** and **item_placement_zone**. The package docstring
(:mod:`physcene.train.constrained`) says what each anchor admits and why.
"""

from __future__ import annotations

import bisect
import functools
import json
import math
import re
from collections.abc import Sequence
from typing import NamedTuple

import regex

from physcene.ctrc.grammar import (
    BOX_EXTENTS,
    BOX_LENGTH,
    CATEGORY,
    CHILD_RELATIONS,
    DESCRIPTION,
    DESCRIPTION_MAX_CHARS,
    ENTRY_SEPARATOR,
    INSTANCE_ID,
    INTEGER_DIGITS,
    ITEM_SEPARATOR,
    KEY_COLON,
    KEY_SEPARATOR,
    LAYER,
    LAYER_DIGITS,
    LAYOUT_CLOSE,
    LAYOUT_HEADER,
    LAYOUT_OPEN,
    MAX_DECIMALS,
    NUMBER_PATTERN,
    OBJECTS_CLOSE,
    PARENT_ID,
    PLACE,
    PLAN_STEP_MAX_CHARS,
    RELATION_TYPE,
    RELATIVE_BBOX,
    RELATIVE_ROTATION,
    STEP_END,
    STEP_NUMBER_END,
    STEP_SEPARATOR,
    TABLE,
    TABLE_RELATION,
    TYPE,
    VALUE_SPACE,
    ZONE,
    ZONE_BBOX,
    ZONE_LENGTH,
    ZONE_ROTATION,
    ZONE_TYPE,
    child_step_pattern,
    key_text,
    next_key,
    quoted,
    step_start,
    step_start_pattern,
    string_value_pattern,
)
from physcene.ctrc.prompts import OBJECT_LIST_LABEL, ZONE_LABEL
from physcene.ctrc.writer import json_line
from physcene.layout import category_from_instance
from physcene.train.constrained.automaton import automaton

__all__ = ["ANCHOR", "PlannedEntry", "Rule", "active_rule", "anchor_core", "constraint_rule", "entered_rule",
           "find_anchor", "last_anchor", "listed_instance_ids", "may_end_anchor", "planned_entries",
           "prompt_zone", "token_may_end_anchor", "within_rule"]

_OBJECT_LIST = re.compile(re.escape(OBJECT_LIST_LABEL) + r"([^\n]*)")
_ZONE = re.compile(re.escape(ZONE_LABEL) + r"(\[[^\]\n]*\])")
_LIST_ITEM = re.compile(r"\s*([^,()]+?) \((\d+)\)")
_ARRAY_LENGTH = {RELATIVE_BBOX: BOX_LENGTH, ZONE_BBOX: BOX_LENGTH, ZONE: ZONE_LENGTH}
# (min, max) index pairs of an array whose max must exceed its min (physcene.ctrc refuses a
# non-positive extent); the root's "bbox" is the zone with a zero height, so it has none.
_ORDERED = {RELATIVE_BBOX: BOX_EXTENTS, ZONE: BOX_EXTENTS[:2]}
_ARRAY_START = re.compile(r"\s*\[([^\]]*)(\]?)")  # a JSON number array's values so far, its "]"
# The keys whose value a rule steers (the others follow from their predecessor's rule).
_CONSTRAINED_KEYS = (INSTANCE_ID, CATEGORY, PARENT_ID, RELATION_TYPE, RELATIVE_BBOX, ZONE_BBOX, ZONE,
                     RELATIVE_ROTATION, ZONE_ROTATION)
# A plan step's text runs to its first STEP_END on its line.
_STEP_REST = f"[^{re.escape(STEP_SEPARATOR + STEP_END)}]*"
# The last of these in the text decides the rule in force (group "key": a JSON key; "step": a plan
# step's number; "line": a finished plan line's number).
_STEP_START = re.escape(STEP_SEPARATOR) + step_start_pattern()  # "\n3. Place"
ANCHOR = re.compile(
    '"(?P<key>' + "|".join(map(re.escape, _CONSTRAINED_KEYS)) + ')"' + re.escape(KEY_COLON)
    + "|" + re.escape(STEP_SEPARATOR) + step_start_pattern(r"(?P<step>\d+)")
    + f"(?!{_STEP_REST}{re.escape(STEP_END)})"
    + "|" + re.escape(STEP_SEPARATOR) + step_start_pattern(r"(?P<line>\d+)") + " " + _STEP_REST
    + re.escape(STEP_END))
_STEP_ID = r" (\S+?)" + f"[ {re.escape(STEP_END)}]"  # a step's id (group 1), after its verb
_PLACED_IN_PLAN = re.compile(_STEP_START + _STEP_ID)
_STEP_LINE = re.compile(_STEP_START)
# A plan line's sentence (group 1), after its number.
_PLAN_LINE = re.compile(re.escape(STEP_SEPARATOR) + r"\d+" + re.escape(STEP_NUMBER_END) + r"([^\n]*)")
_CHILD_STEP = re.compile(child_step_pattern())
_SENTENCE_ID = re.compile(re.escape(PLACE) + _STEP_ID)
_INSTANCE_IDS = re.compile(string_value_pattern(INSTANCE_ID))
_PARENT_IDS = re.compile(string_value_pattern(PARENT_ID))
# The completion's fixed text, as physcene.ctrc.completion_text writes it: the layout's start up to the
# root entry's instance_id; what follows an object entry's closing brace: the next entry up to its
# instance_id (whose own rule follows), or the end of the objects array up to the zone's key.
_ENTRY_START = "{" + quoted(LAYER) + KEY_SEPARATOR
_LAYOUT_START = LAYOUT_OPEN + _ENTRY_START + "0" + key_text(INSTANCE_ID)
_LAYER = rf"[1-9]\d{{0,{LAYER_DIGITS - 1}}}"
_NEXT_ENTRY = regex.escape(ENTRY_SEPARATOR + _ENTRY_START) + _LAYER + regex.escape(key_text(INSTANCE_ID))
_END_OF_OBJECTS = regex.escape(OBJECTS_CLOSE)
_ROOT_KEYS = key_text(TYPE) + VALUE_SPACE + quoted(ZONE_TYPE) + key_text(ZONE_BBOX)  # after the root's id
# One JSON string on one line.
_DESCRIPTION = (regex.escape(VALUE_SPACE) + r'"(?:[^"\\\x00-\x1f]|\\(?:["\\/bfnrt]|u[0-9a-fA-F]{4}))'
                + f'{{0,{DESCRIPTION_MAX_CHARS}}}"')
# The rest of a plan step after its id: plain words (no quote or brace, so no JSON key starts a layout
# rule inside the plan; no line break; the first "." ends the step).
_STEP_WORDS = (f'(?: [^"{{}}\\n{regex.escape(STEP_END)}]{{0,{PLAN_STEP_MAX_CHARS}}})?'
               + regex.escape(STEP_END))
# Characters searched for the last anchor: longer than any constrained segment (the longest: a
# relation, the description and the next key).
_TAIL = 2 * DESCRIPTION_MAX_CHARS


_ANY = r"[\s\S]*"  # what follows a rule that does not end the completion: the next anchor's rule


class Rule(NamedTuple):
    """What the next tokens must continue: ``partial`` (the text since the anchor) + the new text must
    stay a prefix of ``pattern``, and numbers at ``ordered`` (min, max) positions of its JSON array
    must leave room for max > min. ``pattern`` None: the completion is finished; only EOS may follow.
    ``choices``: the rule is one of these literal strings, then ``pattern`` (anything, unless the rule
    gave one: a plan step's words after its id), or nothing after it when ``closed`` (the completion's
    last text): a prefix test stands in for a regex of the choices, so none is compiled per set of ids
    left."""

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
            return any(c.startswith(text) or not self.closed and text.startswith(c) and self._follows(text, c)
                       for c in self.choices)
        machine, state = self._moved(added)
        if not machine.live[state]:
            return False
        machine.keep(text, state)
        return not self.ordered or _extents_possible(text, self.ordered)

    def _moved(self, added: str):
        """(the pattern's automaton, its state after ``partial`` + ``added``): the partial match of the
        pattern as a state; the rule's text so far has its state cached (the last step kept it), so a
        step reads only the token."""
        machine = automaton(self.pattern)
        return machine, machine.step(machine.state(self.partial), added)

    def after(self, added: str, core: _Core | None) -> Rule | None | bool:
        """The rule in force after ``added`` where this rule (of ``core``, from :func:`last_anchor`, its
        ``partial`` the text since the anchor) admits it and no anchor ends inside it: what
        ``admits`` + :func:`active_rule` give; False where the rule refuses ``added``. Under a regex
        rule that does not end the completion one move of the pattern's automaton decides both: its
        pattern is the core's then anything, so the state after the text is live where the rule
        admits it and accepting where the segment is complete (free text follows: None)."""
        if self.choices:
            text = self.partial + added
            if _inside_a_choice(text, self.choices):  # admitted, and no choice complete in it
                return Rule(text, self.pattern, self.ordered, self.choices, self.closed)
            choice = None if self.closed or self.pattern is None else _choice_before(text, self.choices)
            if choice is not None:  # past its one choice (a plan step's id): the words after it
                if self.pattern == _ANY:  # nothing follows the choice: the segment is complete
                    return None
                machine = automaton(self.pattern)  # the core's pattern then anything, after the choice
                state = machine.state(text[len(choice):])
                if not machine.live[state]:
                    return False
                return None if machine.accepting[state] else Rule(text, self.pattern, self.ordered,
                                                                  self.choices)
        if self.choices or self.closed or self.pattern is None:
            return active_rule(self.partial + added, core, within=True) if self.admits(added) else False
        machine, state = self._moved(added)
        if not machine.live[state]:
            return False
        text = self.partial + added
        if self.ordered and not _extents_possible(text, self.ordered):
            return False
        machine.keep(text, state)
        return None if machine.accepting[state] else Rule(text, self.pattern, self.ordered)

    def after_choice(self) -> str | None:
        """The regex the text after a complete choice must continue; None where anything may follow."""
        return None if self.pattern == _ANY else self.pattern

    def _follows(self, text: str, choice: str) -> bool:
        after = self.after_choice()
        if after is None:
            return True
        machine = automaton(after)
        return machine.live[machine.state(text[len(choice):])]


def _inside_a_choice(text: str, choices: tuple[str, ...]) -> bool:
    """Whether ``text`` is a proper prefix of one of ``choices`` and none of them is a prefix of it
    (so a literal rule admits it and is not complete after it); False also where that is not
    decided this way (one choice a prefix of another: the general test decides)."""
    if len(choices) == 1:
        return len(text) < len(choices[0]) and choices[0].startswith(text)
    ordered, nested = _sorted_choices(choices)
    if nested:
        return False
    i = bisect.bisect_left(ordered, text)
    # no choice is a prefix of another, so none is a prefix of a proper prefix of one
    return i < len(ordered) and len(ordered[i]) > len(text) and ordered[i].startswith(text)


def _choice_before(text: str, choices: tuple[str, ...]) -> str | None:
    """The choice that is a prefix of ``text`` where no choice is a prefix of another (then there is
    at most one, and no choice starts with ``text`` unless it is that one); else None."""
    ordered, nested = _sorted_choices(choices)
    if nested:
        return None
    i = bisect.bisect_right(ordered, text) - 1  # the last choice up to text: the prefix, if any
    return ordered[i] if i >= 0 and text.startswith(ordered[i]) else None


@functools.lru_cache(maxsize=4096)
def _sorted_choices(choices: tuple[str, ...]) -> tuple[list[str], bool]:
    """A literal rule's choices in sorted order, and whether one of them is a prefix of another."""
    ordered = sorted(choices)
    return ordered, any(b.startswith(a) for a, b in zip(ordered, ordered[1:]))


class _Core(NamedTuple):
    pattern: str
    ordered: tuple[tuple[int, int], ...] = ()
    then_eos: bool = False  # once the pattern is complete the completion ends
    choices: tuple[str, ...] = ()  # literal alternatives before ``pattern`` (see Rule)

    def prefix_rule(self, partial: str) -> Rule:
        """The :class:`Rule` of this core after ``partial``: its pattern, then anything (the next
        anchor's rule takes over) unless the completion ends with it."""
        pattern = self.pattern if self.then_eos else _then_anything(self.pattern)
        return Rule(partial, pattern, self.ordered, self.choices, closed=self.then_eos)

    def ends_in(self, partial: str) -> bool:
        """Whether ``partial`` starts with all of the rule's text (:meth:`complete` is not None): the
        automaton of the pattern then anything accepts ``partial`` (after a choice, what follows it)."""
        if not self.choices:
            machine = automaton(_then_anything(self.pattern))
            return machine.accepting[machine.state(partial)]
        for c in self.choices:
            if partial.startswith(c):
                if not self.pattern:
                    return True
                machine = automaton(_then_anything(self.pattern))
                if machine.accepting[machine.state(partial[len(c):])]:
                    return True
        return False

    def complete(self, partial: str) -> int | None:
        """Where the rule's text ends if ``partial`` starts with all of it, else None."""
        if not self.choices:
            done = _compiled(self.pattern).match(partial)
            return None if done is None else done.end()
        for c in self.choices:
            if partial.startswith(c):
                done = _compiled(self.pattern).match(partial, len(c)) if self.pattern else None
                if not self.pattern or done is not None:
                    return len(c) if done is None else done.end()
        return None


def _literal(*strings: str, then_eos: bool = False) -> _Core:
    """A rule that is one of ``strings`` (plain text, no regex), the completion's end if ``then_eos``."""
    return _Core("", then_eos=then_eos, choices=strings)


def _extents_possible(text: str, pairs) -> bool:
    """Whether the JSON number array that ``text`` starts (`` [1.5, 2``, a prefix the array's pattern
    admits) can still end with every max above its min: a finished max must exceed its min, a max being
    written must be able to. The values before the last comma (all of them once the array is closed)
    are read once per array prefix (cached), so a step reads only the value being written."""
    m = _ARRAY_START.match(text)
    if m is None:
        return True
    body = m.group(1)
    if m.group(2):  # closed: every value finished (the same body at each step after the "]")
        return _finished_values(body, pairs)[1]
    head, comma, last = body.rpartition(",")
    done, ok = _finished_values(head, pairs) if comma else ((), True)
    if not ok:
        return False
    last = last.strip()
    n_done = len(done)  # the last value, at index n_done, is being written
    for lo, hi in pairs:
        if lo == n_done:  # a min being written: one no max can exceed (9999.99999999)
            if last and not last.startswith("-") and float(last.rstrip(".")) >= _largest(""):
                return False
        elif hi == n_done and not _largest(last) > done[lo]:
            return False
    return True


@functools.lru_cache(maxsize=4096)
def _finished_values(head: str, pairs) -> tuple[tuple[float, ...], bool]:
    """The finished values of an array (``head``: its text before the last comma, or inside its closed
    brackets) and whether each of their (min, max) pairs has max > min."""
    done = tuple(float(v) for v in head.split(","))
    return done, all(done[hi] > done[lo] for lo, hi in pairs if hi < len(done))


def _largest(prefix: str) -> float:
    """The largest number of the grammar (``NUMBER_PATTERN``: at most ``INTEGER_DIGITS`` integer digits and
    ``MAX_DECIMALS`` decimals) that starts with ``prefix``. A max must be able to exceed its min by a
    number that can still be written: a least upper bound would let ``1.06386999`` (eight decimals)
    through after a min of ``1.06386999`` and leave no token that continues the box."""
    negative = prefix.startswith("-")
    digits = prefix[1:] if negative else prefix
    whole, dot, fraction = digits.partition(".")
    if negative:  # the fewest digits: "-" -> -0, "-1." -> -1.0, "-12" -> -12
        return -float(f"{whole or 0}.{fraction or 0}")
    if not dot and whole != "0":  # more integer digits may follow (none after a leading 0)
        whole += "9" * (INTEGER_DIGITS - len(whole))
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


def constraint_rule(text: str, listed: Sequence[str] | None, zone: Sequence[float] | None = None,
                    follow_plan: bool = True) -> Rule | None:
    """The :class:`Rule` the next token of a completion prefix must keep, or None. ``listed``: the
    prompt's ids (:func:`listed_instance_ids`); ``zone``: its placement zone (:func:`prompt_zone`);
    ``follow_plan``: the layout's entries follow the completion's own plan (:func:`planned_entries`).

    None: nothing constrains the next token (free text, a finished segment, or a prefix that already
    broke the rule: the parser will reject it; no mask can repair it).
    """
    found = last_anchor(text, listed, zone, follow_plan)
    return None if found is None else active_rule(text[found[0]:], found[1])


def active_rule(partial: str, core: _Core | None, within: bool = False) -> Rule | None:
    """The rule of ``core`` (from :func:`last_anchor`) while ``partial``, the text since its anchor, is
    inside it; EOS only once a rule that ends the completion is complete; else None. ``within``: the
    caller already knows ``partial`` continues the rule (its last token was checked against it)."""
    if core is None:
        return None
    if core.then_eos:  # EOS only where the rule's text ends the partial exactly
        end = core.complete(partial)
        if end is not None:
            return Rule(partial, None) if end == len(partial) else None
    elif core.ends_in(partial):  # the segment is complete: free text until the next anchor
        return None
    return core.prefix_rule(partial) if within or within_rule(partial, core) else None


def entered_rule(partial: str, core: _Core | None) -> Rule | None | bool:
    """:func:`active_rule` of ``partial``, the text since an anchor just written, where it continues
    ``core``'s rule (:func:`within_rule`); else False. A regex rule that does not end the completion:
    one state of its automaton decides both."""
    if core is None:
        return None
    if core.choices or core.then_eos:
        return active_rule(partial, core, within=True) if within_rule(partial, core) else False
    pattern = _then_anything(core.pattern)
    machine = automaton(pattern)
    state = machine.state(partial)
    if not machine.live[state] or core.ordered and not _extents_possible(partial, core.ordered):
        return False
    return None if machine.accepting[state] else Rule(partial, pattern, core.ordered)


def within_rule(partial: str, core: _Core | None) -> bool:
    """Whether ``partial``, the text since an anchor, can still continue into that anchor's rule."""
    return core is None or core.prefix_rule("").admits(partial)


def last_anchor(text: str, listed: Sequence[str] | None, zone: Sequence[float] | None = None,
                follow_plan: bool = True) -> tuple[int, _Core | None] | None:
    """(position in ``text`` where its last anchor ends, the rule of what must follow it or None).

    None: no anchor in the last ``_TAIL`` characters. The rule stays valid until the next anchor, so
    a decoder need not look for one again until a token that can end an anchor arrives.
    """
    found = find_anchor(text)
    if found is None:
        return None
    position, anchor = found
    return position, _core(text[:position], anchor, listed, zone, follow_plan)


def find_anchor(text: str) -> tuple[int, re.Match] | None:
    """The search of :func:`last_anchor` without the rule: (where the last anchor ends, its match), or
    None. The rule is a function of ``text`` up to there and the match's groups (:func:`anchor_core`)."""
    tail = text[-_TAIL:]
    anchor = _last_match(tail)
    if anchor is None:
        return None
    return len(text) - len(tail) + anchor.end(), anchor


def anchor_core(text: str, found: tuple[int, re.Match], listed: Sequence[str] | None,
                zone: Sequence[float] | None = None, follow_plan: bool = True) -> _Core | None:
    """The rule of the anchor :func:`find_anchor` found in ``text``."""
    return _core(text[:found[0]], found[1], listed, zone, follow_plan)


def _last_match(tail: str):
    """The last of ``ANCHOR``'s matches in ``tail`` (scanned from its start), read from its last lines
    only: a match holds a line break only as its first character, so none spans a line break and the
    scan from the start tries a match at every line break; from there on it finds what a scan from that
    line break finds (a match's look-ahead stops at the next line break, so it sees the same text when
    the scan ends there)."""
    end = len(tail)
    while True:
        start = max(tail.rfind(STEP_SEPARATOR, 0, end), 0)
        anchor = None
        for found in ANCHOR.finditer(tail, start, end):
            anchor = found
        if anchor is not None or start == 0:
            return anchor
        end = start


class PlannedEntry(NamedTuple):
    """What a completion's plan says of one layout entry."""

    iid: str
    parent: str | None
    """The object its step puts it in or on, :data:`TABLE` for a table-level step, None for a step
    that names no object placed before it (the layout's parent is then the model's choice)."""
    relation: str | None
    """``in`` / ``on`` (with ``parent``), :data:`TABLE_RELATION` on the table, None as ``parent``."""


def planned_entries(text: str, listed: Sequence[str] | None) -> tuple[PlannedEntry, ...] | None:
    """The layout entries the plan of ``text`` implies, in its order (physcene.ctrc writes both in one
    order, Algorithm 1's: the plan's k-th step is the layout's k-th object, and a step ``Place X in|on
    Y.`` is the entry of X under Y); None before the layout header, or when the plan does not name
    each id of ``listed`` once (then the layout's ids are only the list's)."""
    end = text.find(LAYOUT_HEADER)
    if end < 0 or not listed:
        return None
    return _planned(text[:end], tuple(listed))


@functools.lru_cache(maxsize=1024)
def _planned(plan: str, listed: tuple[str, ...]) -> tuple[PlannedEntry, ...] | None:
    entries: list[PlannedEntry] = []
    placed: set[str] = set()
    for sentence in _PLAN_LINE.findall(plan):
        step = _CHILD_STEP.match(sentence)
        named = _SENTENCE_ID.match(sentence)
        if named is None or named.group(1) in placed:
            return None
        iid = named.group(1)
        if step is None:
            entries.append(PlannedEntry(iid, TABLE, TABLE_RELATION))
        elif step.group("parent") in placed:
            entries.append(PlannedEntry(iid, step.group("parent"), step.group("relation")))
        else:
            entries.append(PlannedEntry(iid, None, None))
        placed.add(iid)
    return tuple(entries) if placed == set(listed) and len(entries) == len(listed) else None


def _core(text: str, anchor, listed: Sequence[str] | None, zone: Sequence[float] | None,
          follow_plan: bool = True) -> _Core | None:
    """The rule of ``anchor``, the last anchor of ``text`` (which ends with it)."""
    key, step, line = anchor.group("key", "step", "line")
    if step is not None or line is not None:
        if LAYOUT_HEADER in text or not listed:  # the anchor lies in the layout, or no list
            return None
        placed = set(_PLACED_IN_PLAN.findall(text))
        left = [i for i in listed if i not in placed]
        if step is not None:  # an id left, then words without quotes or braces to the "."
            return _Core(_STEP_WORDS, choices=tuple(f" {i}" for i in left)) if left else None
        if left:
            return _literal(STEP_SEPARATOR + step_start(int(line) + 1))
        return _literal(_LAYOUT_START)
    if zone is not None and key in (ZONE_BBOX, ZONE):  # given by the prompt: copy it
        if key == ZONE_BBOX:  # the root entry: the zone with a zero height
            return _literal(VALUE_SPACE + _json_numbers([*zone, 0.0, 0.0]) + key_text(next_key(key)))
        return _literal(VALUE_SPACE + _json_numbers(zone) + LAYOUT_CLOSE, then_eos=True)
    if key in _ARRAY_LENGTH:
        return _array_core(key)
    if key in (RELATIVE_ROTATION, ZONE_ROTATION):
        if listed is None:
            return _rotation_core(None)
        placed = set(_INSTANCE_IDS.findall(text))
        return _rotation_core(any(i not in placed for i in listed))
    ids = _INSTANCE_IDS.findall(text)
    follow = _follow(key)
    if key == CATEGORY:  # the id's own category: no plan needed
        if not ids or ids[-1] == TABLE:
            return None
        return _choices_core((category_from_instance(ids[-1]),), follow)
    plan = planned_entries(text, listed) if follow_plan else None
    planned = _by_iid(plan) if plan else {}
    if key == INSTANCE_ID:
        if not ids:
            return _literal(VALUE_SPACE + f'"{TABLE}"' + _ROOT_KEYS)
        if listed is None:
            return None
        allowed = [i for i in listed if i not in ids]
        if plan and len(ids) - 1 < len(plan) and plan[len(ids) - 1].iid in allowed:
            allowed = [plan[len(ids) - 1].iid]  # the plan's next object (ids[0] is the root)
    elif key == PARENT_ID:
        allowed = [TABLE, *[i for i in ids[:-1] if i != TABLE]]
        step = planned.get(ids[-1]) if ids else None
        if step is not None and step.parent in allowed:
            allowed = [step.parent]
    else:  # relation_type, then the free description: a regex (three patterns in all: near / in / on)
        parents = _PARENT_IDS.findall(text)
        if not parents:
            return None
        allowed = [TABLE_RELATION] if parents[-1] == TABLE else list(CHILD_RELATIONS)
        step = planned.get(ids[-1]) if ids else None
        if step is not None and step.parent == parents[-1] and step.relation in allowed:
            allowed = [step.relation]
        return _relation_core(tuple(allowed), follow)
    if not allowed:
        return None
    return _choices_core(tuple(allowed), follow)


@functools.lru_cache(maxsize=4096)
def _choices_core(allowed: tuple[str, ...], follow: str) -> _Core:
    """The literal rule of one of the ``allowed`` JSON strings, then the key ``follow``."""
    return _literal(*(VALUE_SPACE + f'"{i}"' + follow for i in allowed))


@functools.cache
def _follow(key: str) -> str:
    """The text of the key after ``key``'s value (``, "category":``)."""
    return key_text(next_key(key))


@functools.lru_cache(maxsize=1024)
def _by_iid(plan: tuple[PlannedEntry, ...]) -> dict[str, PlannedEntry]:
    """A plan's entries by id (read-only: shared by every rule of that plan)."""
    return {e.iid: e for e in plan}


@functools.cache
def _array_core(key: str) -> _Core:
    """The rule after a number array's key (a function of the key alone: built once)."""
    n = _ARRAY_LENGTH[key]
    core = (regex.escape(VALUE_SPACE + "[") + NUMBER_PATTERN
            + f"(?:{regex.escape(ITEM_SEPARATOR)}{NUMBER_PATTERN}){{{n - 1}}}" + regex.escape("]"))
    if key == ZONE:  # the layout's last value: its brace, then EOS
        return _Core(core + regex.escape(LAYOUT_CLOSE), _ORDERED[key], then_eos=True)
    return _Core(core + _key(next_key(key)), _ORDERED.get(key, ()))


@functools.cache
def _rotation_core(ids_left: bool | None) -> _Core:
    """The rule after a rotation's key: the number and the entry's brace, then the next entry while ids
    are left (``ids_left``), else the end of the objects array; None: the prompt lists no ids."""
    core = regex.escape(VALUE_SPACE) + NUMBER_PATTERN + regex.escape("}")
    if ids_left is None:
        return _Core(core)
    return _Core(core + (_NEXT_ENTRY if ids_left else _END_OF_OBJECTS))


@functools.cache
def _relation_core(allowed: tuple[str, ...], follow: str) -> _Core:
    """The rule after ``relation_type``'s key: one of ``allowed``, the description, its next key."""
    return _Core(regex.escape(VALUE_SPACE) + '"' + _alternatives(allowed) + '"' + regex.escape(follow)
                 + _DESCRIPTION + _key(next_key(DESCRIPTION)))


def _json_numbers(values: Sequence[float]) -> str:
    """``[0.0, 132.9, ...]`` as physcene.ctrc writes a layout's numbers (JSON floats)."""
    return json_line([float(v) + 0.0 for v in values])


@functools.cache
def _key(name: str) -> str:
    """The regex of :func:`physcene.ctrc.grammar.key_text`: one key of an entry, after the previous value."""
    return regex.escape(key_text(name))


@functools.lru_cache(maxsize=4096)
def _compiled(pattern: str):
    return regex.compile(pattern)


@functools.lru_cache(maxsize=4096)
def _then_anything(pattern: str) -> str:
    """``pattern`` then anything: one string per pattern, so the rule of every step under it looks its
    compiled regex up by a string whose hash is already known."""
    return pattern + _ANY


def token_may_end_anchor(added: str) -> bool:
    """Whether a token's text ``added`` may end an anchor after some text (:func:`may_end_anchor` for
    any ``text``): it holds a key's colon, a line break or a full stop, or it completes "Place" (holds
    it, or starts with the rest of a "Place" whose start the text before it may end with: "e", "ce",
    ... "Place")."""
    if any(c in added for c in (KEY_COLON, STEP_SEPARATOR, STEP_END)) or PLACE in added:
        return True
    return any(PLACE[:-1].endswith(added[:j]) for j, c in enumerate(added[:len(PLACE)]) if c == PLACE[-1])


def may_end_anchor(text: str, added: str) -> bool:
    """Whether appending ``added`` to ``text`` can complete an anchor: a key's ``":``, a plan step's
    ``Place`` (also one split over tokens), or the ``.`` that ends a plan line: only on a line that
    starts ``N. Place``, so a layout's decimal points (most of its ``.``) start no search."""
    if KEY_COLON in added or PLACE in text[-len(PLACE):] + added or STEP_SEPARATOR in added:
        return True
    dot = added.find(STEP_END)
    if dot < 0:
        return False
    line = text.rfind(STEP_SEPARATOR, 0, len(text) + dot)
    return line >= 0 and _STEP_LINE.match(text, line) is not None

