"""Simulator-ready export of a scene: GLB (whole scene), MJCF (MuJoCo) and URDF (SAPIEN/ManiSkill).

Every export is in **metres** (the scene is in cm) with the scene's own frame: origin at the
placement zone's near-left corner, +z up, the table top at z = 0. The table is a static box
under it. Each object is one rigid body posed at its box centre with its yaw; its geometry is the
asset's mesh scaled from the normalised cube [-1, 1]^3 to ``size`` / 2.

Collision geometry keeps cavities hollow: exact primitives become native shapes (box, cylinder,
sphere/ellipsoid); any other mesh is split into convex parts by CoACD (approximate convex
decomposition) once per asset, in the normalised frame. A scaling is linear, so the scaled parts
of a convex decomposition are a convex decomposition of the scaled mesh: one cache entry serves
every size. Entries live on disk keyed by a hash of the mesh and the CoACD settings.

Masses are density × volume: the mesh's own volume when it is a closed volume, else the box's.
Inertia comes from the same solid. Densities per category are in ``configs/export.yaml``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from physcene.assets import PRIMITIVES, Asset
from physcene.config import ConfigError, load_config
from physcene.scene import Scene, SceneObject

__all__ = [
    "CM", "FORMATS", "CollisionShape", "ExportConfig", "ExportError", "ObjectModel", "build_models",
    "convex_parts", "export", "export_glb", "export_mjcf", "export_urdf", "glb_scene", "mjcf_document",
    "table_box",
]

CM = 0.01  # metres per centimetre
FORMATS = ("glb", "mjcf", "urdf")


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


# Convex decomposition ---------------------------------------------------------------------------
def _cache_dir(setting) -> Path:
    if setting:
        return Path(setting)
    base = os.environ.get("PHYSCENE_CACHE") or os.path.join(Path.home(), ".cache", "physcene")
    return Path(base) / "coacd"


def _coacd_kwargs(settings: dict) -> dict:
    keys = ("threshold", "max_convex_hull", "preprocess_mode", "preprocess_resolution", "resolution",
            "mcts_nodes", "mcts_iterations", "mcts_max_depth", "merge", "max_ch_vertex", "seed")
    return {k: settings[k] for k in keys if k in settings}


def convex_parts(mesh: trimesh.Trimesh, settings: dict) -> list[trimesh.Trimesh]:
    """Convex parts covering ``mesh`` (its own frame), cached on disk by content hash.

    A mesh within ``convex_tolerance`` of its convex hull (by volume) is its own single part.
    """
    hull = mesh.convex_hull
    if mesh.is_volume and hull.volume - mesh.volume <= settings.get("convex_tolerance", 0.05) * hull.volume:
        return [hull]
    import coacd

    kwargs = _coacd_kwargs(settings)  # the cache key holds the setting as configured
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    settings_key = {"coacd": getattr(coacd, "__version__", "?"), **kwargs}
    digest.update(json.dumps(settings_key, sort_keys=True).encode())
    path = _cache_dir(settings.get("cache_dir")) / f"{digest.hexdigest()[:32]}.npz"
    if path.is_file():
        try:
            with np.load(path) as data:
                return _unpack_parts(data["vertices"], data["faces"], data["offsets"])
        except (OSError, ValueError, KeyError):
            pass  # a corrupt or foreign entry: decompose again and overwrite it
    if kwargs.get("preprocess_mode", "auto") == "auto":
        # CoACD's own "auto" check aborts the process on some closed meshes (a procedural apple);
        # trimesh decides instead: remesh to a manifold only when the mesh is not a closed volume.
        kwargs["preprocess_mode"] = "off" if mesh.is_volume else "on"
    raw = _run_coacd_isolated(np.asarray(mesh.vertices), np.asarray(mesh.faces), kwargs)
    if raw is None and kwargs["preprocess_mode"] == "off":
        raw = _run_coacd_isolated(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                  {**kwargs, "preprocess_mode": "on"})
    parts = [trimesh.Trimesh(v, f, process=True).convex_hull for v, f in raw or () if len(v) >= 4]
    if not parts:
        warnings.warn(f"CoACD failed on a mesh of {len(mesh.faces)} faces; its convex hull stands in "
                      "(cavities of this asset are closed in the export)", RuntimeWarning, stacklevel=2)
        return [hull]  # not cached: every run says so, and a fixed CoACD gets its chance
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces for p in parts])
    offsets = np.cumsum([[0, 0]] + [[len(p.vertices), len(p.faces)] for p in parts], axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Written to a temporary file in the same folder, then renamed: readers never see half a file.
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz.tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, vertices=vertices, faces=faces, offsets=offsets)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return parts


# The child: a fresh interpreter that reads the mesh from an .npz, runs CoACD and writes the parts.
_COACD_CHILD = """
import json, sys
import numpy as np
import coacd
coacd.set_log_level("error")
data = np.load(sys.argv[1])
parts = coacd.run_coacd(coacd.Mesh(data["vertices"], data["faces"]), **json.loads(sys.argv[3]))
out = {}
for k, (v, f) in enumerate(parts):
    out[f"v{k}"], out[f"f{k}"] = np.asarray(v), np.asarray(f)
np.savez(sys.argv[2], **out)
"""


def _run_coacd_isolated(vertices: np.ndarray, faces: np.ndarray, kwargs: dict):
    """CoACD's parts [(vertices, faces)], run in a child process; None when the child failed.

    CoACD aborts (C++ ``std::logic_error``, SIGABRT) on some inputs, which would kill the whole
    export; in a child process that is a value. The child is a fresh ``python -c`` interpreter,
    not a multiprocessing worker: a forked copy of a parent that has run torch holds a live OpenMP
    pool and CoACD's OpenMP deadlocks in it (seen in a test run), and a spawned worker re-imports
    the parent's ``__main__``, which fails for stdin scripts and notebooks. Parts are cached per
    asset, so the start-up is paid once.
    """
    with tempfile.TemporaryDirectory(prefix="physcene-coacd-") as tmp:
        src, dst = Path(tmp) / "mesh.npz", Path(tmp) / "parts.npz"
        np.savez(src, vertices=np.asarray(vertices, dtype=np.float64),
                 faces=np.asarray(faces, dtype=np.int64))
        done = subprocess.run([sys.executable, "-c", _COACD_CHILD, str(src), str(dst), json.dumps(kwargs)],
                              capture_output=True, text=True)
        if done.returncode != 0 or not dst.exists():
            return None
        with np.load(dst) as parts:
            n = len(parts.files) // 2
            return [(parts[f"v{k}"], parts[f"f{k}"]) for k in range(n)]


def _unpack_parts(vertices: np.ndarray, faces: np.ndarray, offsets: np.ndarray) -> list[trimesh.Trimesh]:
    parts = []
    for (v0, f0), (v1, f1) in zip(offsets[:-1], offsets[1:]):
        parts.append(trimesh.Trimesh(vertices[v0:v1], faces[f0:f1], process=False))
    return parts


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


def build_models(scene: Scene, *, library=None, config: ExportConfig | None = None) -> list[ObjectModel]:
    """One :class:`ObjectModel` per scene object, in scene order (metres)."""
    config = config or ExportConfig.load()
    if library is None:
        from physcene.assets import default_library

        library = default_library()
    models = []
    for obj, name in zip(scene.objects, _safe_names(scene.ids())):
        asset = _resolve(obj, library)
        half = 0.5 * CM * np.asarray(obj.size, dtype=np.float64)
        if asset.mesh is None:  # a shape known only by its SDF: its box is the best solid we have
            unit = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
            kind = "box"
        else:
            unit = asset.mesh
            kind = asset.asset_id.split(":", 1)[1] if asset.source == "primitive" else None
        scale = np.diag([*half, 1.0])
        visual = unit.copy()
        visual.apply_transform(scale)
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


def _color(category: str) -> list[int]:
    h = int(hashlib.md5(category.encode()).hexdigest()[:6], 16)
    return [80 + (h & 0x7F), 80 + ((h >> 8) & 0x7F), 80 + ((h >> 16) & 0x7F), 255]


def _obj_bytes(mesh: trimesh.Trimesh) -> bytes:
    text = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=False,
                                           include_texture=False)
    return text.encode()


# GLB --------------------------------------------------------------------------------------------
def glb_scene(scene: Scene, *, library=None, config: ExportConfig | None = None) -> trimesh.Scene:
    """The whole scene as a ``trimesh.Scene`` in metres: one node per object plus ``table``."""
    config = config or ExportConfig.load()
    centre, half = table_box(scene, config)
    out = trimesh.Scene()
    table = trimesh.creation.box(extents=2 * half)
    table.visual.face_colors = [150, 110, 70, 255]
    out.add_geometry(table, node_name="table", geom_name="table",
                     transform=trimesh.transformations.translation_matrix(centre))
    for model in build_models(scene, library=library, config=config):
        mesh = model.visual.copy()
        mesh.visual.face_colors = _color(model.category)
        mesh.metadata["category"] = model.category
        out.add_geometry(mesh, node_name=model.instance_id, geom_name=model.name,
                         transform=_pose_matrix(model))
    return out


def export_glb(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write ``out_dir/scene.glb`` (metres, +z up as in the scene; glTF viewers may show y up)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = glb_scene(scene, library=library, config=config).export(file_type="glb")
    path = out_dir / "scene.glb"
    _write_atomic(path, data)
    return path


# MJCF -------------------------------------------------------------------------------------------
def _fmt(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.ravel(values))


def mjcf_document(scene: Scene, *, library=None, config: ExportConfig | None = None,
                  models: Sequence[ObjectModel] | None = None) -> tuple[str, dict[str, bytes]]:
    """The MJCF text and its mesh files ({relative path: bytes}), ready for
    ``mujoco.MjModel.from_xml_string(xml, files)`` or for writing beside ``scene.xml``.

    One body with a free joint per object; visual meshes in geom group 2 (no contact), collision
    geoms in group 3; explicit inertials (mass from density × volume); the table a static box.
    """
    config = config or ExportConfig.load()
    if models is None:
        models = build_models(scene, library=library, config=config)
    mj = config.mujoco
    root = ET.Element("mujoco", model=str(scene.meta.get("id", "physcene_scene")))
    # Explicit inertials only: the convex parts overlap and cover a hollow shell, so their summed
    # volume is not the object's; mesh inertia "shell" keeps thin visual meshes from failing.
    ET.SubElement(root, "compiler", angle="radian", autolimits="true", inertiafromgeom="false")
    ET.SubElement(root, "option", timestep=_fmt([mj["timestep"]]), integrator=str(mj["integrator"]),
                  cone=str(mj["cone"]), impratio=_fmt([mj["impratio"]]), gravity="0 0 -9.81")
    default = ET.SubElement(root, "default")
    ET.SubElement(default, "geom", friction=_fmt(mj["friction"]), condim=str(int(mj["condim"])),
                  solref=_fmt(mj["solref"]), solimp=_fmt(mj["solimp"]), margin=_fmt([mj["margin"]]),
                  gap=_fmt([mj["gap"]]))
    visual_class = ET.SubElement(default, "default", {"class": "visual"})
    ET.SubElement(visual_class, "geom", contype="0", conaffinity="0", group="2")
    collision_class = ET.SubElement(default, "default", {"class": "collision"})
    ET.SubElement(collision_class, "geom", group="3", rgba="0.5 0.5 0.9 0.4")
    asset = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", pos="0 0 3", dir="0 0 -1", directional="true")
    centre, half = table_box(scene, config)
    ET.SubElement(world, "geom", name="table", type="box", pos=_fmt(centre), size=_fmt(half),
                  rgba="0.6 0.45 0.3 1")
    files: dict[str, bytes] = {}
    for model in models:
        vis = f"meshes/{model.name}_visual.obj"
        files[vis] = _obj_bytes(model.visual)
        ET.SubElement(asset, "mesh", name=f"{model.name}_visual", file=vis, inertia="shell")
        body = ET.SubElement(world, "body", name=model.name, pos=_fmt(model.position),
                             quat=_fmt(model.quaternion))
        ET.SubElement(body, "freejoint", name=model.name)
        i = model.inertia
        ET.SubElement(body, "inertial", pos=_fmt(model.center_of_mass), mass=_fmt([model.mass]),
                      fullinertia=_fmt([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]))
        r, g, b, _ = _color(model.category)
        ET.SubElement(body, "geom", {"class": "visual", "type": "mesh", "mesh": f"{model.name}_visual",
                                     "rgba": _fmt([r / 255, g / 255, b / 255, 1.0])})
        for k, shape in enumerate(model.collision):
            attrs = {"class": "collision", "name": f"{model.name}_c{k}"}
            if shape.kind == "mesh":
                part = f"meshes/{model.name}_c{k}.obj"
                files[part] = _obj_bytes(shape.mesh)
                ET.SubElement(asset, "mesh", name=f"{model.name}_c{k}", file=part, inertia="shell")
                attrs.update(type="mesh", mesh=f"{model.name}_c{k}")
            else:
                attrs.update(type=shape.kind, size=_fmt(shape.size))
            ET.SubElement(body, "geom", attrs)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode"), files


def export_mjcf(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write ``out_dir/scene.xml`` and its ``meshes/*.obj``; returns the XML's path."""
    xml, files = mjcf_document(scene, library=library, config=config)
    out_dir = Path(out_dir)
    for rel, data in files.items():
        _write_atomic(out_dir / rel, data)
    path = out_dir / "scene.xml"
    _write_atomic(path, xml.encode())
    return path


# URDF -------------------------------------------------------------------------------------------
def _urdf_geometry(parent: ET.Element, shape: CollisionShape | None, mesh_file: str | None) -> None:
    geometry = ET.SubElement(parent, "geometry")
    if mesh_file is not None:
        ET.SubElement(geometry, "mesh", filename=mesh_file)
    elif shape.kind == "box":
        ET.SubElement(geometry, "box", size=_fmt(2 * np.asarray(shape.size)))
    elif shape.kind == "cylinder":
        ET.SubElement(geometry, "cylinder", radius=_fmt([shape.size[0]]), length=_fmt([2 * shape.size[1]]))
    elif shape.kind == "sphere":
        ET.SubElement(geometry, "sphere", radius=_fmt([shape.size[0]]))
    else:
        raise ExportError(f"URDF has no {shape.kind!r} shape; it must be written as a mesh")


def _urdf_robot(name: str, link: str, mass: float, com, inertia, visual_file: str | None,
                shapes: Sequence[tuple[CollisionShape | None, str | None]], rgba) -> str:
    robot = ET.Element("robot", name=name)
    body = ET.SubElement(robot, "link", name=link)
    inertial = ET.SubElement(body, "inertial")
    ET.SubElement(inertial, "origin", xyz=_fmt(com), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=_fmt([mass]))
    ET.SubElement(inertial, "inertia", ixx=_fmt([inertia[0, 0]]), ixy=_fmt([inertia[0, 1]]),
                  ixz=_fmt([inertia[0, 2]]), iyy=_fmt([inertia[1, 1]]), iyz=_fmt([inertia[1, 2]]),
                  izz=_fmt([inertia[2, 2]]))
    if visual_file is not None:
        visual = ET.SubElement(body, "visual")
        ET.SubElement(visual, "origin", xyz="0 0 0", rpy="0 0 0")
        _urdf_geometry(visual, None, visual_file)
        material = ET.SubElement(visual, "material", name=f"{name}_material")
        ET.SubElement(material, "color", rgba=_fmt(rgba))
    for k, (shape, mesh_file) in enumerate(shapes):
        collision = ET.SubElement(body, "collision", name=f"{link}_c{k}")
        ET.SubElement(collision, "origin", xyz="0 0 0", rpy="0 0 0")
        _urdf_geometry(collision, shape, mesh_file)
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def export_urdf(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write one URDF per object plus the table and ``out_dir/scene.json`` listing them with poses.

    Layout: ``objects/<name>/<name>.urdf`` with ``visual.obj`` and ``collision_<k>.obj`` beside it
    (mesh paths relative to the URDF), ``table/table.urdf``. ``scene.json`` (docs/export.md):
    ``{"format": "physcene-urdf-scene", "version": 1, "units": "m", "quaternion": "wxyz",
    "gravity": [0, 0, -9.81], "table": {"urdf", "pose", "fixed": true},
    "objects": [{"id", "category", "urdf", "pose": {"position": [x, y, z], "quaternion": [w, x, y, z]},
    "fixed": false, "mass_kg"}]}``. Each object's link origin is its box centre.
    """
    config = config or ExportConfig.load()
    out_dir = Path(out_dir)
    models = build_models(scene, library=library, config=config)
    centre, half = table_box(scene, config)
    table = CollisionShape("box", tuple(half), trimesh.creation.box(extents=2 * half))
    big = 1e3 * float(np.prod(2 * half))  # a fixed base; its mass only matters to loaders that check it
    table_inertia = np.diag(big / 3.0 * np.array([half[1] ** 2 + half[2] ** 2, half[0] ** 2 + half[2] ** 2,
                                                  half[0] ** 2 + half[1] ** 2]))
    _write_atomic(out_dir / "table" / "table.urdf",
                  _urdf_robot("table", "table", big, np.zeros(3), table_inertia, None, [(table, None)],
                              [0.6, 0.45, 0.3, 1.0]).encode())
    entries = []
    for model in models:
        folder = out_dir / "objects" / model.name
        _write_atomic(folder / "visual.obj", _obj_bytes(model.visual))
        shapes = []
        for k, shape in enumerate(model.collision):
            if shape.kind in ("box", "cylinder", "sphere"):
                shapes.append((shape, None))
            else:
                _write_atomic(folder / f"collision_{k}.obj", _obj_bytes(shape.mesh))
                shapes.append((shape, f"collision_{k}.obj"))
        rgba = [c / 255 for c in _color(model.category)]
        urdf = _urdf_robot(model.name, model.name, model.mass, model.center_of_mass, model.inertia,
                           "visual.obj", shapes, rgba)
        _write_atomic(folder / f"{model.name}.urdf", urdf.encode())
        entries.append({"id": model.instance_id, "category": model.category,
                        "urdf": f"objects/{model.name}/{model.name}.urdf",
                        "pose": {"position": model.position.tolist(),
                                 "quaternion": model.quaternion.tolist()},
                        "fixed": False, "mass_kg": model.mass})
    doc = {"format": "physcene-urdf-scene", "version": 1, "units": "m", "quaternion": "wxyz",
           "gravity": [0.0, 0.0, -9.81],
           "table": {"urdf": "table/table.urdf",
                     "pose": {"position": centre.tolist(), "quaternion": [1.0, 0.0, 0.0, 0.0]},
                     "fixed": True},
           "objects": entries}
    path = out_dir / "scene.json"
    _write_atomic(path, (json.dumps(doc, indent=2) + "\n").encode())
    return path


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def export(scene: Scene, out_dir, fmt: str, *, library=None, config: ExportConfig | None = None) -> Path:
    """Export in one of :data:`FORMATS`; returns the main file written."""
    writers = {"glb": export_glb, "mjcf": export_mjcf, "urdf": export_urdf}
    if fmt not in writers:
        raise ExportError(f"unknown export format {fmt!r}; expected one of {FORMATS}")
    return writers[fmt](scene, out_dir, library=library, config=config)

