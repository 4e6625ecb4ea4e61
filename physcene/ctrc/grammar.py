"""The CTRC format, described once: what a completion's text is made of.

The writer (:mod:`physcene.ctrc.writer`) builds its text from these pieces, the parser
(:mod:`physcene.ctrc.reader`) checks against these keys and limits, the decoding constraint
(:mod:`physcene.train.constrained.grammar`) and PADA's span finders (:mod:`physcene.ctrc.spans`) build
their patterns from them, and the reward's compiled reader takes the limits as arguments. Renaming
a key or changing a limit here changes all of them.

A completion::

    **Sub-instruction:**
    1. Place 1_laptop_0 at the center of the table.
    2. Place 5_pen_0 in 4_pen_holder_0.

    **Scene Layout:**
    {
      "objects": [
        {"layer": 0, "instance_id": "root_zone", "type": "zone", "bbox": [...], "z_rotation": 0.0},
        {"layer": 1, "instance_id": "1_laptop_0", "category": "laptop", ...},
        ...
      ],
      "item_placement_zone": [xmin, xmax, ymin, ymax]
    }
"""

from __future__ import annotations

import json
import re

from physcene.scene import RELATIONS, TABLE

__all__ = [
    "BOX_EXTENTS", "BOX_LENGTH", "CATEGORY", "CHILD_RELATIONS", "DECIMALS", "DESCRIPTION",
    "DESCRIPTION_MAX_CHARS", "ENTRY_KEYS", "ENTRY_SEPARATOR", "INSTANCE_ID", "INTEGER_DIGITS",
    "ITEM_SEPARATOR", "KEY_COLON", "KEY_SEPARATOR", "LAYER", "LAYER_DIGITS", "LAYOUT_CLOSE", "LAYOUT_HEADER",
    "LAYOUT_OPEN", "MAX_ABS_CM", "MAX_CHARS", "MAX_DECIMALS", "MAX_OBJECTS", "NUMBER_PATTERN", "OBJECTS",
    "OBJECTS_CLOSE", "OBJECTS_OPEN", "ON_CONTACT_GAP_CM", "PARENT_ID", "PLACE", "PLAN_HEADER", "PLAN_OPEN",
    "PLAN_STEP_MAX_CHARS", "RELATIONS", "RELATION_ALIASES", "RELATION_TYPE", "RELATIVE_BBOX",
    "RELATIVE_ROTATION", "STEP_END", "STEP_NUMBER_END", "STEP_SEPARATOR", "TABLE", "TABLE_RELATION",
    "TOP_KEYS", "TYPE", "VALUE_SPACE", "ZONE", "ZONE_BBOX", "ZONE_ENTRY_KEYS", "ZONE_LENGTH", "ZONE_ROTATION",
    "ZONE_TYPE", "child_step", "child_step_pattern", "key_text", "next_key", "plan_step", "quoted",
    "step_start", "step_start_pattern", "string_value_pattern",
]

# Numbers ---------------------------------------------------------------------------------------
# Digits after the decimal point in completion text. With the encoder's error feedback (each
# child is written relative to its parent *as decoded from the text*) the decoded pose differs
# from the original by the rounding of the object's own numbers only (≤ 1e-5 cm, ≤ 1e-5 deg),
# however deep the stack.
DECIMALS = 5
# Most digits after the point a completion may write: the CTRC constraint's number rule stops a model
# there (no digits forever), so data written for training stays within it too.
MAX_DECIMALS = 8
# Most integer digits of a number the constraint lets a model write: 100 m (a tabletop is a few
# metres) keeps even a deep stack of relative offsets under MAX_ABS_CM.
INTEGER_DIGITS = 4
# A number a completion may write (JSON, no leading zero, no exponent), within the digits above.
NUMBER_PATTERN = rf"-?(?:0|[1-9]\d{{0,{INTEGER_DIGITS - 1}}})(?:\.\d{{1,{MAX_DECIMALS}}})?"
# Coordinates or sizes beyond this (cm, 1 km) are model garbage, not a tabletop.
MAX_ABS_CM = 1e5

# Limits ----------------------------------------------------------------------------------------
# Completions longer than this are not layouts; refusing them bounds parse time.
MAX_CHARS = 200_000
# More objects than this is not a tabletop (MesaTask's largest scenes have a few dozen); refusing
# them keeps downstream O(n^2) graph and physics work bounded.
MAX_OBJECTS = 1000
# Digits of an entry's layer (its depth, at most one per object).
LAYER_DIGITS = len(str(MAX_OBJECTS))
# Longest description the constraint lets a model write (one JSON string on one line).
DESCRIPTION_MAX_CHARS = 300
# Longest rest of a plan step the constraint lets a model write after the step's id (the writer's
# longest, "to the right of X, about 62 cm away, at the right back of the table", is under 100).
PLAN_STEP_MAX_CHARS = 300

# Keys ------------------------------------------------------------------------------------------
OBJECTS = "objects"
ZONE = "item_placement_zone"
TOP_KEYS = (OBJECTS, ZONE)  # the layout JSON's keys, in the order written
LAYER = "layer"
INSTANCE_ID = "instance_id"
CATEGORY = "category"
PARENT_ID = "parent_id"
RELATION_TYPE = "relation_type"
DESCRIPTION = "description"
RELATIVE_BBOX = "relative_bbox"
RELATIVE_ROTATION = "relative_rotation_deg"
# An object entry's keys, in the order written.
ENTRY_KEYS = (LAYER, INSTANCE_ID, CATEGORY, PARENT_ID, RELATION_TYPE, DESCRIPTION, RELATIVE_BBOX,
              RELATIVE_ROTATION)
TYPE = "type"
ZONE_TYPE = "zone"  # the root entry's type
ZONE_BBOX = "bbox"
ZONE_ROTATION = "z_rotation"
# The root entry's keys (the table, instance id TABLE), in the order written.
ZONE_ENTRY_KEYS = (LAYER, INSTANCE_ID, TYPE, ZONE_BBOX, ZONE_ROTATION)
BOX_LENGTH = 6  # relative_bbox and the root's bbox: [xmin, xmax, ymin, ymax, zmin, zmax]
ZONE_LENGTH = 4  # item_placement_zone: [xmin, xmax, ymin, ymax]
# (min, max) index pairs of a relative box [xmin, xmax, ymin, ymax, zmin, zmax], x then y then z (the
# zone's [xmin, xmax, ymin, ymax] is the first two).
BOX_EXTENTS = ((0, 1), (2, 3), (4, 5))

# Relations -------------------------------------------------------------------------------------
TABLE_RELATION = "near"  # every table-level object (parent TABLE)
CHILD_RELATIONS = ("in", "on")  # an object under another object
# What a reader takes for each relation word (the paper writes on_surface; models write others).
RELATION_ALIASES = {
    "in": "in", "inside": "in", "inside_of": "in", "in_container": "in", "contained_in": "in",
    "within": "in",
    "on": "on", "on_top": "on", "on_top_of": "on", "on_surface": "on", "supported_by": "on",
    "stacked_on": "on",
    "near": "near", "next_to": "near", "beside": "near", "on_table": "near", "table": "near",
}
# An ``on`` child's relative z is measured from this far above its support's top, so relative zmin 0
# ("resting on it") decodes 1e-5 cm above the top: exact contact reads as float32 noise, ~1e-7-1e-6 cm
# of penetration that counts at the paper's 0 cm threshold (and costs the reward its +50). TTO rests
# on children the same distance up (configs/tto.yaml contact_gap_cm). 0.1 µm: no visible gap.
ON_CONTACT_GAP_CM = 1e-5

# The writer's whitespace -----------------------------------------------------------------------
ITEM_SEPARATOR = ", "  # between a JSON line's items (json.dumps's own)
KEY_COLON = ":"
VALUE_SPACE = " "
KEY_SEPARATOR = KEY_COLON + VALUE_SPACE  # between a key and its value (json.dumps's own)
_INDENT = "  "
PLAN_HEADER = "**Sub-instruction:**"
LAYOUT_HEADER = "**Scene Layout:**"
PLAN_OPEN = PLAN_HEADER + "\n"
STEP_SEPARATOR = "\n"  # between plan steps
# From the plan's last step to the first entry: a blank line, the layout header, the objects array.
OBJECTS_OPEN = "{\n" + _INDENT + json.dumps(OBJECTS) + KEY_SEPARATOR + "[\n" + 2 * _INDENT
LAYOUT_OPEN = "\n\n" + LAYOUT_HEADER + "\n" + OBJECTS_OPEN
ENTRY_SEPARATOR = ",\n" + 2 * _INDENT  # one entry per line
# After the last entry, up to the zone's value (which follows after VALUE_SPACE).
OBJECTS_CLOSE = "\n" + _INDENT + "]," + "\n" + _INDENT + json.dumps(ZONE) + KEY_COLON
LAYOUT_CLOSE = "\n}\n"  # after the zone's value: the end of the completion

# Plan steps: "3. Place <instance id> <where>." ---------------------------------------------------
PLACE = "Place"
STEP_NUMBER_END = ". "  # after a step's number
STEP_END = "."  # a step's sentence ends at its first full stop (ids and words carry none)


def plan_step(number: int, sub_instruction: str) -> str:
    """One line of the plan: ``3. Place 7_mug_0 on 6_saucer_0.``."""
    return f"{number}{STEP_NUMBER_END}{sub_instruction}"


def child_step(iid: str, relation: str, parent: str) -> str:
    """The sentence of the plan step that puts ``iid`` in or on ``parent``: ``Place 2_pen_0 in 1_cup_0.``
    (a table-level object's sentence says where on the table instead)."""
    return f"{PLACE} {iid} {relation} {parent}{STEP_END}"


def child_step_pattern() -> str:
    """The regex of a whole plan line written by :func:`child_step` (after its ``N. ``): groups
    ``iid``, ``relation`` (one of :data:`CHILD_RELATIONS`) and ``parent``. Ids carry no spaces or
    full stops, so ``Place X in front of Y, ...`` (a table-level step) does not match."""
    return (re.escape(PLACE) + r" (?P<iid>[^\s.]+) (?P<relation>" + "|".join(CHILD_RELATIONS)
            + r") (?P<parent>[^\s.]+)" + re.escape(STEP_END) + "$")


def step_start(number: int) -> str:
    """The fixed start of plan step ``number``, up to its instance id: ``3. Place ``."""
    return plan_step(number, PLACE + " ")


def quoted(name: str) -> str:
    """A key or string value as JSON writes it: ``"name"``."""
    return json.dumps(name)


def key_text(name: str) -> str:
    """``, "name":``: a key of an entry after the previous value, up to its value's space."""
    return ITEM_SEPARATOR + quoted(name) + KEY_COLON


def string_value_pattern(key: str) -> str:
    """The regex of ``"key": "value"`` as the writer puts it on an entry's line; group 1: the value."""
    return re.escape(quoted(key) + KEY_SEPARATOR) + r'"([^"]*)"'


def step_start_pattern(number: str = r"\d+") -> str:
    """The regex of a plan step's start up to its verb (``3. Place``); ``number``: the regex of the
    step's number (a named group where the caller reads it)."""
    return number + re.escape(STEP_NUMBER_END + PLACE)


def next_key(key: str) -> str:
    """The key written after ``key`` in its entry (object or root entry)."""
    keys = ENTRY_KEYS if key in ENTRY_KEYS else ZONE_ENTRY_KEYS
    return keys[keys.index(key) + 1]

