"""The exporters' shared model: the config, one rigid body per scene object (metres), the table box.

Frames, units, collision and mass rules: the package docstring (:mod:`physcene.export`).
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import trimesh

from physcene.assets import PRIMITIVES, Asset, default_library
from physcene.config import ConfigError, load_config
from physcene.export.decompose import convex_parts
from physcene.scene import Scene, SceneObject

__all__ = ["CM", "CollisionShape", "ExportConfig", "ExportError", "ObjectModel", "build_models",
           "category_color", "table_box", "visual_meshes"]

CM = 0.01  # metres per centimetre


class ExportError(ValueError):
    """A scene could not be exported (names the object and why)."""


@dataclass(frozen=True, kw_only=True)
class ExportConfig:
    """Everything ``configs/export.yaml`` sets for the exporters (see that file for units)."""

    densities: dict = field(default_factory=lambda: {"default": 500.0})
    """Category -> effective density of the solid mesh volume, kg/m^3 (key ``default`` required)."""
    min_mass_kg: float = 0.005
    """Lower bound of every body's mass, kg."""
    table_margin_cm: float = 20.0
    """How far the table box reaches beyond the zone and every object, cm."""
    table_thickness_cm: float = 4.0
    """Thickness of the table box below z = 0, cm."""
    decomposition: dict = field(default_factory=dict)
    """CoACD keyword arguments plus ``convex_tolerance`` and ``cache_dir``."""
    mujoco: dict = field(default_factory=dict)
    """MJCF solver/contact settings: timestep, integrator, cone, impratio, friction, condim, solref,
    solimp, margin, gap."""

    @classmethod
    def load(cls, overrides: Sequence[str] = (), name: str = "export") -> ExportConfig:
        """The config ``name`` (``configs/export.yaml``) with ``key=value`` overrides."""
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(load_config(name, overrides), resolve=True)
        densities = {str(k): float(v) for k, v in cfg["density_kg_m3"].items()}
        if "default" not in densities:
            raise ConfigError("density_kg_m3 needs a 'default' entry")
        bad = {k: v for k, v in densities.items() if not v > 0}
        if bad:
            raise ConfigError(f"densities must be positive, got {bad}")
        return cls(densities=densities, min_mass_kg=float(cfg["min_mass_kg"]),
                   table_margin_cm=float(cfg["table"]["margin_cm"]),
                   table_thickness_cm=float(cfg["table"]["thickness_cm"]),
                   decomposition=dict(cfg["decomposition"]), mujoco=dict(cfg["mujoco"]))

    def density(self, category: str) -> float:
        return self.densities.get(category, self.densities["default"])


@dataclass(frozen=True)
class CollisionShape:
    """One convex collision element in the body frame (metres).

    ``kind`` is ``box`` (``size`` = half extents), ``cylinder`` (radius, half height), ``sphere``
    (radius), ``ellipsoid`` (three radii) or ``mesh`` (a convex part). ``mesh`` always holds the
    convex geometry, so formats without a native shape (URDF has no ellipsoid) can use it.
    """

    kind: str
    size: tuple[float, ...]
    mesh: trimesh.Trimesh = field(repr=False)


@dataclass(frozen=True)
class ObjectModel:
    """A scene object as one rigid body, in metres (frames: module docstring)."""

    instance_id: str
    category: str
    name: str
    """A file- and XML-safe unique name derived from the instance id."""
    position: np.ndarray  # (3,) m, the box centre in the scene frame
    quaternion: np.ndarray  # (4,) w, x, y, z: the yaw about +z
    visual: trimesh.Trimesh = field(repr=False)  # body frame, metres
    collision: tuple[CollisionShape, ...] = field(repr=False)
    mass: float = 0.0  # kg
    center_of_mass: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m, body frame
    inertia: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3, 3) kg m^2 about the COM



# Object models ----------------------------------------------------------------------------------
def _yaw_quaternion(yaw: float) -> np.ndarray:
    return np.array([math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw)])


def _safe_names(ids: Sequence[str]) -> list[str]:
    names, used = [], set()
    for i in ids:
        base = re.sub(r"[^A-Za-z0-9_.-]", "_", i) or "object"
        name, k = base, 1
        while name.lower() in used or name.lower() == "table":
            name, k = f"{base}_{k}", k + 1
        used.add(name.lower())
        names.append(name)
    return names


def _primitive_shapes(kind: str, half: np.ndarray, mesh: trimesh.Trimesh) -> tuple[CollisionShape, ...]:
    hull = mesh.convex_hull
    if kind == "box":
        return (CollisionShape("box", tuple(half), hull),)
    if kind == "cylinder" and math.isclose(half[0], half[1], rel_tol=1e-6):
        return (CollisionShape("cylinder", (float(half[0]), float(half[2])), hull),)
    if kind == "sphere":
        if np.allclose(half, half[0], rtol=1e-6):
            return (CollisionShape("sphere", (float(half[0]),), hull),)
        return (CollisionShape("ellipsoid", tuple(half), hull),)
    return (CollisionShape("mesh", (), hull),)  # an elliptic cylinder: convex, its own hull


def _mass_properties(mesh: trimesh.Trimesh, half: np.ndarray, density: float, min_mass: float):
    """(mass kg, COM (3,) m, inertia (3, 3) kg m^2) of the solid mesh, or of its box if not closed."""
    if mesh.is_volume and mesh.volume > 1e-12:
        solid = mesh.copy()
        solid.density = density
        mass, com = float(solid.mass), np.asarray(solid.center_mass)
        inertia = np.asarray(solid.moment_inertia)
    else:
        ext = 2.0 * half
        mass = density * float(np.prod(ext))
        com = np.zeros(3)
        inertia = np.diag(mass / 12.0 * np.array([ext[1] ** 2 + ext[2] ** 2, ext[0] ** 2 + ext[2] ** 2,
                                                  ext[0] ** 2 + ext[1] ** 2]))
    if mass < min_mass:
        inertia = inertia * (min_mass / mass)
        mass = min_mass
    return mass, com, 0.5 * (inertia + inertia.T)


def _resolve(obj: SceneObject, library) -> Asset:
    try:
        return library.resolve(obj.category, obj.asset_id).asset
    except (KeyError, ValueError) as exc:
        raise ExportError(f"object {obj.instance_id!r}: no asset for category {obj.category!r}: "
                          f"{exc}") from exc


def _visual(obj: SceneObject, library):
    """(asset, primitive kind or None, unit mesh, half extents m, visual mesh in metres) of ``obj``."""
    asset = _resolve(obj, library)
    half = 0.5 * CM * np.asarray(obj.size, dtype=np.float64)
    if asset.mesh is None:  # a shape known only by its SDF: its box is the best solid we have
        unit = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
        kind = "box"
    else:
        unit = asset.mesh
        kind = asset.asset_id.split(":", 1)[1] if asset.source == "primitive" else None
    visual = unit.copy()
    visual.apply_transform(np.diag([*half, 1.0]))
    return asset, kind, unit, half, visual


def visual_meshes(scene: Scene, *, library=None) -> list[tuple[SceneObject, str, Asset, trimesh.Trimesh]]:
    """(object, safe name, asset, visual mesh in metres, body frame) per object, without the collision
    decomposition: what viewers and SceneEval need."""
    if library is None:
        library = default_library()
    out = []
    for obj, name in zip(scene.objects, _safe_names(scene.ids())):
        asset, _, _, _, visual = _visual(obj, library)
        out.append((obj, name, asset, visual))
    return out


def build_models(scene: Scene, *, library=None, config: ExportConfig | None = None) -> list[ObjectModel]:
    """One :class:`ObjectModel` per scene object, in scene order (metres)."""
    config = config or ExportConfig.load()
    if library is None:
        library = default_library()
    models = []
    for obj, name in zip(scene.objects, _safe_names(scene.ids())):
        asset, kind, unit, half, visual = _visual(obj, library)
        scale = np.diag([*half, 1.0])
        if kind in PRIMITIVES:
            shapes = _primitive_shapes(kind, half, visual)
        else:
            parts = convex_parts(unit, config.decomposition)
            shapes = []
            for part in parts:
                part = part.copy()
                part.apply_transform(scale)
                if part.volume > 1e-10:  # 0.1 mm^3: slivers add nothing but trouble to a hull solver
                    shapes.append(CollisionShape("mesh", (), part))
            if not shapes:
                raise ExportError(f"object {obj.instance_id!r}: convex decomposition of asset "
                                  f"{asset.asset_id!r} left no part of positive volume")
            shapes = tuple(shapes)
        # A category the config does not list takes the density of the asset it was retrieved as
        # ("desk_lamp" -> lamp), before the default.
        category = obj.category if obj.category in config.densities else asset.category
        mass, com, inertia = _mass_properties(visual, half, config.density(category), config.min_mass_kg)
        models.append(ObjectModel(
            instance_id=obj.instance_id, category=obj.category, name=name,
            position=CM * np.asarray(obj.center, dtype=np.float64), quaternion=_yaw_quaternion(obj.yaw),
            visual=visual, collision=shapes, mass=mass, center_of_mass=com, inertia=inertia))
    return models


def table_box(scene: Scene, config: ExportConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), half extents (3,)) of the static table box in metres; its top is z = 0."""
    config = config or ExportConfig.load()
    lo = np.array([scene.zone.xmin, scene.zone.ymin])
    hi = np.array([scene.zone.xmax, scene.zone.ymax])
    for obj in scene.objects:
        box = obj.aabb()
        lo, hi = np.minimum(lo, box[[0, 2]]), np.maximum(hi, box[[1, 3]])
    lo, hi = lo - config.table_margin_cm, hi + config.table_margin_cm
    t = config.table_thickness_cm
    centre = CM * np.array([*(0.5 * (lo + hi)), -0.5 * t])
    half = CM * np.array([*(0.5 * (hi - lo)), 0.5 * t])
    return centre, half


def _pose_matrix(model: ObjectModel) -> np.ndarray:
    m = trimesh.transformations.quaternion_matrix(model.quaternion)
    m[:3, 3] = model.position
    return m


def category_color(category: str) -> list[int]:
    """A fixed RGBA colour (0-255) per category: the same in every export and in the viewer."""
    h = int(hashlib.md5(category.encode()).hexdigest()[:6], 16)
    return [80 + (h & 0x7F), 80 + ((h >> 8) & 0x7F), 80 + ((h >> 16) & 0x7F), 255]


def _obj_bytes(mesh: trimesh.Trimesh) -> bytes:
    text = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=False,
                                           include_texture=False)
    return text.encode()


def _fmt(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.ravel(values))
