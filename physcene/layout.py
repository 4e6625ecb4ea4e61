"""MesaTask ``layout.json`` reader and writer (centimetres).

A MesaTask layout is a JSON object::

    {"item_placement_zone": [xmin, xmax, ymin, ymax],
     "restricted_zone": [xmin, xmax, ymin, ymax] | [[...], ...] | [],
     "sink_zone": same shape as restricted_zone (optional),
     "scene_type": "...", "instruction": "..." (optional),
     "objects": [{"instance": "1_teapot_0", "position": [x, y, z], "size": [w, d, h],
                  "rotation": [qx, qy, qz, qw], "z_rotation": yaw_rad,
                  "retrieved_uid": "...", "description": "..."}, ...]
                | {"1_teapot_0": {...}, ...}}

``position`` is the box centre, ``size`` the extents in the object's own frame. When both are
given, the quaternion ``rotation`` decides the yaw (``z_rotation`` is a derived convenience field
that MesaTask files do not always keep in sync). Roll and pitch, if any, are dropped: the scene
model is yaw-only. ``restricted_zone`` and ``sink_zone`` both become ``Scene.restricted_zones``.
Optional ``parent``/``relation`` keys (written by :func:`layout_to_dict` for scenes that carry a
hierarchy) are read back.

Every error is a :class:`~physcene.scene.SceneError` naming the file, the object and the field.
"""

from __future__ import annotations

import gzip
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path

from physcene.files import write_atomic
from physcene.scene import Scene, SceneError, SceneObject, Zone

__all__ = [
    "PRIMITIVE_CATEGORIES",
    "category_from_instance",
    "dumps_layout",
    "iter_layout_tree",
    "json_records",
    "layout_record_lines",
    "layout_to_dict",
    "load_layout",
    "MAX_COORDINATE_CM",
    "MAX_SIZE_CM",
    "MIN_SIZE_CM",
    "RECORD_FILES",
    "parse_json",
    "quaternion_tilt",
    "quaternion_to_yaw",
    "read_layout",
    "records_by_id",
    "row_file",
    "write_layout",
    "write_layout_records",
    "yaw_to_quaternion",
]

# Bounds of a layout file's numbers (cm), checked where a command reads one (``bounded=True``): a
# tabletop's objects and zones lie within 10 m of its origin and no object is over 5 m or under
# 0.01 mm. Beyond them a number is a typo or a broken exporter (a size of 1e30 wrote Infinity).
MAX_COORDINATE_CM = 1000.0
MAX_SIZE_CM = 500.0
MIN_SIZE_CM = 0.001
_COORDINATE = (-MAX_COORDINATE_CM, MAX_COORDINATE_CM)

# Instances named ``box_*``, ``cylinder_*``, ``sphere_*`` are exact primitives, whatever follows.
PRIMITIVE_CATEGORIES = ("box", "cylinder", "sphere")
# Keys of a layout object that the reader understands; anything else is kept in Scene.meta.
_OBJECT_KEYS = {"instance", "position", "size", "rotation", "z_rotation", "retrieved_uid",
                "selected_uid", "description", "category", "parent", "relation"}
_SCENE_KEYS = {"item_placement_zone", "restricted_zone", "sink_zone", "scene_type", "instruction",
               "objects"}
_LEADING_INDEX = re.compile(r"^\d+_")
_TRAILING_INDEX = re.compile(r"_\d+$")


def category_from_instance(name: str) -> str:
    """The category of a MesaTask instance name: ``"1_teapot_0"`` and ``"teapot_0"`` -> ``"teapot"``.

    A leading ``<n>_`` (MesaTask's object index) and a trailing ``_<n>`` (the copy number) are
    dropped. Names starting with ``box_``, ``cylinder_`` or ``sphere_`` (after the index) give
    exactly that primitive category.
    """
    stem = _LEADING_INDEX.sub("", name.strip()) or name.strip()
    for kind in PRIMITIVE_CATEGORIES:
        if stem == kind or stem.startswith(kind + "_"):
            return kind
    return _TRAILING_INDEX.sub("", stem) or stem


def quaternion_to_yaw(q) -> float:
    """Yaw (rad, about +z) of a quaternion [x, y, z, w]; raises ValueError if it has no length."""
    x, y, z, w = (float(v) for v in q)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quaternion {list(q)} has no usable length")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_tilt(q) -> float:
    """Angle (rad) between the rotated +z axis and world +z: the roll/pitch a yaw-only model drops."""
    x, y, z, w = (float(v) for v in q)
    n2 = x * x + y * y + z * z + w * w
    if not math.isfinite(n2) or n2 < 1e-24:
        return 0.0
    return math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y) / n2)))


def yaw_to_quaternion(yaw: float) -> list[float]:
    """The quaternion [x, y, z, w] of a pure rotation by ``yaw`` rad about +z."""
    return [0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)]


def _number_list(value, n: int, *, obj: str | None, field: str, source: str,
                 bounds: tuple[float, float] | None = None) -> list[float]:
    """``value`` as ``n`` finite floats, each within ``bounds`` (lo, hi) when given."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise SceneError(f"expected a list of {n} numbers, got {value!r:.80}", obj=obj, field=field,
                         source=source)
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SceneError(f"expected numbers, got {v!r:.40}", obj=obj, field=field, source=source)
        if isinstance(v, int) and abs(v) > 1e300:  # a 400-digit integer has no float
            raise SceneError(f"number too large ({len(str(abs(v)))} digits)", obj=obj, field=field,
                             source=source)
        if not math.isfinite(float(v)):
            raise SceneError(f"non-finite value {v!r}", obj=obj, field=field, source=source)
        if bounds is not None and not bounds[0] <= v <= bounds[1]:
            raise SceneError(f"{v:g} cm is outside {bounds[0]:g} to {bounds[1]:g} cm", obj=obj,
                             field=field, source=source)
        out.append(float(v))
    return out


def _rects(value, *, field: str, source: str, bounded: bool = False) -> list[Zone]:
    """One rect [xmin, xmax, ymin, ymax], a list of rects, or nothing (None / [] / {})."""
    if value is None or value == [] or value == {}:
        return []
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, float)) for v in value):
        value = [value]
    if not isinstance(value, (list, tuple)):
        raise SceneError(f"expected [xmin, xmax, ymin, ymax] or a list of them, got {value!r:.80}",
                         field=field, source=source)
    zones = []
    for i, rect in enumerate(value):
        vals = _number_list(rect, 4, obj=None, field=f"{field}[{i}]", source=source,
                            bounds=_COORDINATE if bounded else None)
        try:
            zones.append(Zone.from_list(vals, field=f"{field}[{i}]"))
        except SceneError as exc:
            raise exc.with_source(source) from None
    return zones


def _object_items(objects, source: str) -> list[tuple[str, dict]]:
    if isinstance(objects, dict):
        items = []
        for key, entry in objects.items():
            if not isinstance(entry, dict):
                raise SceneError(f"expected an object, got {type(entry).__name__}", obj=str(key),
                                 field="objects", source=source)
            items.append((str(entry.get("instance", key)), entry))
        return items
    if isinstance(objects, list):
        items = []
        for i, entry in enumerate(objects):
            if not isinstance(entry, dict):
                raise SceneError(f"expected an object, got {type(entry).__name__}", field=f"objects[{i}]",
                                 source=source)
            name = entry.get("instance")
            if not isinstance(name, str) or not name.strip():
                raise SceneError(f"missing or empty instance name {name!r:.40}",
                                 field=f"objects[{i}].instance", source=source)
            items.append((name, entry))
        return items
    raise SceneError(f"expected a list or a dict of objects, got {type(objects).__name__}", field="objects",
                     source=source)


def _optional_str(entry: dict, key: str, *, obj: str, source: str) -> str | None:
    value = entry.get(key)
    if value is None:
        return None
    if not isinstance(value, (str, int)) or isinstance(value, bool):
        raise SceneError(f"expected a string, got {value!r:.40}", obj=obj, field=key, source=source)
    return str(value)


def _load_object(name: str, entry: dict, source: str, bounded: bool = False) -> SceneObject:
    position = _number_list(entry.get("position"), 3, obj=name, field="position", source=source,
                            bounds=_COORDINATE if bounded else None)
    size = _number_list(entry.get("size"), 3, obj=name, field="size", source=source,
                        bounds=(MIN_SIZE_CM, MAX_SIZE_CM) if bounded else None)
    yaw = None
    if entry.get("rotation") is not None:
        quat = _number_list(entry["rotation"], 4, obj=name, field="rotation", source=source)
        try:
            yaw = quaternion_to_yaw(quat)
        except ValueError:
            yaw = None  # a zero quaternion says nothing: fall back to z_rotation
    if yaw is None and entry.get("z_rotation") is not None:
        yaw = _number_list([entry["z_rotation"]], 1, obj=name, field="z_rotation", source=source)[0]
    if yaw is None and entry.get("rotation") is not None:
        raise SceneError("zero-length quaternion and no z_rotation", obj=name, field="rotation",
                         source=source)
    category = _optional_str(entry, "category", obj=name, source=source) or category_from_instance(name)
    try:
        return SceneObject(
            instance_id=name,
            category=category,
            center=tuple(position),
            size=tuple(size),
            yaw=float(yaw or 0.0),
            description=_optional_str(entry, "description", obj=name, source=source) or "",
            # MesaTask's retrieval step writes the chosen asset as selected_uid.
            asset_id=(_optional_str(entry, "retrieved_uid", obj=name, source=source)
                      or _optional_str(entry, "selected_uid", obj=name, source=source)),
            parent=_optional_str(entry, "parent", obj=name, source=source),
            relation=_optional_str(entry, "relation", obj=name, source=source),
        )
    except SceneError as exc:
        raise exc.with_source(source) from None


def load_layout(data: dict, *, source: str = "<dict>", scene_type: str | None = None,
                bounded: bool = False) -> Scene:
    """A :class:`Scene` from a parsed MesaTask layout dict (cm). ``scene_type`` fills a missing one.

    ``bounded``: positions and zones must lie within ``MAX_COORDINATE_CM`` of the origin and sizes
    from ``MIN_SIZE_CM`` to ``MAX_SIZE_CM`` (layout files; the CTRC reader has its own limit)."""
    if not isinstance(data, dict):
        raise SceneError(f"expected a JSON object at the top level, got {type(data).__name__}", source=source)
    for key in ("item_placement_zone", "objects"):
        if key not in data:
            raise SceneError("missing (a layout needs an item_placement_zone and an objects list)",
                             field=key, source=source)
    zone_vals = _number_list(data["item_placement_zone"], 4, obj=None, field="item_placement_zone",
                             source=source, bounds=_COORDINATE if bounded else None)
    try:
        zone = Zone.from_list(zone_vals, field="item_placement_zone")
    except SceneError as exc:
        raise exc.with_source(source) from None
    restricted = _rects(data.get("restricted_zone"), field="restricted_zone", source=source, bounded=bounded)
    restricted += _rects(data.get("sink_zone"), field="sink_zone", source=source, bounded=bounded)
    items = _object_items(data["objects"], source)
    objects = [_load_object(name, entry, source, bounded) for name, entry in items]
    # Yaw-only scenes drop roll/pitch; say which objects lost more than ~0.5 degree of it.
    tilted = sorted(name for name, entry in items
                    if isinstance(entry.get("rotation"), list) and len(entry["rotation"]) == 4
                    and quaternion_tilt(entry["rotation"]) > 0.01)
    extras = {name: {k: v for k, v in entry.items() if k not in _OBJECT_KEYS} for name, entry in items}
    for key in ("scene_type", "instruction"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise SceneError(f"expected a string, got {data[key]!r:.40}", field=key, source=source)
    meta = {k: v for k, v in data.items() if k not in _SCENE_KEYS}
    meta["source"] = source
    if tilted:
        meta["tilted_objects"] = tilted
    extras = {name: e for name, e in extras.items() if e}
    if extras:
        meta["object_extras"] = extras  # unknown per-object keys, written back by layout_to_dict
    try:
        return Scene(zone=zone, objects=tuple(objects), scene_type=data.get("scene_type") or scene_type or "",
                     instruction=data.get("instruction") or "", restricted_zones=tuple(restricted), meta=meta)
    except SceneError as exc:
        raise exc.with_source(source) from None


def read_layout(path, *, scene_type: str | None = None, bounded: bool = False) -> Scene:
    """Read a MesaTask ``layout.json``; errors name the file, the object and the field.
    ``bounded``: as :func:`load_layout` (the commands that read a user's files set it; layouts a
    run saved itself, such as eval's ``layouts/``, may hold a model's far-out guesses)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(f"not UTF-8 text ({exc.reason})", source=str(path)) from None
    data = parse_json(text, source=str(path), allow_nan=False)
    return load_layout(data, source=str(path), scene_type=scene_type, bounded=bounded)


def parse_json(text: str, *, source: str, allow_nan: bool = True):
    """``json.loads(text)``, where every way JSON text can fail (a syntax error, NaN when not
    ``allow_nan``, an integer of over 4,300 digits, nesting too deep for the parser) is one
    :class:`SceneError` naming ``source``."""
    try:
        return json.loads(text, **({} if allow_nan else {"parse_constant": _reject_constant}))
    except json.JSONDecodeError as exc:
        raise SceneError(f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}",
                         source=source) from None
    except RecursionError:
        raise SceneError("invalid JSON: nested too deeply", source=source) from None
    except ValueError as exc:
        raise SceneError(f"invalid JSON: {exc}", source=source) from None


def _reject_constant(name: str):
    raise ValueError(f"non-finite number {name} is not allowed")


def _round(v: float) -> float:
    # Full float precision (JSON's repr round-trips exactly); only -0.0 is normalised.
    v = float(v)
    return 0.0 if v == 0 else v


def layout_to_dict(scene: Scene) -> dict:
    """The MesaTask layout dict of ``scene`` (cm): ``instance``, ``position``, ``size``,
    ``rotation`` [x, y, z, w], ``z_rotation``, ``retrieved_uid``, ``description`` per object.

    ``category`` is written only where it differs from what the instance name implies;
    ``parent``/``relation`` only where the scene carries them; per-object keys the reader did not
    know (``Scene.meta["object_extras"]``) are written back; top-level keys the reader kept in
    ``meta`` are not (they may describe a layout that has since changed).
    """
    extras = scene.meta.get("object_extras", {}) if isinstance(scene.meta, dict) else {}
    objects = []
    for o in scene.objects:
        entry = {
            "instance": o.instance_id,
            "position": [_round(v) for v in o.center],
            "size": [_round(v) for v in o.size],
            "rotation": [_round(v) for v in yaw_to_quaternion(o.yaw)],
            "z_rotation": _round(o.yaw),
            "retrieved_uid": o.asset_id,
            "description": o.description,
        }
        if o.category != category_from_instance(o.instance_id):
            entry["category"] = o.category
        if o.parent is not None:
            entry["parent"] = o.parent
        if o.relation is not None:
            entry["relation"] = o.relation
        for k, v in extras.get(o.instance_id, {}).items():
            entry.setdefault(k, v)
        objects.append(entry)
    out: dict = {}
    if scene.scene_type:
        out["scene_type"] = scene.scene_type
    if scene.instruction:
        out["instruction"] = scene.instruction
    out["item_placement_zone"] = [_round(v) for v in scene.zone.to_list()]
    out["restricted_zone"] = [[_round(v) for v in z.to_list()] for z in scene.restricted_zones]
    out["objects"] = objects
    return out


def dumps_layout(scene: Scene) -> str:
    """``scene`` as MesaTask layout.json text: top-level keys indented, one object per line."""
    data = layout_to_dict(scene)
    objects = data.pop("objects")
    dump = lambda v: json.dumps(v, ensure_ascii=False, allow_nan=False)  # noqa: E731
    lines = [f"  {dump(k)}: {dump(v)}," for k, v in data.items()]
    rows = ",\n".join(f"    {dump(o)}" for o in objects)
    body = '  "objects": [\n' + rows + "\n  ]" if objects else '  "objects": []'
    return "{\n" + "\n".join(lines + [body]) + "\n}\n"


def write_layout(scene: Scene, path) -> Path:
    """Write ``scene`` as a MesaTask ``layout.json`` atomically (temp file, then rename)."""
    return write_atomic(path, dumps_layout(scene))


def iter_layout_tree(root, *, skip_errors: bool = False) -> Iterator[tuple[Path, Scene]]:
    """Every ``<table_type>/<scene>/layout.json`` under ``root`` (MesaTask's ``Layout_info``).

    ``root`` may be the ``Layout_info`` folder itself or a folder containing it. A layout without
    ``scene_type`` gets its table-type folder name (underscores read as spaces). Files come in
    sorted order; with ``skip_errors`` broken files are skipped instead of raising.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"layout tree {str(root)!r} is not a directory")
    if (root / "Layout_info").is_dir():
        root = root / "Layout_info"
    for path in sorted(root.rglob("layout.json")):
        rel = path.relative_to(root).parts
        table_type = rel[-3].replace("_", " ") if len(rel) >= 3 else None
        try:
            scene = read_layout(path, scene_type=table_type)
        except (SceneError, OSError):
            if skip_errors:
                continue
            raise
        yield path, scene


RECORD_FILES = (".jsonl", ".jsonl.gz")
"""The name endings of a JSONL file of layout records, gzipped or not (:func:`layout_record_lines`)."""


def layout_record_lines(path) -> list[tuple[int, str]]:
    """(line number, text) of every non-blank line of a JSONL file of layout records, gzipped when
    its name ends in ``.gz`` (``physcene check`` and the eval harness's ``file:`` generator read
    ablation layouts so). Unreadable files raise OSError (a bad gzip stream is one)."""
    path = Path(path)
    opened = gzip.open(path, "rt", encoding="utf-8") if path.suffix == ".gz" else path.open(encoding="utf-8")
    with opened as f:
        return [(number, line) for number, line in enumerate(f, start=1) if line.strip()]


def json_records(path, *, error: type[ValueError] = ValueError, prefix: str = "") -> list[tuple[int, object]]:
    """(line number, parsed JSON) of each non-blank line of a JSONL file (gzipped when its name ends in
    ``.gz``). ``error`` (ValueError or a subclass) names the file, after ``prefix``, and the line of a
    file that cannot be read or a line that is not JSON."""
    path = Path(path)
    try:
        lines = layout_record_lines(path)
    except (OSError, UnicodeDecodeError, EOFError) as exc:  # a bad gzip stream is an OSError
        raise error(f"{prefix}{path}: cannot be read ({exc})") from None
    out = []
    for number, line in lines:
        try:
            out.append((number, json.loads(line)))
        except json.JSONDecodeError as exc:
            raise error(f"{prefix}{path}:{number}: not JSON ({exc})") from None
    return out


def records_by_id(path, *, error: type[ValueError] = ValueError,
                  prefix: str = "") -> dict[str, tuple[int, dict]]:
    """Each record of a JSONL file of ``{"id", ...}`` records by its id, with its line number; errors as
    :func:`json_records`'s, and a record without an id."""
    by_id = {}
    for number, record in json_records(path, error=error, prefix=prefix):
        if not isinstance(record, dict) or "id" not in record:
            raise error(f"{prefix}{path}:{number}: a record needs an 'id'")
        by_id[str(record["id"])] = (number, record)
    return by_id


def row_file(name: str, suffix: str = ".jsonl.gz") -> str:
    """The file name of a table row's layouts (or, with ``suffix``, of another file of that row):
    ``pada*`` -> ``pada_star.jsonl.gz``, ``sft+tto`` -> ``sft_tto.jsonl.gz``, ``pada@12`` ->
    ``pada-12.jsonl.gz``; ``row_file("sft+plan", ".completions.jsonl.gz")`` ->
    ``sft_plan.completions.jsonl.gz``."""
    return name.replace("*", "_star").replace("+", "_").replace("@", "-") + suffix


def write_layout_records(records, path) -> Path:
    """One JSON object per line (gzipped when the name ends in ``.gz``, byte-identical for the same
    records: no timestamp in the header), written atomically (temp file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    body = "".join(json.dumps(r, ensure_ascii=False, allow_nan=False) + "\n" for r in records).encode()
    data = gzip.compress(body, mtime=0) if path.suffix == ".gz" else body
    write_atomic(path, data)
    return path
