"""The scene model: a tabletop layout in centimetres.

Frame (docs/design.md "Units and frames"): table top at z = 0, origin at the near-left corner of the
item placement zone, +x right, +y away from the viewer, +z up. ``size`` is [w, d, h] in the
object's own yawed frame, ``center`` the box centre, ``yaw`` radians about +z through the centre.

Every constructor validates; bad input raises :class:`SceneError` naming the object and field.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["RELATIONS", "Scene", "SceneError", "SceneObject", "Zone", "TABLE", "ZONE_TOLERANCE_CM",
           "footprint_half_extents", "wrap_angle", "zone_overshoot"]

# Parent id used for objects that rest on (or near) the table itself.
TABLE = "root_zone"
# Hierarchy relations in priority order (in ≻ on ≻ near).
RELATIONS = ("in", "on", "near")
# A footprint may poke this far (cm) past the zone before the object counts as out of zone: the
# MesaTask annotations place objects flush with the zone edge.
ZONE_TOLERANCE_CM = 0.5


def footprint_half_extents(wd: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(..., 2) cm: half extents of the axis-aligned box around yawed w × d footprints (``wd``
    (..., 2), ``yaw`` (...) rad)."""
    c, s = np.abs(np.cos(yaw)), np.abs(np.sin(yaw))
    return 0.5 * np.stack([c * wd[..., 0] + s * wd[..., 1], s * wd[..., 0] + c * wd[..., 1]], -1)


def zone_overshoot(xy: np.ndarray, wd: np.ndarray, yaw: np.ndarray, zone: np.ndarray) -> np.ndarray:
    """How far (cm) yawed boxes reach past a zone: the largest of the four sides, 0 inside.

    ``xy`` (..., 2) centres, ``wd`` (..., 2) widths and depths, ``yaw`` (...) rad, ``zone`` (..., 4)
    xmin, xmax, ymin, ymax (broadcast against the boxes). The out-of-zone metric
    (``physcene.eval.metrics.out_of_zone``) and PADA's per-object charge (``SceneBatch.zone_overshoot``).
    """
    half = footprint_half_extents(wd, yaw)
    hx, hy = half[..., 0], half[..., 1]
    past = np.stack([zone[..., 0] - (xy[..., 0] - hx), xy[..., 0] + hx - zone[..., 1],
                     zone[..., 2] - (xy[..., 1] - hy), xy[..., 1] + hy - zone[..., 3]], -1)
    return np.maximum(past.max(-1), 0.0)


class SceneError(ValueError):
    """A scene (or one of its objects) is invalid.

    ``obj`` is the offending instance id (or None for scene-level fields); ``field`` the field;
    ``source`` the file (or other input) it came from, when known. ``detail`` is the bare message.
    """

    def __init__(self, message: str, *, obj: str | None = None, field: str | None = None,
                 source: str | None = None):
        self.obj = obj
        self.field = field
        self.source = source
        self.detail = message
        where = ", ".join(p for p in (source or "", f"object {obj!r}" if obj else "",
                                      f"field {field!r}" if field else "") if p)
        super().__init__(f"{where}: {message}" if where else message)

    def with_source(self, source: str) -> SceneError:
        """The same error, now also naming the input it came from."""
        return SceneError(self.detail, obj=self.obj, field=self.field, source=source)


def wrap_angle(angle: float) -> float:
    """``angle`` (rad) wrapped to [-pi, pi)."""
    return float((angle + math.pi) % (2.0 * math.pi) - math.pi)


def _finite_vector(value, n: int, *, obj: str | None, name: str) -> tuple[float, ...]:
    if isinstance(value, (tuple, list)) and len(value) == n and all(
            isinstance(v, (float, int)) and not isinstance(v, bool) for v in value):
        # Fast path for plain Python numbers (the common case: parsing thousands of completions).
        vals = tuple(float(v) for v in value)
        if not all(math.isfinite(v) for v in vals):
            raise SceneError(f"non-finite value in {list(vals)}", obj=obj, field=name)
        return vals
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"expected {n} numbers, got {value!r}", obj=obj, field=name) from exc
    if arr.shape != (n,):
        raise SceneError(f"expected {n} numbers, got {arr.size}", obj=obj, field=name)
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"non-finite value in {arr.tolist()}", obj=obj, field=name)
    return tuple(float(v) for v in arr)


@dataclass(frozen=True)
class Zone:
    """An axis-aligned rectangle on the table, [xmin, xmax] × [ymin, ymax] in cm."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float

    def __post_init__(self):
        vals = _finite_vector((self.xmin, self.xmax, self.ymin, self.ymax), 4, obj=None, name="zone")
        object.__setattr__(self, "xmin", vals[0])
        object.__setattr__(self, "xmax", vals[1])
        object.__setattr__(self, "ymin", vals[2])
        object.__setattr__(self, "ymax", vals[3])
        if not (self.xmax > self.xmin and self.ymax > self.ymin):
            raise SceneError(f"empty zone {list(vals)}", field="zone")

    @classmethod
    def from_list(cls, values: Sequence[float], *, field: str = "zone") -> Zone:
        vals = _finite_vector(values, 4, obj=None, name=field)
        if not (vals[1] > vals[0] and vals[3] > vals[2]):
            raise SceneError(f"empty zone {list(vals)} (expects [xmin, xmax, ymin, ymax])", field=field)
        return cls(*vals)

    def to_list(self) -> list[float]:
        return [self.xmin, self.xmax, self.ymin, self.ymax]

    @property
    def center(self) -> tuple[float, float]:
        return (0.5 * (self.xmin + self.xmax), 0.5 * (self.ymin + self.ymax))

    @property
    def width(self) -> float:
        return self.xmax - self.xmin

    @property
    def depth(self) -> float:
        return self.ymax - self.ymin


@dataclass(frozen=True)
class SceneObject:
    """One object: a posed box (cm, radians) plus what it is.

    ``parent``/``relation`` are the object's place in the hierarchical scene graph when known
    (from CTRC text or :func:`physcene.graph.build_hierarchy`); None means "not annotated".
    """

    instance_id: str
    category: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    description: str = ""
    asset_id: str | None = None
    parent: str | None = None
    relation: str | None = None

    def __post_init__(self):
        if not isinstance(self.instance_id, str) or not self.instance_id:
            raise SceneError(f"instance_id must be a non-empty string, got {self.instance_id!r}",
                             field="instance_id")
        oid = self.instance_id
        if not isinstance(self.category, str) or not self.category:
            raise SceneError(f"category must be a non-empty string, got {self.category!r}", obj=oid,
                             field="category")
        object.__setattr__(self, "center", _finite_vector(self.center, 3, obj=oid, name="center"))
        size = _finite_vector(self.size, 3, obj=oid, name="size")
        if min(size) <= 0:
            raise SceneError(f"sizes must be positive, got {list(size)}", obj=oid, field="size")
        object.__setattr__(self, "size", size)
        yaw = _finite_vector([self.yaw], 1, obj=oid, name="yaw")[0]
        object.__setattr__(self, "yaw", yaw)
        if self.relation is not None and self.relation not in RELATIONS:
            raise SceneError(f"relation must be one of {RELATIONS}, got {self.relation!r}", obj=oid,
                             field="relation")
        if self.parent is not None and (not isinstance(self.parent, str) or not self.parent):
            raise SceneError(f"parent must be a non-empty string, got {self.parent!r}", obj=oid,
                             field="parent")
        if self.parent == oid:
            raise SceneError("an object cannot be its own parent", obj=oid, field="parent")
        # "near" is the table-level relation (docs/design.md): it never hangs under an object, and
        # nothing is "in" the table.
        if self.relation == "near" and self.parent not in (None, TABLE):
            raise SceneError(f"relation 'near' needs parent {TABLE!r}, got {self.parent!r}", obj=oid,
                             field="relation")
        if self.relation == "in" and self.parent == TABLE:
            raise SceneError(f"nothing can be 'in' {TABLE!r}", obj=oid, field="relation")

    # Box geometry ---------------------------------------------------------------------------
    @property
    def zmin(self) -> float:
        return self.center[2] - 0.5 * self.size[2]

    @property
    def zmax(self) -> float:
        return self.center[2] + 0.5 * self.size[2]

    def footprint(self) -> np.ndarray:
        """The yawed footprint's four corners, (4, 2) cm, counter-clockwise."""
        hw, hd = 0.5 * self.size[0], 0.5 * self.size[1]
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        local = np.array([[-hw, -hd], [hw, -hd], [hw, hd], [-hw, hd]])
        rot = np.array([[c, -s], [s, c]])
        return local @ rot.T + np.asarray(self.center[:2])

    def aabb(self) -> np.ndarray:
        """World axis-aligned box of the yawed object: [xmin, xmax, ymin, ymax, zmin, zmax] cm."""
        fp = self.footprint()
        return np.array([fp[:, 0].min(), fp[:, 0].max(), fp[:, 1].min(), fp[:, 1].max(),
                         self.zmin, self.zmax])

    def volume(self) -> float:
        return self.size[0] * self.size[1] * self.size[2]

    def moved(self, **changes) -> SceneObject:
        return replace(self, **changes)


@dataclass(frozen=True)
class Scene:
    """A tabletop scene: the placement zone and its objects (cm).

    ``restricted_zones`` are rectangles where nothing may stand (sinks, MesaTask's
    ``restricted_zone``/``sink_zone``). ``meta`` keeps whatever else a source carried.
    """

    zone: Zone
    objects: tuple[SceneObject, ...]
    scene_type: str = ""
    instruction: str = ""
    restricted_zones: tuple[Zone, ...] = ()
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        if not isinstance(self.zone, Zone):
            raise SceneError(f"zone must be a Zone, got {type(self.zone).__name__}", field="zone")
        objects = tuple(self.objects)
        for o in objects:
            if not isinstance(o, SceneObject):
                raise SceneError(f"objects must be SceneObject, got {type(o).__name__}", field="objects")
        object.__setattr__(self, "objects", objects)
        object.__setattr__(self, "restricted_zones", tuple(self.restricted_zones))
        seen: set[str] = set()
        for o in objects:
            if o.instance_id in seen:
                raise SceneError("duplicate instance id", obj=o.instance_id, field="instance_id")
            seen.add(o.instance_id)
        by_id = {o.instance_id: o for o in objects}
        for o in objects:
            if o.parent is not None and o.parent != TABLE and o.parent not in by_id:
                raise SceneError(f"unknown parent {o.parent!r}", obj=o.instance_id, field="parent")
        self._check_acyclic(by_id)

    @staticmethod
    def _check_acyclic(by_id: dict[str, SceneObject]) -> None:
        state: dict[str, int] = {}  # 1 = on the current path, 2 = done
        for start in by_id:
            path = []
            node = start
            while node in by_id and state.get(node) != 2:
                if state.get(node) == 1:
                    cycle = path[path.index(node):] + [node]
                    raise SceneError(f"parent cycle {' -> '.join(cycle)}", obj=node, field="parent")
                state[node] = 1
                path.append(node)
                node = by_id[node].parent
            for n in path:
                state[n] = 2

    # Access -----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.objects)

    def __iter__(self):
        return iter(self.objects)

    def ids(self) -> list[str]:
        return [o.instance_id for o in self.objects]

    def by_id(self) -> dict[str, SceneObject]:
        return {o.instance_id: o for o in self.objects}

    def get(self, instance_id: str) -> SceneObject:
        for o in self.objects:
            if o.instance_id == instance_id:
                return o
        raise KeyError(instance_id)

    def children(self, parent_id: str) -> list[SceneObject]:
        return [o for o in self.objects if o.parent == parent_id]

    @property
    def has_hierarchy(self) -> bool:
        return all(o.parent is not None for o in self.objects)

    def with_objects(self, objects: Iterable[SceneObject]) -> Scene:
        return replace(self, objects=tuple(objects), meta=dict(self.meta))

    def poses(self) -> np.ndarray:
        """(n_obj, 4) float64: x, y, z, yaw (cm, rad)."""
        return np.array([[*o.center, o.yaw] for o in self.objects], dtype=np.float64).reshape(-1, 4)

    def sizes(self) -> np.ndarray:
        """(n_obj, 3) float64 sizes in cm."""
        return np.array([o.size for o in self.objects], dtype=np.float64).reshape(-1, 3)

    def with_poses(self, poses: np.ndarray) -> Scene:
        """A copy with every object's (x, y, z, yaw) replaced; poses (n_obj, 4) cm/rad."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != (len(self.objects), 4):
            raise SceneError(f"poses must be ({len(self.objects)}, 4), got {poses.shape}", field="poses")
        return self.with_objects(
            o.moved(center=tuple(p[:3]), yaw=float(p[3])) for o, p in zip(self.objects, poses)
        )
