"""The CTRC writer: a :class:`~physcene.scene.Scene` as layered entries and as completion text.

A completion is a numbered plan of templated sub-instructions, anchor first (paper Algorithm 1),
followed by the layered layout JSON (paper appendix example); :mod:`physcene.ctrc.grammar` holds
its keys, headers and whitespace.
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter

from physcene.ctrc.frames import Frame, absolute, relative, rounded
from physcene.ctrc.grammar import (
    BOX_EXTENTS,
    DECIMALS,
    ENTRY_KEYS,
    ENTRY_SEPARATOR,
    ITEM_SEPARATOR,
    KEY_SEPARATOR,
    LAYOUT_CLOSE,
    LAYOUT_HEADER,
    LAYOUT_OPEN,
    MAX_DECIMALS,
    OBJECTS_CLOSE,
    PLACE,
    PLAN_OPEN,
    STEP_SEPARATOR,
    TABLE_RELATION,
    VALUE_SPACE,
    ZONE_ENTRY_KEYS,
    ZONE_TYPE,
    child_step,
    plan_step,
)
from physcene.graph import anchor_order, ensure_hierarchy, near_references
from physcene.scene import TABLE, Scene, SceneObject, Zone

__all__ = ["coarse_location", "completion_text", "decimals_of", "encode", "json_line", "sub_instructions",
           "usual_decimals"]

_DIRECTION_PHRASE = {"left of": "to the left of", "right of": "to the right of",
                     "in front of": "in front of", "behind": "behind"}


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
    table = Frame.of_zone(scene.zone if decimals is None
                          else Zone(*(rounded(v, decimals) for v in scene.zone.to_list())))
    entries = []
    for iid in anchor_order(scene):
        o = by_id[iid]
        frame = table if o.parent == TABLE else Frame.of_object(decoded[o.parent])
        relation = TABLE_RELATION if o.parent == TABLE else o.relation  # "on the table" is the table level
        box, rot = relative(o, frame, relation)
        box = [rounded(v, decimals) for v in box]
        if decimals is not None:  # an extent thinner than the last decimal would round to zero
            for lo, hi in BOX_EXTENTS:
                if not box[hi] > box[lo]:
                    box[hi] = rounded(box[lo] + 10.0 ** -decimals, decimals)
        rot = rounded(rot, decimals)
        if rot >= 180.0:  # canonical [-180, 180): rounding may land a hair below 180 on 180
            rot -= 360.0
        center, size, yaw = absolute(box, rot, frame, relation)
        decoded[iid] = o.moved(center=center, size=size, yaw=yaw) if decimals is not None else o
        layer[iid] = layer[o.parent] + 1
        values = (layer[iid], iid, o.category, o.parent, relation, o.description, box, rot)
        entries.append(dict(zip(ENTRY_KEYS, values, strict=True)))
    return entries


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
            out.append((iid, child_step(iid, o.relation, o.parent)))
            continue
        where = coarse_location(o, scene.zone)
        ref = refs.get(iid)
        if ref is None:
            dist = math.hypot(o.center[0] - cx, o.center[1] - cy)
            text = (f"{PLACE} {iid} at the center of the table." if where == "center"
                    else f"{PLACE} {iid} at the {where} of the table, about {dist:.0f} cm from the center.")
        else:
            rid, direction = ref
            r = by_id[rid]
            dist = math.hypot(o.center[0] - r.center[0], o.center[1] - r.center[1])
            text = (f"{PLACE} {iid} {_DIRECTION_PHRASE[direction]} {rid}, about {dist:.0f} cm away, "
                    f"at the {where} of the table.")
        out.append((iid, text))
    return out


def json_line(value) -> str:
    """``value`` as one line of JSON, with the format's separators."""
    return json.dumps(value, ensure_ascii=False, allow_nan=False, separators=(ITEM_SEPARATOR, KEY_SEPARATOR))


def completion_text(scene: Scene, *, decimals: int = DECIMALS) -> str:
    """The CTRC completion: numbered sub-instruction plan, then the layered layout JSON."""
    scene = ensure_hierarchy(scene)
    zone = [rounded(v, decimals) for v in scene.zone.to_list()]
    plan = [plan_step(k, text) for k, (_, text) in enumerate(sub_instructions(scene), start=1)]
    rows = [dict(zip(ZONE_ENTRY_KEYS, (0, TABLE, ZONE_TYPE, [*zone, 0.0, 0.0], 0.0), strict=True))]
    rows += encode(scene, decimals=decimals)
    body = ENTRY_SEPARATOR.join(json_line(r) for r in rows)
    return (PLAN_OPEN + STEP_SEPARATOR.join(plan) + LAYOUT_OPEN + body + OBJECTS_CLOSE + VALUE_SPACE
            + json_line(zone) + LAYOUT_CLOSE)


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
