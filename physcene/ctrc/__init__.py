"""CTRC, the Cognitive Topological Reasoning Chain: a layout written as text a model can learn.

A completion is a numbered plan of templated sub-instructions, anchor first (paper Algorithm 1),
followed by the layered layout JSON (paper appendix example). One module per stage:

- :mod:`~physcene.ctrc.grammar`: the format itself (headers, keys and their order, number syntax,
  limits, the writer's whitespace, plan steps); every other consumer derives from it;
- :mod:`~physcene.ctrc.frames`: the parent frames, relative <-> absolute boxes;
- :mod:`~physcene.ctrc.writer`: :func:`encode`, :func:`completion_text`, :func:`sub_instructions`;
- :mod:`~physcene.ctrc.reader`: :func:`parse` (total: a Scene or a :class:`ParseError`), :func:`decode`;
- :mod:`~physcene.ctrc.prompts`: :func:`build_prompt`, :func:`zero_shot_prompt`;
- :mod:`~physcene.ctrc.spans`: where objects and their numbers sit in a completion's text (PADA).
"""

from physcene.ctrc.grammar import (
    BOX_EXTENTS,
    DECIMALS,
    ENTRY_KEYS,
    ENTRY_SEPARATOR,
    LAYOUT_HEADER,
    MAX_ABS_CM,
    MAX_CHARS,
    MAX_DECIMALS,
    MAX_OBJECTS,
    OBJECTS_CLOSE,
    OBJECTS_OPEN,
    ON_CONTACT_GAP_CM,
    PLAN_HEADER,
    TOP_KEYS,
)
from physcene.ctrc.prompts import build_prompt, with_physics, zero_shot_prompt
from physcene.ctrc.reader import ParseError, decode, parse
from physcene.ctrc.writer import (
    coarse_location,
    completion_text,
    decimals_of,
    encode,
    sub_instructions,
    usual_decimals,
)

__all__ = [
    "BOX_EXTENTS",
    "DECIMALS",
    "ENTRY_KEYS",
    "ENTRY_SEPARATOR",
    "LAYOUT_HEADER",
    "MAX_ABS_CM",
    "MAX_CHARS",
    "MAX_DECIMALS",
    "MAX_OBJECTS",
    "OBJECTS_CLOSE",
    "OBJECTS_OPEN",
    "ON_CONTACT_GAP_CM",
    "PLAN_HEADER",
    "ParseError",
    "TOP_KEYS",
    "build_prompt",
    "coarse_location",
    "completion_text",
    "decimals_of",
    "decode",
    "encode",
    "parse",
    "sub_instructions",
    "usual_decimals",
    "with_physics",
    "zero_shot_prompt",
]
