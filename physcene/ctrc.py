"""CTRC, the Cognitive Topological Reasoning Chain: a layout written as text a model can learn.

A completion is a numbered plan of templated sub-instructions, anchor first (paper Algorithm 1),
followed by the layered layout JSON (paper appendix example)::

    **Sub-instruction:**
    1. Place 1_laptop_0 at the center of the table.
    2. Place 4_pen_holder_0 to the left of 1_laptop_0, about 44 cm away, at the left of the table.
    3. Place 5_pen_0 in 4_pen_holder_0.

    **Scene Layout:**
    {"objects": [
      {"layer": 0, "instance_id": "root_zone", "type": "zone", "bbox": [...], "z_rotation": 0.0},
      {"layer": 1, "instance_id": "1_laptop_0", "category": "laptop", "parent_id": "root_zone",
       "relation_type": "near", "description": "...", "relative_bbox": [xmin, xmax, ymin, ymax,
       zmin, zmax], "relative_rotation_deg": 0.0}, ...],
     "item_placement_zone": [xmin, xmax, ymin, ymax]}

Relative placement (DESIGN.md): a child's ``relative_bbox`` is its own box (own-frame extents
w, d, h, centred at its centre) written in the parent's yawed frame, x/y measured from the
parent's (xmin, ymin) corner; ``relative_rotation_deg`` = child yaw − parent yaw; z is measured
from the parent's bottom for ``in`` and from its top for ``on`` (``ON_CONTACT_GAP_CM`` above it: zmin 0
rests the child on its support without a float32 contact). Table-level objects use the
zone's (xmin, ymin) corner, no rotation, and z from the table top. All lengths in cm.

:func:`parse` is total: any string gives a :class:`~physcene.scene.Scene` or a
:class:`ParseError` with a reason; it also reads the MesaTask-style flat output of the paper's
zero-shot Prompt 3 (absolute ``position``/``size``/``z_rotation``).
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from physcene.graph import anchor_order, ensure_hierarchy, near_references
from physcene.layout import category_from_instance, load_layout
from physcene.scene import TABLE, Scene, SceneError, SceneObject, Zone, wrap_angle

__all__ = [
    "BOX_EXTENTS",
    "DECIMALS",
    "ENTRY_SEPARATOR",
    "LAYOUT_HEADER",
    "MAX_ABS_CM",
    "MAX_DECIMALS",
    "MAX_OBJECTS",
    "OBJECTS_CLOSE",
    "OBJECTS_OPEN",
    "ON_CONTACT_GAP_CM",
    "PLAN_HEADER",
    "ParseError",
    "build_prompt",
    "coarse_location",
    "completion_text",
    "decimals_of",
    "decode",
    "encode",
    "parse",
    "sub_instructions",
    "usual_decimals",
    "zero_shot_prompt",
]

# Digits after the decimal point in completion text. With the encoder's error feedback (each
# child is written relative to its parent *as decoded from the text*) the decoded pose differs
# from the original by the rounding of the object's own numbers only (≤ 1e-5 cm, ≤ 1e-5 deg),
# however deep the stack.
DECIMALS = 5
# Most digits after the point a completion may write: the CTRC constraint's number rule stops a model
# there (no digits forever), so data written for training stays within it too.
MAX_DECIMALS = 8
# Coordinates or sizes beyond this (cm, 1 km) are model garbage, not a tabletop.
MAX_ABS_CM = 1e5
# Completions longer than this are not layouts; refusing them bounds parse time.
MAX_CHARS = 200_000
# More objects than this is not a tabletop (MesaTask's largest scenes have a few dozen); refusing
# them keeps downstream O(n^2) graph and physics work bounded.
MAX_OBJECTS = 1000
# The completion's fixed text (completion_text writes it; train/constrained.py steers a model along it):
# the plan header, the layout header, and the layout JSON's frame around the object entries.
PLAN_HEADER = "**Sub-instruction:**"
LAYOUT_HEADER = "**Scene Layout:**"
OBJECTS_OPEN = '{\n  "objects": [\n    '
ENTRY_SEPARATOR = ",\n    "
OBJECTS_CLOSE = '\n  ],\n  "item_placement_zone":'
# An ``on`` child's relative z is measured from this far above its support's top, so relative zmin 0
# ("resting on it") decodes 1e-5 cm above the top: exact contact reads as float32 noise, ~1e-7-1e-6 cm
# of penetration that counts at the paper's 0 cm threshold (and costs the reward its +50). TTO rests
# on children the same distance up (configs/tto.yaml contact_gap_cm). 0.1 µm: no visible gap.
ON_CONTACT_GAP_CM = 1e-5
# (min, max) index pairs of a relative box [xmin, xmax, ymin, ymax, zmin, zmax], x then y then z (the
# zone's [xmin, xmax, ymin, ymax] is the first two).
BOX_EXTENTS = ((0, 1), (2, 3), (4, 5))
# How many candidate '{' positions the JSON search tries before giving up.
_MAX_JSON_ATTEMPTS = 256

_RELATION_ALIASES = {
    "in": "in", "inside": "in", "inside_of": "in", "in_container": "in", "contained_in": "in",
    "within": "in",
    "on": "on", "on_top": "on", "on_top_of": "on", "on_surface": "on", "supported_by": "on",
    "stacked_on": "on",
    "near": "near", "next_to": "near", "beside": "near", "on_table": "near", "table": "near",
}
_DIRECTION_PHRASE = {"left of": "to the left of", "right of": "to the right of",
                     "in front of": "in front of", "behind": "behind"}


@dataclass(frozen=True)
class ParseError:
    """A completion that is not a layout. A value, never raised: ``reason`` says why."""

    reason: str

    def __str__(self) -> str:
        return self.reason


# Relative frames ------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Frame:
    """Where a child's relative box is measured from: corner (cm), yaw (rad), z bases (cm)."""

    x0: float
    y0: float
    yaw: float
    z_in: float
    z_on: float

    @classmethod
    def of_zone(cls, zone: Zone) -> _Frame:
        return cls(zone.xmin, zone.ymin, 0.0, 0.0, 0.0)

    @classmethod
    def of_object(cls, o: SceneObject) -> _Frame:
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        hw, hd = 0.5 * o.size[0], 0.5 * o.size[1]
        return cls(o.center[0] - c * hw + s * hd, o.center[1] - s * hw - c * hd, o.yaw, o.zmin,
                   o.zmax + ON_CONTACT_GAP_CM)

    def z_base(self, relation: str) -> float:
        return self.z_in if relation == "in" else self.z_on


def _relative(o: SceneObject, frame: _Frame, relation: str) -> tuple[list[float], float]:
    """(relative_bbox [xmin, xmax, ymin, ymax, zmin, zmax] cm, relative rotation deg)."""
    c, s = math.cos(frame.yaw), math.sin(frame.yaw)
    dx, dy = o.center[0] - frame.x0, o.center[1] - frame.y0
    rx, ry = c * dx + s * dy, -s * dx + c * dy
    zb = frame.z_base(relation)
    hw, hd = 0.5 * o.size[0], 0.5 * o.size[1]
    box = [rx - hw, rx + hw, ry - hd, ry + hd, o.zmin - zb, o.zmax - zb]
    if relation == "on" and -2.0 * ON_CONTACT_GAP_CM <= box[4] < 0.0:  # touching (no gap): resting on it
        box[4], box[5] = 0.0, box[5] - box[4]
    return box, math.degrees(wrap_angle(o.yaw - frame.yaw))


def _absolute(box: Sequence[float], rot_deg: float, frame: _Frame, relation: str):
    """(center (3,), size (3,), yaw rad) of a relative box; inverse of :func:`_relative`."""
    rx, ry = 0.5 * (box[0] + box[1]), 0.5 * (box[2] + box[3])
    c, s = math.cos(frame.yaw), math.sin(frame.yaw)
    cz = frame.z_base(relation) + 0.5 * (box[4] + box[5])
    center = (frame.x0 + c * rx - s * ry, frame.y0 + s * rx + c * ry, cz)
    size = (box[1] - box[0], box[3] - box[2], box[5] - box[4])
    return center, size, wrap_angle(frame.yaw + math.radians(rot_deg))


def _rounded(v: float, decimals: int | None) -> float:
    return v if decimals is None else round(v, decimals) + 0.0  # + 0.0 turns -0.0 into 0.0


# Encode / decode ------------------------------------------------------------------------------
def encode(scene: Scene, *, decimals: int | None = None) -> list[dict]:
    """The layered CTRC entries of ``scene`` in Algorithm-1 order (the zone entry excluded).

    Each entry: ``layer`` (1 = on the table), ``instance_id``, ``category``, ``parent_id``,
    ``relation_type`` (in/on/near), ``description``, ``relative_bbox`` [xmin, xmax, ymin, ymax,
    zmin, zmax] cm and ``relative_rotation_deg``. A scene without a hierarchy gets one
    (:func:`physcene.graph.build_hierarchy`). With ``decimals`` the numbers are rounded, each
    relative to its parent as it will be decoded, so rounding errors do not pile up down a stack.
    """
    scene = ensure_hierarchy(scene)
    by_id = scene.by_id()
    decoded: dict[str, SceneObject] = {}  # the pose a reader of the entries will reconstruct
    layer: dict[str, int] = {TABLE: 0}
    # Table-level boxes are measured from the zone corner the text will carry (rounded too).
    table = _Frame.of_zone(scene.zone if decimals is None
                           else Zone(*(_rounded(v, decimals) for v in scene.zone.to_list())))
    entries = []
    for iid in anchor_order(scene):
        o = by_id[iid]
        frame = table if o.parent == TABLE else _Frame.of_object(decoded[o.parent])
        relation = "near" if o.parent == TABLE else o.relation  # "on the table" is the table level
        box, rot = _relative(o, frame, relation)
        box = [_rounded(v, decimals) for v in box]
        if decimals is not None:  # an extent thinner than the last decimal would round to zero
            for lo, hi in BOX_EXTENTS:
                if not box[hi] > box[lo]:
                    box[hi] = _rounded(box[lo] + 10.0 ** -decimals, decimals)
        rot = _rounded(rot, decimals)
        if rot >= 180.0:  # canonical [-180, 180): rounding may land a hair below 180 on 180
            rot -= 360.0
        center, size, yaw = _absolute(box, rot, frame, relation)
        decoded[iid] = o.moved(center=center, size=size, yaw=yaw) if decimals is not None else o
        layer[iid] = layer[o.parent] + 1
        entries.append({
            "layer": layer[iid],
            "instance_id": iid,
            "category": o.category,
            "parent_id": o.parent,
            "relation_type": relation,
            "description": o.description,
            "relative_bbox": box,
            "relative_rotation_deg": rot,
        })
    return entries


def _field(entry: dict, key: str, iid: str | None, kinds, default=None):
    """``entry[key]`` checked against ``kinds`` (booleans are never numbers); None -> default."""
    value = entry.get(key, default)
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, kinds):
        raise SceneError(f"wrong type {type(value).__name__}", obj=iid, field=key)
    return value


def _finite(value, *, iid: str, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(f"expected a number, got {value!r:.40}", obj=iid, field=field)
    v = float(value)
    if not math.isfinite(v):
        raise SceneError(f"non-finite value {value!r}", obj=iid, field=field)
    if abs(v) > MAX_ABS_CM:
        raise SceneError(f"absurd magnitude {v:g} (limit {MAX_ABS_CM:g})", obj=iid, field=field)
    return v


def _relative_box(value, iid: str) -> list[float]:
    if not isinstance(value, list) or len(value) != 6:
        raise SceneError("expected [xmin, xmax, ymin, ymax, zmin, zmax]", obj=iid, field="relative_bbox")
    box = [_finite(v, iid=iid, field="relative_bbox") for v in value]
    for axis, (lo, hi) in zip("xyz", BOX_EXTENTS):
        if not box[hi] > box[lo]:
            raise SceneError(f"{axis}max {box[hi]:g} must exceed {axis}min {box[lo]:g} (non-positive extent)",
                             obj=iid, field="relative_bbox")
    return box


def _relation(entry: dict, iid: str, parent: str) -> str:
    raw = _field(entry, "relation_type", iid, str, entry.get("relation"))
    if raw is None:
        if parent == TABLE:
            return "near"
        raise SceneError("missing", obj=iid, field="relation_type")
    rel = _RELATION_ALIASES.get(raw.strip().lower().replace(" ", "_").replace("-", "_"))
    if rel is None:
        raise SceneError(f"unknown relation {raw!r:.40} (expected in, on or near)", obj=iid,
                         field="relation_type")
    if parent == TABLE:
        if rel == "in":
            raise SceneError(f"nothing can be 'in' {TABLE}", obj=iid, field="relation_type")
        return "near"  # "on the table" is the table level
    if rel == "near":
        raise SceneError(f"'near' is a table-level relation; parent must be {TABLE}", obj=iid,
                         field="relation_type")
    return rel


def decode(entries: Iterable[dict], zone: Zone, *, scene_type: str = "", instruction: str = "",
           restricted_zones: Sequence[Zone] = ()) -> Scene:
    """The absolute :class:`Scene` of layered CTRC entries (inverse of :func:`encode`).

    Entries may come in any order; the zone entry (``instance_id`` root_zone) is skipped. Raises
    :class:`~physcene.scene.SceneError` naming the object and field for any invalid entry
    (unknown parent, cycle, duplicate id, non-positive extent, absurd magnitude, wrong type).
    """
    if isinstance(zone, (list, tuple)):
        zone = Zone.from_list(zone)
    parsed: dict[str, tuple] = {}
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise SceneError(f"expected an object, got {type(entry).__name__}", field=f"objects[{k}]")
        if entry.get("type") == "zone":
            continue
        iid = entry.get("instance_id", entry.get("instance"))
        if not isinstance(iid, str) or not iid.strip():
            raise SceneError(f"missing or empty instance_id {iid!r:.40}", field=f"objects[{k}].instance_id")
        if iid == TABLE:
            continue
        if iid in parsed:
            raise SceneError("duplicate instance id", obj=iid, field="instance_id")
        layer = _field(entry, "layer", iid, int)  # redundant with the parents: type-checked only
        if layer is not None and layer < 0:
            raise SceneError(f"negative layer {layer}", obj=iid, field="layer")
        parent = _field(entry, "parent_id", iid, str, TABLE)
        relation = _relation(entry, iid, parent)
        box = _relative_box(entry.get("relative_bbox"), iid)
        rot = _finite(_field(entry, "relative_rotation_deg", iid, (int, float), 0.0), iid=iid,
                      field="relative_rotation_deg")
        category = _field(entry, "category", iid, str) or category_from_instance(iid)
        description = _field(entry, "description", iid, str, "")
        asset = _field(entry, "asset_id", iid, str, entry.get("retrieved_uid"))
        parsed[iid] = (parent, relation, box, rot, category, description, asset)
    for iid, (parent, *_rest) in parsed.items():
        if parent != TABLE and parent not in parsed:
            raise SceneError(f"unknown parent {parent!r:.60}", obj=iid, field="parent_id")

    objects: dict[str, SceneObject] = {}
    for start in parsed:
        chain, on_chain = [], set()  # walk up to a decoded ancestor, then decode back down
        node = start
        while node != TABLE and node not in objects:
            if node in on_chain:
                cycle = chain[chain.index(node):] + [node]
                raise SceneError(f"parent cycle {' -> '.join(cycle)}", obj=node, field="parent_id")
            chain.append(node)
            on_chain.add(node)
            node = parsed[node][0]
        for iid in reversed(chain):
            parent, relation, box, rot, category, description, asset = parsed[iid]
            frame = _Frame.of_zone(zone) if parent == TABLE else _Frame.of_object(objects[parent])
            center, size, yaw = _absolute(box, rot, frame, relation)
            for v in center:
                if abs(v) > MAX_ABS_CM:
                    raise SceneError(f"absolute position {v:g} beyond {MAX_ABS_CM:g}", obj=iid,
                                     field="relative_bbox")
            objects[iid] = SceneObject(instance_id=iid, category=category, center=center, size=size,
                                       yaw=yaw, description=description, asset_id=asset, parent=parent,
                                       relation=relation)
    return Scene(zone=zone, objects=tuple(objects[i] for i in parsed), scene_type=scene_type,
                 instruction=instruction, restricted_zones=tuple(restricted_zones))


# Text -----------------------------------------------------------------------------------------
def coarse_location(o: SceneObject, zone: Zone) -> str:
    """Where ``o``'s centre falls on a 3×3 grid of the zone: "center", "left back", "front", ..."""
    fx = (o.center[0] - zone.xmin) / zone.width
    fy = (o.center[1] - zone.ymin) / zone.depth
    col = "left" if fx < 1 / 3 else "right" if fx > 2 / 3 else ""
    row = "front" if fy < 1 / 3 else "back" if fy > 2 / 3 else ""
    return " ".join(p for p in (col, row) if p) or "center"


def sub_instructions(scene: Scene) -> list[tuple[str, str]]:
    """(instance id, templated sub-instruction) per object, in Algorithm-1 order."""
    scene = ensure_hierarchy(scene)
    by_id = scene.by_id()
    refs = near_references(scene)
    cx, cy = scene.zone.center
    out = []
    for iid in anchor_order(scene):
        o = by_id[iid]
        if o.parent != TABLE:
            out.append((iid, f"Place {iid} {o.relation} {o.parent}."))
            continue
        where = coarse_location(o, scene.zone)
        ref = refs.get(iid)
        if ref is None:
            dist = math.hypot(o.center[0] - cx, o.center[1] - cy)
            text = (f"Place {iid} at the center of the table." if where == "center"
                    else f"Place {iid} at the {where} of the table, about {dist:.0f} cm from the center.")
        else:
            rid, direction = ref
            r = by_id[rid]
            dist = math.hypot(o.center[0] - r.center[0], o.center[1] - r.center[1])
            text = (f"Place {iid} {_DIRECTION_PHRASE[direction]} {rid}, about {dist:.0f} cm away, "
                    f"at the {where} of the table.")
        out.append((iid, text))
    return out


def _json_line(value) -> str:
    return json.dumps(value, ensure_ascii=False, allow_nan=False)


def completion_text(scene: Scene, *, decimals: int = DECIMALS) -> str:
    """The CTRC completion: numbered sub-instruction plan, then the layered layout JSON."""
    scene = ensure_hierarchy(scene)
    zone = [_rounded(v, decimals) for v in scene.zone.to_list()]
    plan = [f"{k}. {text}" for k, (_, text) in enumerate(sub_instructions(scene), start=1)]
    rows = [{"layer": 0, "instance_id": TABLE, "type": "zone", "bbox": [*zone, 0.0, 0.0], "z_rotation": 0.0}]
    rows += encode(scene, decimals=decimals)
    body = ENTRY_SEPARATOR.join(_json_line(r) for r in rows)
    return (PLAN_HEADER + "\n" + "\n".join(plan) + "\n\n" + LAYOUT_HEADER + "\n"
            + OBJECTS_OPEN + body + OBJECTS_CLOSE + " " + _json_line(zone) + "\n}\n")


_FRACTION = re.compile(r"-?\d+\.(\d+)")


def decimals_of(completion: str) -> int:
    """Digits after the point a completion's layout was written with: the most any of its numbers
    has (0 when all are whole: JSON writes ``12.0``), at most ``MAX_DECIMALS``. The inverse of
    ``completion_text(scene, decimals=...)`` for text that function wrote, which is how a dataset's
    completions are re-written at their own precision after their layouts change.
    """
    return min(max(_fraction_digits(completion), default=0), MAX_DECIMALS)


def usual_decimals(completion: str) -> int:
    """The digits after the point most of a completion's layout numbers have (those with any; ties:
    the more digits; 0 when all are whole), at most ``MAX_DECIMALS``. Unlike :func:`decimals_of`, one
    stray long number a model wrote (``1.06386999``) does not set the precision of the rest: text
    re-written from a model's output at its usual precision stays at its training data's."""
    digits = Counter(d for d in _fraction_digits(completion) if d > 0)
    if not digits:
        return 0
    return min(max(digits, key=lambda d: (digits[d], d)), MAX_DECIMALS)


def _fraction_digits(completion: str) -> list[int]:
    """Per number of the layout, its digits after the point (trailing zeros dropped)."""
    start = completion.find(LAYOUT_HEADER)
    return [len(m.group(1).rstrip("0")) for m in _FRACTION.finditer(completion, max(start, 0))]


def _object_list(objects) -> str:
    counts: dict[str, int] = {}
    for o in objects:
        name = o.category if isinstance(o, SceneObject) else category_from_instance(str(o))
        name = name.replace("_", " ")
        counts[name] = counts.get(name, 0) + 1
    return ", ".join(f"{name} ({n})" for name, n in counts.items())


def _zone_list(zone) -> list[float]:
    return (zone if isinstance(zone, Zone) else Zone.from_list(zone)).to_list()


def build_prompt(instruction: str, scene_type: str, zone, objects=None, *, restricted_zones=()) -> str:
    """The CTRC generation prompt: instruction, table type, placement zone, optional object list.

    ``zone``: a :class:`Zone` or [xmin, xmax, ymin, ymax] cm; ``objects``: SceneObjects,
    categories or instance ids (counted per category), or None to let the model choose;
    ``restricted_zones``: Zones or rects (sinks) where nothing may stand, listed when given.
    """
    zone_vals = [round(v, 2) + 0.0 for v in _zone_list(zone)]
    lines = [
        "Generate a physically plausible layout of objects on the tabletop: nothing may float or "
        "interpenetrate.",
        f"**Instruction**: {instruction}",
        f"**Table type**: {scene_type}",
        f"**item_placement_zone**: {_json_line(zone_vals)} (cm; origin at the near-left corner, "
        "+x right, +y away from the viewer, +z up; the table top is z = 0)",
    ]
    if restricted_zones:
        rects = [[round(v, 2) + 0.0 for v in _zone_list(z)] for z in restricted_zones]
        lines.append(f"**restricted_zone**: {_json_line(rects)} (nothing may stand there)")
    if objects:
        lines.append(f"**Object List**: {_object_list(objects)}")
    lines += [
        "",
        "First write **Sub-instruction:** as a numbered plan, one step per object: the anchor "
        "(the object closest to the table centre) first, then table-level objects by proximity, "
        "each container's or support's contents right after it, bottom-up.",
        "Then write **Scene Layout:** as JSON with \"objects\" (a root_zone entry, then one entry "
        "per object with layer, instance_id, category, parent_id, relation_type in/on/near, "
        "description, relative_bbox [xmin, xmax, ymin, ymax, zmin, zmax] in cm in the parent's "
        "frame from its (xmin, ymin) corner, z from the parent's bottom for \"in\" and its top for "
        "\"on\", and relative_rotation_deg) and \"item_placement_zone\".",
    ]
    return "\n".join(lines)


_ZERO_SHOT = """You are tasked with generating a scene graph layout for a tabletop arrangement based on the \
following instructions and parameters.

### TASK:
Your primary goal is to output a **VALID JSON OBJECT** that strictly follows the specified format between \
the `<json>` tokens. This JSON must represent the scene graph layout for objects placed on a tabletop.

### INPUT PARAMETERS:
1. **Tabletop Information:**
   - The tabletop's dimensions are defined by the "item_placement_zone" with the following boundaries:
     **item_placement_zone**: {zone}
     Units are in centimeters (cm).

2. **Placement Instructions:**
   - Follow the natural language instructions to determine the placement of objects:
     **Instructions**: "{instruction}"

3. **Objects Cluster:**
   - The objects to be placed on the tabletop are listed below. Each object must have:
     - A **unique instance name**.
     - **Reasonable dimensions** (width, depth, height in cm).
     - A **position** within the specified tabletop boundaries.
     - A **z_rotation** (rotation around the vertical axis in radians). If not specified, assume \
`z_rotation = 0.0`.
     - A **short description** that explains the object's purpose or appearance.
     **Objects cluster**: {objects}

### OUTPUT REQUIREMENTS:
- You must output a **VALID JSON OBJECT** strictly between the `<json>` tokens.
  (not <json>xxx</json>)
- The JSON must have the following structure:

<json>
{{
    "item_placement_zone": [
        x_min,
        x_max,
        y_min,
        y_max
    ],
    "objects": [
        {{
            "instance": "unique_object_name",
            "z_rotation": float,
            "size": [width, depth, height],
            "position": [x, y, z],
            "description": "short description of the object"
        }},
        ...
    ]
}}
<json>

### DETAILED GUIDELINES:
1. **Object Placement:**
   - Ensure that all objects are placed within the boundaries of the `item_placement_zone`.
   - Follow the placement logic specified in the instructions. For example:
     - If an object should be placed in a corner, position it near the respective boundary.
     - If objects need to be grouped closely, ensure their positions are adjacent within reasonable \
spacing (e.g., 2-5 cm).

2. **Object Properties:**
   - Assign **realistic dimensions** to each object based on its type. For instance:
     - A woven basket might have dimensions like `[20.0, 15.0, 12.0]` (width, depth, height).
     - A lotion bottle might have dimensions like `[5.0, 5.0, 15.0]`.
   - Use **intuitive and consistent instance names** (e.g., "woven_basket_0", "lotion_bottle_1").
   - Set the `z_rotation` to `0.0` unless the object is explicitly rotated in the instructions.

3. **Avoid Overlapping:**
   - Ensure objects do not overlap or extend beyond the tabletop boundaries.
   - Maintain logical spacing between objects unless the instructions specify otherwise.

4. **Avoid Suspension:**
    - Ensure that the items are firmly placed on the table. The position of each asset is the center \
coordinate, so the z value cannot be zero. If it is on the table, it should be half of the asset's height.
    - If there is a stacking situation, the z coordinate of the upper asset should be the sum of the z \
coordinate of the lower asset and half of the height of both assets.

5. **Output Validation:**
   - Ensure the JSON is valid by checking for correct syntax (e.g., no trailing commas, proper nesting of \
keys and values).

IMPORTANT:
The JSON output MUST be placed between the <json> tokens.
If you encounter ambiguity, use logical reasoning to infer the most likely placement or dimensions.
DO NOT include any additional text or explanations outside the <json> tokens in the output."""


def zero_shot_prompt(instruction: str, zone, objects) -> str:
    """The paper's Prompt 3 (zero-shot LLM layout, MesaTask flat JSON between ``<json>`` tokens)."""
    return _ZERO_SHOT.format(zone=_json_line([round(v, 2) + 0.0 for v in _zone_list(zone)]),
                             instruction=instruction, objects=_object_list(objects))


# Parsing --------------------------------------------------------------------------------------
class _Reject(ValueError):
    """A completion is not a layout; the message is the ParseError reason."""


def _reject_constant(name: str):
    raise _Reject(f"non-finite number {name} in the JSON")


# strict=False: a raw newline or tab inside a string (a wrapped description) is not worth a -100.
_DECODER = json.JSONDecoder(parse_constant=_reject_constant, strict=False)
_TRAILING_COMMA = re.compile(r",\s*([}\]])")
_FENCE = re.compile(r"```[a-zA-Z]*\s*\n?(.*?)(?:```|$)", re.S)
_JSON_TOKEN = re.compile(r"</?json>", re.I)


def _layout_in(value, depth: int = 0):
    """The first dict with an "objects" key in ``value`` (a layout wrapped in one more key is fine)."""
    if isinstance(value, dict):
        if "objects" in value:
            return value
        if depth < 2:
            for v in value.values():
                found = _layout_in(v, depth + 1)
                if found is not None:
                    return found
    return None


def _search_json(segment: str, errors: list[str]):
    pos = segment.find("{")
    attempts = 0
    while pos >= 0 and attempts < _MAX_JSON_ATTEMPTS:
        attempts += 1
        try:
            value, end = _DECODER.raw_decode(segment, pos)
        except json.JSONDecodeError as exc:
            errors.append(f"invalid JSON ({exc.msg} at char {exc.pos - pos} of the object)")
            pos = segment.find("{", pos + 1)
            continue
        except _Reject as exc:
            errors.append(str(exc))
            pos = segment.find("{", pos + 1)
            continue
        except RecursionError:
            raise _Reject("JSON nested too deeply") from None
        except ValueError as exc:  # e.g. an integer literal with thousands of digits
            errors.append(f"invalid JSON ({exc})")
            pos = segment.find("{", pos + 1)
            continue
        found = _layout_in(value)
        if found is not None:
            return found
        pos = segment.find("{", end)
    return None


def _segments(text: str) -> list[str]:
    """Where the layout JSON may be, most specific first."""
    out = []
    parts = _JSON_TOKEN.split(text)
    if len(parts) > 1:
        out += parts[1:]  # after each <json> token (Prompt 3 closes with <json> again)
    out += [m.group(1) for m in _FENCE.finditer(text)]
    marker = text.rfind("Scene Layout")
    if marker >= 0:
        out.append(text[marker:])
    out.append(text)
    seen, unique = set(), []
    for s in out:
        if s.strip() and s not in seen:
            seen.add(s)
            unique.append(s)
    return unique


def _extract_layout(text: str) -> dict:
    errors: list[str] = []
    for lenient in (False, True):
        for segment in _segments(text):
            if lenient:
                segment = _TRAILING_COMMA.sub(r"\1", segment)
            found = _search_json(segment, errors)
            if found is not None:
                return found
    if "{" not in text:
        raise _Reject("no JSON object in the completion")
    detail = errors[0] if errors else "no object with an \"objects\" list"
    raise _Reject(f"no complete layout JSON (truncated or malformed: {detail})")


def _zone_from(data: dict, zone) -> Zone:
    if zone is not None:
        return zone if isinstance(zone, Zone) else Zone.from_list(zone)
    raw = data.get("item_placement_zone")
    if raw is None:
        entries = data.get("objects")
        for e in entries if isinstance(entries, list) else []:
            if isinstance(e, dict) and (e.get("type") == "zone" or e.get("instance_id") == TABLE):
                bbox = e.get("bbox")
                raw = bbox[:4] if isinstance(bbox, list) else bbox
                break
    if raw is None:
        raise _Reject("no item_placement_zone in the completion and none given")
    if not isinstance(raw, list) or len(raw) != 4:
        raise SceneError("expected [xmin, xmax, ymin, ymax]", field="item_placement_zone")
    vals = [_finite(v, iid=None, field="item_placement_zone") for v in raw]
    return Zone.from_list(vals, field="item_placement_zone")


def _is_flat(entries) -> bool:
    if isinstance(entries, dict):
        return True  # MesaTask objects keyed by instance
    rows = [e for e in entries if isinstance(e, dict) and e.get("type") != "zone"
            and e.get("instance_id") != TABLE]
    return bool(rows) and not any("relative_bbox" in e for e in rows) and any("position" in e for e in rows)


def _parse_flat(data: dict, zone: Zone, **scene_fields) -> Scene:
    entries = data["objects"]
    if isinstance(entries, list):
        entries = [({"instance": e.get("instance_id", e.get("name")), **e}
                    if isinstance(e, dict) and "instance" not in e else e) for e in entries]
    layout = {"item_placement_zone": zone.to_list(), "objects": entries}
    scene = load_layout(layout, source="completion")
    for o in scene.objects:
        for field, values in (("position", o.center), ("size", o.size)):
            for v in values:
                if abs(v) > MAX_ABS_CM:
                    raise SceneError(f"absurd magnitude {v:g} (limit {MAX_ABS_CM:g})", obj=o.instance_id,
                                     field=field)
    return Scene(zone=zone, objects=scene.objects, **scene_fields)


def _parse(text, zone, scene_fields) -> Scene:
    if not isinstance(text, str):
        raise _Reject(f"expected a string completion, got {type(text).__name__}")
    if not text.strip():
        raise _Reject("empty completion")
    if len(text) > MAX_CHARS:
        raise _Reject(f"completion of {len(text)} characters exceeds {MAX_CHARS}")
    data = _extract_layout(text)
    entries = data["objects"]
    if not isinstance(entries, (list, dict)):
        raise _Reject(f"\"objects\" must be a list, got {type(entries).__name__}")
    if len(entries) > MAX_OBJECTS:
        raise _Reject(f"{len(entries)} objects exceed the limit of {MAX_OBJECTS}")
    zone = _zone_from(data, zone)
    if _is_flat(entries):
        scene = _parse_flat(data, zone, **scene_fields)
    else:
        scene = decode(entries, zone, **scene_fields)
    if not scene.objects:
        raise _Reject("the layout has no objects")
    return scene


def parse(text: str, *, zone=None, scene_type: str = "", instruction: str = "",
          restricted_zones: Sequence[Zone] = ()) -> Scene | ParseError:
    """A :class:`Scene` from a completion, or a :class:`ParseError` saying why not. Never raises.

    Reads CTRC completions (plan + layered JSON) and MesaTask flat JSON (Prompt 3; absolute
    ``position``/``size``/``z_rotation``, no hierarchy: call
    :func:`physcene.graph.build_hierarchy` if you need one). The JSON may sit after the plan,
    between ``<json>`` tokens or in a code fence; trailing commas are forgiven. ``zone`` (a
    :class:`Zone` or [xmin, xmax, ymin, ymax] cm), when given, is the table the task set and
    overrides the completion's ``item_placement_zone``. A layout with no objects is an error.
    """
    scene_fields = {"scene_type": scene_type, "instruction": instruction,
                    "restricted_zones": tuple(restricted_zones)}
    try:
        return _parse(text, zone, scene_fields)
    except RecursionError:
        return ParseError("JSON nested too deeply")
    except Exception as exc:  # the boundary: model output must never crash the caller
        reason = str(exc).strip()
        if not isinstance(exc, (_Reject, SceneError)):
            reason = f"{type(exc).__name__}: {reason}" if reason else type(exc).__name__
        return ParseError(reason or type(exc).__name__)
