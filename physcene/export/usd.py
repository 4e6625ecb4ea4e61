"""USD (Isaac Sim / IsaacLab): one stage with UsdPhysics rigid bodies, written with ``pxr`` (usd-core).

The stage mirrors the MJCF export body for body (:mod:`physcene.export.mjcf` reads the same
:class:`~physcene.export.models.ObjectModel`): ``/World/table`` a static box collider,
``/World/Objects/<name>`` one ``Xform`` per object with ``RigidBodyAPI`` and ``MassAPI`` (mass,
centre of mass, principal inertia), a ``visual`` mesh and ``collision/c<k>`` children: native
``Cube`` / ``Cylinder`` / ``Sphere`` prims for the exact primitives, convex meshes
(``physics:approximation = convexHull``) for the CoACD parts. Metres, +z up, ``PhysicsScene`` with
gravity -9.81 m/s^2.

mujoco-usd-converter (the MJCF -> USD converter of the Newton project) pins ``mujoco<3.17``, which
the ``[sim]`` extra's MuJoCo 4 excludes; physcene therefore writes the stage itself. The converter
still reads the MJCF export (``physcene export ... --format mjcf``) in an environment of its own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from physcene.export.models import (
    ExportConfig,
    ExportError,
    ObjectModel,
    build_models,
    category_color,
    table_box,
)
from physcene.files import write_atomic
from physcene.scene import Scene

__all__ = ["export_usd", "usd_stage"]


def _pxr():
    # pxr is the [usd] extra: imported here so that the other exporters work without it.
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt
    except ImportError as exc:
        raise ExportError("--format usd needs usd-core: pip install 'physcene[usd]'") from exc
    return Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt


def _mesh(UsdGeom, Vt, Gf, stage, path: str, mesh: trimesh.Trimesh):
    prim = UsdGeom.Mesh.Define(stage, path)
    prim.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, v)) for v in mesh.vertices]))
    prim.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(mesh.faces)))
    prim.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in np.ravel(mesh.faces)]))
    prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    return prim


def _principal(inertia: np.ndarray):
    """(principal moments (3,), rotation quaternion w, x, y, z of the principal axes)."""
    moments, axes = np.linalg.eigh(0.5 * (inertia + inertia.T))
    if np.linalg.det(axes) < 0:
        axes[:, 2] = -axes[:, 2]
    quat = trimesh.transformations.quaternion_from_matrix(np.block([[axes, np.zeros((3, 1))],
                                                                    [np.zeros((1, 3)), np.ones((1, 1))]]))
    return moments, quat


def usd_stage(scene: Scene, *, library=None, config: ExportConfig | None = None,
              models: list[ObjectModel] | None = None, path: str | None = None):
    """The scene as a ``pxr.Usd.Stage`` (in memory, or created at ``path``)."""
    Gf, Sdf, Usd, UsdGeom, UsdPhysics, Vt = _pxr()
    config = config or ExportConfig.load()
    if models is None:
        models = build_models(scene, library=library, config=config)
    stage = Usd.Stage.CreateNew(path) if path else Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    physics = UsdPhysics.Scene.Define(stage, "/World/PhysicsScene")
    physics.CreateGravityDirectionAttr(Gf.Vec3f(0.0, 0.0, -1.0))
    physics.CreateGravityMagnitudeAttr(9.81)

    centre, half = table_box(scene, config)
    table = UsdGeom.Cube.Define(stage, "/World/table")
    table.CreateSizeAttr(2.0)  # a Cube spans [-size/2, size/2]: size 2 and a scale of the half extents
    table.AddTranslateOp().Set(Gf.Vec3d(*map(float, centre)))
    table.AddScaleOp().Set(Gf.Vec3f(*map(float, half)))
    table.CreateDisplayColorAttr([Gf.Vec3f(0.6, 0.45, 0.3)])
    UsdPhysics.CollisionAPI.Apply(table.GetPrim())  # a collider without a rigid body is static

    UsdGeom.Scope.Define(stage, "/World/Objects")
    for model in models:
        root = f"/World/Objects/{_prim_name(model.name)}"
        body = UsdGeom.Xform.Define(stage, root)
        body.AddTranslateOp().Set(Gf.Vec3d(*map(float, model.position)))
        w, x, y, z = map(float, model.quaternion)
        body.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(w, x, y, z))
        prim = body.GetPrim()
        prim.SetCustomDataByKey("physcene:instance_id", model.instance_id)
        prim.SetCustomDataByKey("physcene:category", model.category)
        UsdPhysics.RigidBodyAPI.Apply(prim)
        mass = UsdPhysics.MassAPI.Apply(prim)
        mass.CreateMassAttr(float(model.mass))
        mass.CreateCenterOfMassAttr(Gf.Vec3f(*map(float, model.center_of_mass)))
        moments, axes = _principal(model.inertia)
        mass.CreateDiagonalInertiaAttr(Gf.Vec3f(*map(float, moments)))
        mass.CreatePrincipalAxesAttr(Gf.Quatf(*map(float, axes)))
        visual = _mesh(UsdGeom, Vt, Gf, stage, f"{root}/visual", model.visual)
        r, g, b, _ = category_color(model.category)
        visual.CreateDisplayColorAttr([Gf.Vec3f(r / 255, g / 255, b / 255)])
        UsdGeom.Scope.Define(stage, f"{root}/collision")
        for k, shape in enumerate(model.collision):
            _collider(stage, f"{root}/collision/c{k}", shape, Gf, UsdGeom, UsdPhysics, Vt)
    return stage


def _prim_name(name: str) -> str:
    # A prim name is an identifier: letters, digits, underscores, not starting with a digit.
    clean = "".join(c if c.isalnum() or c == "_" else "_" for c in name)
    return clean if clean[:1].isalpha() or clean[:1] == "_" else f"_{clean}"


def _collider(stage, path: str, shape, Gf, UsdGeom, UsdPhysics, Vt) -> None:
    if shape.kind == "box":
        geom = UsdGeom.Cube.Define(stage, path)
        geom.CreateSizeAttr(2.0)
        geom.AddScaleOp().Set(Gf.Vec3f(*map(float, shape.size)))
    elif shape.kind == "cylinder":
        geom = UsdGeom.Cylinder.Define(stage, path)
        geom.CreateAxisAttr(UsdGeom.Tokens.z)
        geom.CreateRadiusAttr(float(shape.size[0]))
        geom.CreateHeightAttr(2.0 * float(shape.size[1]))
    elif shape.kind == "sphere":
        geom = UsdGeom.Sphere.Define(stage, path)
        geom.CreateRadiusAttr(float(shape.size[0]))
    elif shape.kind == "ellipsoid":  # a unit sphere scaled by the three radii
        geom = UsdGeom.Sphere.Define(stage, path)
        geom.CreateRadiusAttr(1.0)
        geom.AddScaleOp().Set(Gf.Vec3f(*map(float, shape.size)))
    else:
        geom = _mesh(UsdGeom, Vt, Gf, stage, path, shape.mesh)
        UsdPhysics.MeshCollisionAPI.Apply(geom.GetPrim()).CreateApproximationAttr("convexHull")
    geom.CreatePurposeAttr(UsdGeom.Tokens.guide)  # colliders are not drawn in a render
    UsdPhysics.CollisionAPI.Apply(geom.GetPrim())


def export_usd(scene: Scene, out_dir, *, library=None, config: ExportConfig | None = None) -> Path:
    """Write ``out_dir/scene.usda`` (text USD, one file: meshes inline); returns its path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "scene.usda"
    stage = usd_stage(scene, library=library, config=config)
    # Exported from memory and written whole: a reader never sees half a stage.
    write_atomic(path, stage.GetRootLayer().ExportToString())
    return path
