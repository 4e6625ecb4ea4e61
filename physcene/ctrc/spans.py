"""Where a completion's objects and numbers sit in its text: character spans for PADA's masks.

PADA* leaves the geometry's numbers to exploration (:func:`numeric_spans`); object credit charges
each object's own text (:func:`object_text_spans`). The patterns are built from
:mod:`physcene.ctrc.grammar`'s key names and plan-step syntax.
"""

from __future__ import annotations

import re

from physcene.ctrc.grammar import (
    INSTANCE_ID,
    KEY_COLON,
    LAYOUT_HEADER,
    PLACE,
    RELATIVE_BBOX,
    RELATIVE_ROTATION,
    STEP_NUMBER_END,
    quoted,
    string_value_pattern,
)

__all__ = ["GEOMETRY_KEYS", "OBJECT_TEXT_SCOPES", "numeric_spans", "object_line_spans", "object_text_spans"]

# JSON keys whose numbers PADA* leaves to exploration: the geometry, not the semantics.
GEOMETRY_KEYS = (RELATIVE_BBOX, RELATIVE_ROTATION)
# What of an object's text :func:`object_text_spans` returns: its plan step and layout line, or only
# the numbers of its geometry.
OBJECT_TEXT_SCOPES = ("line", "numbers")
# Any JSON number a model may write (an exponent too): spans are looked for in unchecked output.
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_INSTANCE_ID = re.compile(string_value_pattern(INSTANCE_ID))
# A plan step "3. Place <id> ..." (any whitespace between the number and the verb); group 1: the id.
_PLAN_STEP = re.compile(r"\s*\d+" + re.escape(STEP_NUMBER_END.strip()) + r"\s+" + re.escape(PLACE)
                        + r" (\S+)\s")


def numeric_spans(text: str, keys: tuple[str, ...] | list[str] = GEOMETRY_KEYS) -> list[tuple[int, int]]:
    """Character spans ``[start, end)`` of the numbers inside the JSON values of ``keys`` in ``text``.

    A value is the bracketed list or the scalar after ``"key":``. Numbers elsewhere (instance ids such
    as ``pen_0``, layer indices, the zone) are semantic and stay supervised.
    """
    spans = []
    for key in keys:
        value = re.escape(quoted(key)) + r"\s*" + re.escape(KEY_COLON) + r"\s*(\[[^\]]*\]|[-+0-9.eE]+)"
        for m in re.finditer(value, text):
            base = m.start(1)
            spans.extend((base + n.start(), base + n.end()) for n in _NUMBER.finditer(m.group(1)))
    return sorted(spans)


def object_line_spans(text: str) -> list[tuple[int, int]]:
    """Character spans ``[start, end)`` of the object lines of a CTRC layout, in the order written
    (the lines with a ``relative_bbox``; the zone's line has none): object k of the parsed scene."""
    spans, start = [], 0
    marker = quoted(RELATIVE_BBOX)
    for line in text.splitlines(keepends=True):
        if marker in line:
            spans.append((start, start + len(line.rstrip("\n"))))
        start += len(line)
    return spans


def object_text_spans(text: str, scope: str = "line") -> list[list[tuple[int, int]]]:
    """Per object of a CTRC layout, in the order written (object k of the parsed scene): the
    character spans of the text that places it. ``scope`` ``line``: its plan step ("k. Place <id>
    ...", the first one naming it, when the plan has one) and its layout line
    (:func:`object_line_spans`); ``numbers``: only the numbers of its geometry (:data:`GEOMETRY_KEYS`)
    on that line, so its id, category, relation and description are never charged."""
    if scope not in OBJECT_TEXT_SCOPES:
        raise ValueError(f"object credit scope must be one of {list(OBJECT_TEXT_SCOPES)}, got {scope!r}")
    if scope == "numbers":
        return [[(a + x, a + y) for x, y in numeric_spans(text[a:b])] for a, b in object_line_spans(text)]
    plan_end = text.find(LAYOUT_HEADER)
    steps, start = {}, 0
    for line in text[:max(plan_end, 0)].splitlines(keepends=True):
        if (m := _PLAN_STEP.match(line)) is not None:
            steps.setdefault(m.group(1), (start, start + len(line.rstrip("\n"))))
        start += len(line)
    spans = []
    for a, b in object_line_spans(text):
        m = _INSTANCE_ID.search(text, a, b)
        step = steps.get(m.group(1)) if m is not None else None
        spans.append([s for s in (step, (a, b)) if s is not None])
    return spans
