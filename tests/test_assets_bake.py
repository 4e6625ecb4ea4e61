"""Acceptance of the SDF bake (issue 3): accuracy, signs, open meshes, cavities, CPU vs CUDA."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import trimesh

import physcene.kernels
from physcene import cli
from physcene.assets import (
    CATEGORY_PRIORS,
    BakeCache,
    BakeUnavailableError,
    bake_mesh_asset,
    normalise_mesh,
    primitive_asset,
    procedural_mesh,
    sample_sdf,
    sign_method_for,
)
from physcene.assets.primitives import box_sdf, cylinder_sdf, sphere_sdf
from physcene.kernels.sdf_bake import bake_sdf

R = 64
VOXEL = 2.0 / (R - 1)
TORUS_R, TORUS_r = 0.6, 0.3


def _torus_sdf(q):
    return np.sqrt((np.linalg.norm(q[..., :2], axis=-1) - TORUS_R) ** 2 + q[..., 2] ** 2) - TORUS_r


def _random_points(n=10_000, seed=0):
    return np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n, 3))


def _check_accuracy(grid, exact_fn):
    q = _random_points()
    approx, exact = sample_sdf(grid, q), exact_fn(q)
    err = np.abs(approx - exact)
    assert err.max() <= 0.5 * VOXEL, f"max |phi_grid - phi_exact| = {err.max() / VOXEL:.3f} voxel"
    far = np.abs(exact) > VOXEL
    assert far.sum() > 5000
    assert np.all(np.sign(approx[far]) == np.sign(exact[far]))
    return err.max() / VOXEL


@pytest.mark.parametrize(
    "kind,exact_fn", [("box", box_sdf), ("cylinder", cylinder_sdf), ("sphere", sphere_sdf)]
)
def test_primitive_grid_accuracy(kind, exact_fn):
    _check_accuracy(primitive_asset(kind, resolution=R), exact_fn)


@pytest.mark.parametrize("name", ["sphere", "torus"])
def test_warp_bake_of_watertight_meshes_is_within_half_a_voxel(name):
    if name == "sphere":
        mesh, exact_fn = trimesh.creation.icosphere(subdivisions=4, radius=1.0), sphere_sdf
    else:
        mesh, exact_fn = (
            trimesh.creation.torus(TORUS_R, TORUS_r, major_sections=128, minor_sections=64),
            _torus_sdf,
        )
    assert sign_method_for(mesh) == "parity"
    grid = bake_sdf(mesh.vertices, mesh.faces, R, sign_method="parity")
    assert grid.shape == (R, R, R) and grid.dtype == np.float32
    # the nodes themselves: exact up to the mesh's own tessellation error
    g = np.linspace(-1, 1, R)
    nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    assert np.abs(grid - exact_fn(nodes)).max() < 0.05 * VOXEL
    _check_accuracy(grid, exact_fn)
    # the winding-number sign agrees with parity away from the surface
    winding = bake_sdf(mesh.vertices, mesh.faces, 24, sign_method="winding")
    parity = bake_sdf(mesh.vertices, mesh.faces, 24, sign_method="parity")
    np.testing.assert_allclose(winding, parity, atol=1e-6)


def _open_bowl():
    """The procedural bowl with its rim ring deleted: an open, non-watertight shell."""
    closed, _ = normalise_mesh(procedural_mesh("bowl"))
    top = closed.vertices[:, 2].max()
    keep = ~np.all(np.isclose(closed.vertices[closed.faces][:, :, 2], top, atol=1e-6), axis=1)
    open_mesh = trimesh.Trimesh(closed.vertices, closed.faces[keep], process=False)
    return closed, open_mesh


def test_open_bowl_gets_a_consistent_inside():
    closed, open_mesh = _open_bowl()
    assert not open_mesh.is_watertight and sign_method_for(open_mesh) == "winding"
    res = 40
    voxel = 2.0 / (res - 1)
    reference = bake_sdf(closed.vertices, closed.faces, res, sign_method="parity")
    grid = bake_sdf(open_mesh.vertices, open_mesh.faces, res, sign_method="winding")
    g = np.linspace(-1, 1, res)
    nodes = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    # away from the missing rim, inside and outside are those of the closed bowl: the wall material
    # (thinner than a voxel or two, so compared at nodes a quarter voxel from the surface) inside,
    # the cavity and the world outside
    rim_gap = nodes[..., 2] > 1.0 - 3 * voxel
    far = (np.abs(reference) > 0.25 * voxel) & ~rim_gap
    assert np.any(reference[far] < 0) and np.any(reference[far] > 0)
    assert np.all(np.sign(grid[far]) == np.sign(reference[far]))
    assert sample_sdf(grid, np.array([0.0, 0.0, 0.3])) > 0  # the cavity


def _without_warp(monkeypatch):
    """Import physcene.kernels.sdf_bake fails from here on, as on a machine without Warp."""
    monkeypatch.delattr(physcene.kernels, "sdf_bake", raising=False)
    monkeypatch.setitem(sys.modules, "physcene.kernels.sdf_bake", None)


def test_without_warp_a_cached_asset_loads_and_one_to_bake_is_one_error_naming_it(tmp_path, monkeypatch):
    box = trimesh.creation.box((1.0, 2.0, 0.5))
    bake = dict(category="cup", source="test", resolution=16, n_points=64, cache=BakeCache(tmp_path))
    baked = bake_mesh_asset(box, asset_id="cup_01", **bake)
    _without_warp(monkeypatch)
    again = bake_mesh_asset(box, asset_id="cup_01", **bake)  # a cache hit needs no Warp
    np.testing.assert_array_equal(again.sdf, baked.sdf)
    sphere = trimesh.creation.icosphere(subdivisions=2)  # another shape (every box normalises to one)
    message = r"asset 'cup_02': baking its SDF \(not in .*\) needs Warp"
    with pytest.raises(BakeUnavailableError, match=message) as err:
        bake_mesh_asset(sphere, asset_id="cup_02", **bake)
    assert str(tmp_path) in str(err.value) and "PHYSCENE_CACHE" in str(err.value)
    with pytest.raises(BakeUnavailableError, match=r"asset 'bowl_01': classifying its open mesh needs Warp"):
        bake_mesh_asset(_open_bowl()[1], asset_id="bowl_01", **bake)


def test_the_cli_reports_a_bake_without_warp_as_one_line(tmp_path, monkeypatch, capsys):
    _without_warp(monkeypatch)
    monkeypatch.setenv("PHYSCENE_CACHE", str(tmp_path))
    assert cli.main(["assets", "bake", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("physcene assets: error: asset ") and "needs Warp" in err
    assert len(err.strip().splitlines()) == 1


def _sheet_bowl():
    """A hemisphere surface stretched to fill the cube: one layer, no thickness."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    keep = sphere.triangles_center[:, 2] < 0.0
    sheet = trimesh.Trimesh(sphere.vertices, sphere.faces[keep])
    sheet.remove_unreferenced_vertices()
    return normalise_mesh(sheet)[0]


def test_single_layer_bowl_is_a_thin_shell_with_an_empty_cavity():
    sheet = _sheet_bowl()
    assert sign_method_for(sheet) == "shell"
    res = 32
    voxel = 2.0 / (res - 1)
    grid = bake_sdf(sheet.vertices, sheet.faces, res, sign_method="shell")
    # the winding number alone would fill the cavity
    assert sample_sdf(bake_sdf(sheet.vertices, sheet.faces, res, sign_method="winding"), [0.0, 0.0, 0.0]) < 0
    q = _random_points(2000, seed=1)
    distance = sample_sdf(grid, q) + voxel  # back to the unsigned distance
    inside_cavity = (np.linalg.norm(q[:, :2], axis=1) < 0.5) & (q[:, 2] > 0.0)
    assert np.all(sample_sdf(grid, q[inside_cavity]) > 0)  # the cavity is empty
    assert np.all(distance > -0.5 * voxel)
    bottom = sheet.vertices[np.argmin(sheet.vertices[:, 2])]
    assert sample_sdf(grid, bottom) < 0  # the sheet itself is solid, one voxel each side


# Where each container's cavity is, in cm, measured from its builder in physcene.assets.procedural:
# (x of the body axis relative to the bounding-box centre, floor height above the base, cube side).
_CAVITIES = {
    "mug": (lambda w, d, h: -(w - d) / 2, 0.6, 2.0),
    "bowl": (lambda w, d, h: 0.0, 6.5 * 0.15 + 0.4, 2.0),
    "basket": (lambda w, d, h: 0.0, 0.8, 3.0),
    "pen_holder": (lambda w, d, h: 0.0, 0.6, 2.0),
}


@pytest.fixture(scope="module")
def containers():
    return {
        c: bake_mesh_asset(
            procedural_mesh(c), asset_id=f"procedural:{c}", category=c, source="procedural", resolution=R
        )
        for c in _CAVITIES
    }


def _cube_points_in_container(asset, center_cm, side_cm):
    """The container-frame normalised coordinates of a cube's surface points."""
    cube = primitive_asset("box", resolution=2).points.astype(np.float64) * side_cm / 2 + center_cm
    return cube / (np.array(asset.extents) / 2)


@pytest.mark.parametrize("category", sorted(_CAVITIES))
def test_small_cube_inside_a_container_is_outside_its_shape(containers, category):
    asset = containers[category]
    w, d, h = CATEGORY_PRIORS[category].mean_cm
    assert np.allclose(asset.extents, (w, d, h))
    axis_x, floor, side = _CAVITIES[category]
    center = np.array([axis_x(w, d, h), 0.0, -h / 2 + floor + side / 2 + 0.3])
    q = _cube_points_in_container(asset, center, side)
    phi_cm = sample_sdf(asset, q) * min(asset.extents) / 2  # the engine's conservative scaling
    assert np.all(phi_cm > 0), (
        f"{category}: {np.sum(phi_cm <= 0)} cube points inside, min {phi_cm.min():.3f} cm"
    )
    # not vacuous: the same cube pushed into the side wall penetrates
    into_wall = center + np.array([0.0, d / 2, 0.0])
    assert np.any(sample_sdf(asset, _cube_points_in_container(asset, into_wall, side)) < 0)


@pytest.mark.cuda
def test_cpu_and_cuda_bakes_agree():
    meshes = [
        trimesh.creation.torus(TORUS_R, TORUS_r, major_sections=128, minor_sections=64),
        normalise_mesh(procedural_mesh("mug"))[0],
        _open_bowl()[1],
        _sheet_bowl(),
    ]
    worst = 0.0
    for mesh in meshes:
        method = sign_method_for(mesh)
        cpu = bake_sdf(mesh.vertices, mesh.faces, R, sign_method=method, device="cpu")
        gpu = bake_sdf(mesh.vertices, mesh.faces, R, sign_method=method, device="cuda:0")
        worst = max(worst, float(np.abs(cpu - gpu).max()))
    print(f"max |cpu - cuda| = {worst:.3g}")
    assert worst <= 1e-4
