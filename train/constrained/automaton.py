"""A rule's regular expression as a lazily built DFA, so that a row's check per decoding step costs one
table look-up per token instead of a partial match over all the text since its anchor.

``regex``'s partial matching (``fullmatch(text, partial=True)``) asks whether ``text`` is a prefix of a
string of the pattern's language; ``match(text)`` whether a prefix of ``text`` is one. Both are
properties of the language alone, and the rules' patterns are plain regular expressions (literals,
classes, groups, alternation, greedy repeats: no anchors, look-arounds or back-references), so a
deterministic automaton answers them exactly: the state after ``text`` is live (some continuation
reaches acceptance) iff ``text`` is such a prefix, and the state of ``pattern`` + ``[\\s\\S]*`` after
``text`` accepts iff a prefix of ``text`` matches ``pattern``. Each state is the set of positions of
the pattern's Thompson NFA; states and their moves are built on first use and kept, and the state of
each text seen is cached by the text itself (the next step's text is this one plus a token).
Character classes (``\\d``, ``\\s``, ...) are decided by ``regex`` itself, one character at a time,
so a class means here what it means to the partial matcher.
"""

from __future__ import annotations

import functools
import re

import regex

try:  # Python 3.11+
    import re._constants as sre
    import re._parser as sre_parse
except ImportError:  # Python 3.10
    import sre_constants as sre
    import sre_parse

__all__ = ["DEAD", "Automaton", "automaton"]

DEAD = 0
"""The state of every text that no continuation brings into the language (the empty set of positions)."""

_CATEGORIES = {sre.CATEGORY_DIGIT: r"\d", sre.CATEGORY_NOT_DIGIT: r"\D", sre.CATEGORY_SPACE: r"\s",
               sre.CATEGORY_NOT_SPACE: r"\S", sre.CATEGORY_WORD: r"\w", sre.CATEGORY_NOT_WORD: r"\W"}
_POSSESSIVE_REPEAT = getattr(sre, "POSSESSIVE_REPEAT", None)  # Python 3.11+
_UNSUPPORTED_FLAGS = re.IGNORECASE | re.DOTALL | re.MULTILINE | re.LOCALE | re.VERBOSE | re.ASCII
# texts and (state, token text) moves cached per automaton; past these the cache starts afresh
# (a step needs only its row's last text: a few per row)
_TEXTS_KEPT = 1 << 14
_MOVES_KEPT = 1 << 16


class Automaton:
    """The DFA of one pattern: ``state(text)`` (cached by text), ``step(state, added)`` (cached by
    state and token text), ``live[state]`` (text so far is a prefix of the language) and
    ``accepting[state]`` (text so far is in the language)."""

    def __init__(self, pattern: str):
        parsed = sre_parse.parse(pattern)
        if parsed.state.flags & _UNSUPPORTED_FLAGS:
            raise ValueError(f"automaton: flags of {pattern!r} are not supported")
        # the NFA: per node, ("char", test, next) | ("split", [next, ...]) | ("accept",)
        self._nodes: list = [("accept",)]
        start = self._sequence(list(parsed), 0, pattern)
        self._ids: dict[tuple[int, ...], int] = {}
        self._sets: list[tuple[int, ...]] = []
        self.live: list[bool] = []
        self.accepting: list[bool] = []
        self._state_of(())  # DEAD
        self.start = self._state_of(self._closure([start]))
        self._char_moves: dict[tuple[int, str], int] = {}
        self._moves: dict[tuple[int, str], int] = {}
        self._texts: dict[str, int] = {}

    def state(self, text: str) -> int:
        """The state after ``text`` from the start (cached by the text)."""
        found = self._texts.get(text)
        if found is None:
            found = self.advance(self.start, text)
            self.keep(text, found)
        return found

    def keep(self, text: str, state: int) -> None:
        """Remember that ``text`` leads to ``state`` (the next step continues from it)."""
        if len(self._texts) >= _TEXTS_KEPT:
            self._texts.clear()
        self._texts[text] = state

    def step(self, state: int, added: str) -> int:
        """The state after ``added`` from ``state`` (cached: ``added`` is mostly a token's text)."""
        key = (state, added)
        found = self._moves.get(key)
        if found is None:
            if len(self._moves) >= _MOVES_KEPT:
                self._moves.clear()
            found = self._moves[key] = self.advance(state, added)
        return found

    def advance(self, state: int, text: str) -> int:
        """The state after ``text`` from ``state``, one character at a time."""
        moves = self._char_moves
        for ch in text:
            if state == DEAD:
                return DEAD
            nxt = moves.get((state, ch))
            if nxt is None:
                nxt = moves[(state, ch)] = self._move(state, ch)
            state = nxt
        return state

    def _move(self, state: int, ch: str) -> int:
        nodes = self._nodes
        targets = [nodes[i][2] for i in self._sets[state] if nodes[i][0] == "char" and nodes[i][1](ch)]
        return self._state_of(self._closure(targets))

    def _closure(self, starts: list[int]) -> tuple[int, ...]:
        """The char and accept nodes reached from ``starts`` without reading a character."""
        seen, stack, out = set(), list(starts), set()
        while stack:
            i = stack.pop()
            if i in seen:
                continue
            seen.add(i)
            node = self._nodes[i]
            if node[0] == "split":
                stack.extend(node[1])
            else:
                out.add(i)
        return tuple(sorted(out))

    def _state_of(self, positions: tuple[int, ...]) -> int:
        found = self._ids.get(positions)
        if found is None:
            found = self._ids[positions] = len(self._sets)
            self._sets.append(positions)
            # every node reaches acceptance (Thompson's construction, classes that each admit some
            # character), so a non-empty set of positions is live
            self.live.append(bool(positions))
            self.accepting.append(0 in positions)
        return found

    def _add(self, node: tuple) -> int:
        self._nodes.append(node)
        return len(self._nodes) - 1

    def _sequence(self, items: list, after: int, pattern: str) -> int:
        for op, arg in reversed(items):
            after = self._item(op, arg, after, pattern)
        return after

    def _item(self, op, arg, after: int, pattern: str) -> int:
        if op in (sre.LITERAL, sre.NOT_LITERAL, sre.ANY, sre.IN):
            return self._add(("char", _char_test(op, arg, pattern), after))
        if op is sre.SUBPATTERN:
            _, add_flags, del_flags, sub = arg
            if add_flags or del_flags:
                raise ValueError(f"automaton: inline flags of {pattern!r} are not supported")
            return self._sequence(list(sub), after, pattern)
        if op is sre.BRANCH:
            return self._add(("split", [self._sequence(list(alt), after, pattern) for alt in arg[1]]))
        if op is _POSSESSIVE_REPEAT and op is not None:
            raise ValueError(f"automaton: possessive repeats of {pattern!r} are not supported")
        if op in (sre.MAX_REPEAT, sre.MIN_REPEAT):
            low, high, sub = arg
            sub = list(sub)
            if high == sre.MAXREPEAT:
                loop = self._add(("split", []))
                self._nodes[loop][1].extend([self._sequence(sub, loop, pattern), after])
                start = loop
            else:
                start = after
                for _ in range(high - low):  # (x(x(x)?)?)?: each optional copy leads to the rest
                    start = self._add(("split", [self._sequence(sub, start, pattern), after]))
            for _ in range(low):
                start = self._sequence(sub, start, pattern)
            return start
        raise ValueError(f"automaton: {op} in {pattern!r} is not supported")


def _char_test(op, arg, pattern: str):
    """Whether one character matches the atom (``regex`` decides the classes)."""
    if op is sre.LITERAL:
        return chr(arg).__eq__
    if op is sre.NOT_LITERAL:
        return chr(arg).__ne__
    if op is sre.ANY:
        return "\n".__ne__
    negate, tests = False, []
    for kind, value in arg:
        if kind is sre.NEGATE:
            negate = True
        elif kind is sre.LITERAL:
            tests.append(chr(value).__eq__)
        elif kind is sre.RANGE:
            tests.append(lambda ch, lo=value[0], hi=value[1]: lo <= ord(ch) <= hi)
        elif kind is sre.CATEGORY and value in _CATEGORIES:
            matcher = regex.compile(_CATEGORIES[value]).fullmatch
            tests.append(lambda ch, m=matcher: m(ch) is not None)
        else:
            raise ValueError(f"automaton: {kind} {value} in a class of {pattern!r} is not supported")
    return lambda ch: any(t(ch) for t in tests) != negate


@functools.lru_cache(maxsize=256)
def automaton(pattern: str) -> Automaton:
    """The automaton of ``pattern`` (built once per pattern: the rules' patterns are few)."""
    return Automaton(pattern)
