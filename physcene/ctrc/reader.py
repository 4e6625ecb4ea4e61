"""The CTRC reader: completion text -> :class:`~physcene.scene.Scene`, or a :class:`ParseError`.

:func:`parse` is total: any string gives a Scene or a ParseError with a reason; it also reads the
MesaTask-style flat output of the paper's zero-shot Prompt 3 (absolute ``position``/``size``/
``z_rotation``). :func:`decode` inverts :func:`physcene.ctrc.writer.encode`.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from physcene.ctrc.frames import Frame, absolute
from physcene.ctrc.grammar import (
    BOX_EXTENTS,
    BOX_LENGTH,
    CATEGORY,
    DESCRIPTION,
    INSTANCE_ID,
    LAYER,
    MAX_ABS_CM,
    MAX_CHARS,
    MAX_OBJECTS,
    OBJECTS,
    PARENT_ID,
    RELATION_ALIASES,
    RELATION_TYPE,
    RELATIVE_BBOX,
    RELATIVE_ROTATION,
    TABLE_RELATION,
    TYPE,
    ZONE,
    ZONE_BBOX,
    ZONE_LENGTH,
    ZONE_TYPE,
)
from physcene.layout import category_from_instance, load_layout
from physcene.scene import TABLE, Scene, SceneError, SceneObject, Zone

__all__ = ["ParseError", "decode", "parse"]

# How many candidate '{' positions the JSON search tries before giving up.
_MAX_JSON_ATTEMPTS = 256


@dataclass(frozen=True)
class ParseError:
    """A completion that is not a layout. A value, never raised: ``reason`` says why."""

    reason: str

    def __str__(self) -> str:
        return self.reason


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
    if not isinstance(value, list) or len(value) != BOX_LENGTH:
        raise SceneError("expected [xmin, xmax, ymin, ymax, zmin, zmax]", obj=iid, field=RELATIVE_BBOX)
    box = [_finite(v, iid=iid, field=RELATIVE_BBOX) for v in value]
    for axis, (lo, hi) in zip("xyz", BOX_EXTENTS):
        if not box[hi] > box[lo]:
            raise SceneError(f"{axis}max {box[hi]:g} must exceed {axis}min {box[lo]:g} (non-positive extent)",
                             obj=iid, field=RELATIVE_BBOX)
    return box


def _relation(entry: dict, iid: str, parent: str) -> str:
    raw = _field(entry, RELATION_TYPE, iid, str, entry.get("relation"))
    if raw is None:
        if parent == TABLE:
            return TABLE_RELATION
        raise SceneError("missing", obj=iid, field=RELATION_TYPE)
    rel = RELATION_ALIASES.get(raw.strip().lower().replace(" ", "_").replace("-", "_"))
    if rel is None:
        raise SceneError(f"unknown relation {raw!r:.40} (expected in, on or near)", obj=iid,
                         field=RELATION_TYPE)
    if parent == TABLE:
        if rel == "in":
            raise SceneError(f"nothing can be 'in' {TABLE}", obj=iid, field=RELATION_TYPE)
        return TABLE_RELATION  # "on the table" is the table level
    if rel == TABLE_RELATION:
        raise SceneError(f"'{TABLE_RELATION}' is a table-level relation; parent must be {TABLE}", obj=iid,
                         field=RELATION_TYPE)
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
            raise SceneError(f"expected an object, got {type(entry).__name__}", field=f"{OBJECTS}[{k}]")
        if entry.get(TYPE) == ZONE_TYPE:
            continue
        iid = entry.get(INSTANCE_ID, entry.get("instance"))
        if not isinstance(iid, str) or not iid.strip():
            raise SceneError(f"missing or empty instance_id {iid!r:.40}",
                             field=f"{OBJECTS}[{k}].{INSTANCE_ID}")
        if iid == TABLE:
            continue
        if iid in parsed:
            raise SceneError("duplicate instance id", obj=iid, field=INSTANCE_ID)
        layer = _field(entry, LAYER, iid, int)  # redundant with the parents: type-checked only
        if layer is not None and layer < 0:
            raise SceneError(f"negative layer {layer}", obj=iid, field=LAYER)
        parent = _field(entry, PARENT_ID, iid, str, TABLE)
        relation = _relation(entry, iid, parent)
        box = _relative_box(entry.get(RELATIVE_BBOX), iid)
        rot = _finite(_field(entry, RELATIVE_ROTATION, iid, (int, float), 0.0), iid=iid,
                      field=RELATIVE_ROTATION)
        category = _field(entry, CATEGORY, iid, str) or category_from_instance(iid)
        description = _field(entry, DESCRIPTION, iid, str, "")
        asset = _field(entry, "asset_id", iid, str, entry.get("retrieved_uid"))
        parsed[iid] = (parent, relation, box, rot, category, description, asset)
    for iid, (parent, *_rest) in parsed.items():
        if parent != TABLE and parent not in parsed:
            raise SceneError(f"unknown parent {parent!r:.60}", obj=iid, field=PARENT_ID)

    objects: dict[str, SceneObject] = {}
    for start in parsed:
        chain, on_chain = [], set()  # walk up to a decoded ancestor, then decode back down
        node = start
        while node != TABLE and node not in objects:
            if node in on_chain:
                cycle = chain[chain.index(node):] + [node]
                raise SceneError(f"parent cycle {' -> '.join(cycle)}", obj=node, field=PARENT_ID)
            chain.append(node)
            on_chain.add(node)
            node = parsed[node][0]
        for iid in reversed(chain):
            parent, relation, box, rot, category, description, asset = parsed[iid]
            frame = Frame.of_zone(zone) if parent == TABLE else Frame.of_object(objects[parent])
            center, size, yaw = absolute(box, rot, frame, relation)
            for v in center:
                if abs(v) > MAX_ABS_CM:
                    raise SceneError(f"absolute position {v:g} beyond {MAX_ABS_CM:g}", obj=iid,
                                     field=RELATIVE_BBOX)
            objects[iid] = SceneObject(instance_id=iid, category=category, center=center, size=size,
                                       yaw=yaw, description=description, asset_id=asset, parent=parent,
                                       relation=relation)
    return Scene(zone=zone, objects=tuple(objects[i] for i in parsed), scene_type=scene_type,
                 instruction=instruction, restricted_zones=tuple(restricted_zones))



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
        if OBJECTS in value:
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
    raw = data.get(ZONE)
    if raw is None:
        entries = data.get(OBJECTS)
        for e in entries if isinstance(entries, list) else []:
            if isinstance(e, dict) and (e.get(TYPE) == ZONE_TYPE or e.get(INSTANCE_ID) == TABLE):
                bbox = e.get(ZONE_BBOX)
                raw = bbox[:ZONE_LENGTH] if isinstance(bbox, list) else bbox
                break
    if raw is None:
        raise _Reject("no item_placement_zone in the completion and none given")
    if not isinstance(raw, list) or len(raw) != ZONE_LENGTH:
        raise SceneError("expected [xmin, xmax, ymin, ymax]", field=ZONE)
    vals = [_finite(v, iid=None, field=ZONE) for v in raw]
    return Zone.from_list(vals, field=ZONE)


def _is_flat(entries) -> bool:
    if isinstance(entries, dict):
        return True  # MesaTask objects keyed by instance
    rows = [e for e in entries if isinstance(e, dict) and e.get(TYPE) != ZONE_TYPE
            and e.get(INSTANCE_ID) != TABLE]
    return bool(rows) and not any(RELATIVE_BBOX in e for e in rows) and any("position" in e for e in rows)


def _parse_flat(data: dict, zone: Zone, **scene_fields) -> Scene:
    entries = data[OBJECTS]
    if isinstance(entries, list):
        entries = [({"instance": e.get(INSTANCE_ID, e.get("name")), **e}
                    if isinstance(e, dict) and "instance" not in e else e) for e in entries]
    layout = {ZONE: zone.to_list(), OBJECTS: entries}
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
    entries = data[OBJECTS]
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
