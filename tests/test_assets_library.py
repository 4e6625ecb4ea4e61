"""Asset library: categories, retrieval, surface points, cache, mesh folders, bad files, CLI."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import trimesh

import physcene.assets.cache as cache_module
from physcene.assets import (
    CATEGORY_PRIORS,
    IID_SCENE_TYPES,
    OOD_SCENE_TYPES,
    PROCEDURAL_BUILDERS,
    AssetFileError,
    AssetLibrary,
    BakeCache,
    bake_mesh_asset,
    categories_for_scene_type,
    load_mesh_file,
    normalise_category,
    primitive_asset,
    procedural_mesh,
    sample_sdf,
    surface_points,
)
from physcene.cli import main

REQUIRED = {
    "container": [
        "mug",
        "cup",
        "bowl",
        "pot",
        "basket",
        "pen_holder",
        "vase",
        "plate",
        "tray",
        "open_box",
        "soap_dish",
        "toothbrush_cup",
    ],
    "support": ["book", "laptop", "cutting_board", "saucer", "monitor_stand"],
    "object": [
        "lamp",
        "headphones",
        "plant",
        "teapot",
        "monitor",
        "pen",
        "toothbrush",
        "soap",
        "apple",
        "orange",
        "banana",
        "lemon",
        "candle",
        "keyboard",
        "mouse",
        "phone",
        "remote",
        "glasses",
        "bottle",
        "lotion_bottle",
        "jar",
        "spoon",
        "fork",
        "knife",
        "wallet",
        "keys",
        "clock",
        "picture_frame",
        "tissue_box",
        "cash_register",
    ],
}


# ------------------------------------------------------------------ categories and procedural meshes


def test_category_priors_cover_the_brief():
    assert len(CATEGORY_PRIORS) >= 40
    for role, names in REQUIRED.items():
        for name in names:
            assert name in CATEGORY_PRIORS, name
            if role != "object":
                assert CATEGORY_PRIORS[name].role == role, name
    for name, prior in CATEGORY_PRIORS.items():
        assert name == normalise_category(name), f"{name} is not lower_snake_case singular"
        assert all(0 < s < m for s, m in zip(prior.std_cm, prior.mean_cm)), name
        assert max(prior.mean_cm) < 120, name
    for scene_type in IID_SCENE_TYPES + OOD_SCENE_TYPES:
        assert len(categories_for_scene_type(scene_type)) >= 10, scene_type
    assert "mug" in categories_for_scene_type("Office_Table")


def test_every_category_has_a_watertight_procedural_mesh_of_its_prior_size():
    assert set(PROCEDURAL_BUILDERS) == set(CATEGORY_PRIORS)
    for category, prior in CATEGORY_PRIORS.items():
        mesh = procedural_mesh(category)
        assert mesh.is_watertight and mesh.volume > 0, category
        np.testing.assert_allclose(mesh.extents, prior.mean_cm, rtol=1e-6, err_msg=category)
        assert abs(mesh.bounds[0][2]) < 1e-9, category


def test_containers_have_real_cavities():
    for category, prior in CATEGORY_PRIORS.items():
        if prior.role != "container":
            continue
        mesh = procedural_mesh(category)
        w, d, h = prior.mean_cm
        # a vertical line through the cavity (off the basket's handle, on the body axis of a cup with a
        # handle) first meets the floor, low down: the top is open
        axis_x = -(w - d) / 2 if category in ("mug", "teacup") else 0.0
        off_y = d / 4 if category == "basket" else 0.0
        hits, _, _ = mesh.ray.intersects_location([[axis_x, off_y, h + 5.0]], [[0.0, 0.0, -1.0]])
        top_hit = hits[:, 2].max()
        assert top_hit < h * 0.5, f"{category}: first surface under the opening at z={top_hit:.2f} of h={h}"
        assert mesh.volume < 0.6 * w * d * h, category


# ------------------------------------------------------------------ retrieval


@pytest.fixture
def library(tmp_path):
    lib = AssetLibrary(resolution=12, n_points=64, cache=BakeCache(tmp_path / "cache"))
    lib.add_primitives()
    lib.add_procedural(["mug", "book", "lamp", "pen_holder", "coffee_maker"])
    return lib


def test_resolve_exact_by_id_and_by_category(library):
    r = library.resolve("book")
    assert r.fallback is None and r.asset.asset_id == "procedural:book" and r.asset.category == "book"
    r = library.resolve("anything", asset_id="procedural:mug")
    assert r.fallback is None and r.asset.asset_id == "procedural:mug"
    assert library.resolve("sphere").asset.asset_id == "primitive:sphere"


@pytest.mark.parametrize(
    "asked,expected",
    [
        ("coffee_mug", "mug"),
        ("books", "book"),
        ("desk_lamp", "lamp"),
        ("Pen Holders", "pen_holder"),
        ("table_lamp_small", "lamp"),
    ],
)
def test_resolve_nearest_category_is_reported(library, asked, expected):
    r = library.resolve(asked)
    assert r.asset.category == expected
    assert r.fallback is not None and asked in r.fallback and expected in r.fallback


def test_resolve_unknown_falls_back_to_a_box_and_warns_once(library, caplog):
    with caplog.at_level(logging.WARNING, logger="physcene.assets"):
        r1 = library.resolve("spaceship")
        r2 = library.resolve("spaceship")
    assert r1.asset.asset_id == r2.asset.asset_id == "primitive:box"
    assert "box" in r1.fallback
    assert sum("spaceship" in m for m in caplog.messages) == 1


def test_resolve_unknown_asset_id_falls_back_to_category(library):
    r = library.resolve("mug", asset_id="no-such-uid")
    assert r.asset.asset_id == "procedural:mug" and "no-such-uid" in r.fallback


def test_assets_are_memoised(library):
    assert library.get("procedural:mug") is library.get("procedural:mug")


# ------------------------------------------------------------------ surface points and sampling


def test_surface_points_are_deterministic_and_include_corners():
    mesh = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    a = surface_points(mesh, 256, seed=3)
    b = surface_points(mesh, 256, seed=3)
    c = surface_points(mesh, 256, seed=4)
    assert a.shape == (256, 3) and np.array_equal(a, b) and not np.array_equal(a, c)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
    assert all(np.any(np.all(np.isclose(a, k), axis=1)) for k in corners)
    on_edge = np.sum(np.isclose(np.abs(a), 1.0), axis=1) >= 2
    assert on_edge.sum() >= 0.2 * 256  # the sharp-edge share
    assert np.all(np.isclose(np.abs(a).max(axis=1), 1.0))  # every point on the surface


def test_baked_points_lie_on_the_zero_level_set():
    asset = bake_mesh_asset(
        procedural_mesh("mug"), asset_id="m", category="mug", source="test", resolution=32, n_points=256
    )
    assert asset.points.shape == (256, 3)
    assert np.abs(asset.points).max() <= 1.0 + 1e-6
    assert np.abs(sample_sdf(asset, asset.points)).max() < 1.0 * asset.voxel


def test_sample_sdf_reproduces_trilinear_fields_exactly():
    g = np.linspace(-1, 1, 9)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    grid = x * y * z + 2 * x - y + 0.5
    q = np.random.default_rng(0).uniform(-1, 1, (500, 3))
    exact = q[:, 0] * q[:, 1] * q[:, 2] + 2 * q[:, 0] - q[:, 1] + 0.5
    np.testing.assert_allclose(sample_sdf(grid, q), exact, atol=1e-12)
    np.testing.assert_allclose(sample_sdf(grid, np.array([2.0, 0.0, 0.0])), 2.5 + 1.0)  # outside: + distance


# ------------------------------------------------------------------ cache


def _bake(mesh, cache):
    return bake_mesh_asset(
        mesh, asset_id="t", category="t", source="test", resolution=10, n_points=32, cache=cache
    )


def test_cache_hit_returns_identical_arrays_without_baking(tmp_path, monkeypatch):
    cache = BakeCache(tmp_path)
    mesh = procedural_mesh("cup")
    first = _bake(mesh, cache)
    assert len(list(tmp_path.glob("*.npz"))) == 1

    def no_bake(*a, **k):
        raise AssertionError("baked despite a cache hit")

    monkeypatch.setattr("physcene.kernels.sdf_bake.bake_sdf", no_bake)
    second = _bake(mesh, cache)
    assert np.array_equal(first.sdf, second.sdf) and np.array_equal(first.points, second.points)


def test_cache_key_depends_on_content_and_settings():
    mesh = procedural_mesh("cup")
    k = BakeCache.key(mesh.vertices, mesh.faces, resolution=64, n_points=1024, seed=0, sign_method="parity")
    moved = mesh.vertices + 1e-3
    assert k != BakeCache.key(moved, mesh.faces, resolution=64, n_points=1024, seed=0, sign_method="parity")
    assert k != BakeCache.key(
        mesh.vertices, mesh.faces, resolution=32, n_points=1024, seed=0, sign_method="parity"
    )
    assert k != BakeCache.key(
        mesh.vertices, mesh.faces, resolution=64, n_points=512, seed=0, sign_method="parity"
    )
    for weighting in ({"points_scale": (11.0, 8.0, 1.5)}, {"edge_angle_deg": 45.0}):  # the points' inputs
        assert k != BakeCache.key(
            mesh.vertices, mesh.faces, resolution=64, n_points=1024, seed=0, sign_method="parity", **weighting
        )


def test_slabs_share_one_bake_whichever_is_baked_first(tmp_path):
    """Book, towel and phone are one box in the normalised frame: one cache entry, whose points are
    weighed by the first of them in CATEGORY_PRIORS order (book), in every process and bake order.
    Before, the entry held the points of whichever slab a machine baked first, so a scene's seating
    (and the split synthesised from it) depended on what had been baked earlier."""
    from physcene.assets.library import procedural_points_scale

    assert procedural_points_scale("towel") == procedural_points_scale("phone") == tuple(
        m / 2 for m in CATEGORY_PRIORS["book"].mean_cm)
    assert procedural_points_scale("mug") == tuple(m / 2 for m in CATEGORY_PRIORS["mug"].mean_cm)
    points = {}
    for order in (("towel", "phone", "book"), ("book", "phone", "towel")):
        cache = BakeCache(tmp_path / "-".join(order))
        library = AssetLibrary(resolution=10, n_points=32, cache=cache)
        library.add_procedural(order)
        points[order] = {c: library.get(f"procedural:{c}").points for c in order}
        assert len(list(cache.root.glob("*.npz"))) == 1
    first, second = points.values()
    for category in ("towel", "phone", "book"):
        assert np.array_equal(first[category], second[category])
        assert np.array_equal(first[category], first["book"])


def test_corrupt_cache_entry_is_detected_and_rebaked(tmp_path, caplog):
    cache = BakeCache(tmp_path)
    mesh = procedural_mesh("cup")
    good = _bake(mesh, cache)
    (entry,) = tmp_path.glob("*.npz")
    entry.write_bytes(entry.read_bytes()[: entry.stat().st_size // 2])  # truncated
    with caplog.at_level(logging.WARNING):
        again = _bake(mesh, cache)
    assert "corrupt" in caplog.text
    assert np.array_equal(good.sdf, again.sdf)
    assert cache.load(entry.stem, 10, 32) is not None  # rewritten whole


def test_interrupted_bake_leaves_no_cache_entry(tmp_path, monkeypatch):
    cache = BakeCache(tmp_path)

    def failing_write(f, **arrays):
        f.write(b"PK\x03\x04 half an npz")
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(cache_module, "_write_npz", failing_write)
    with pytest.raises(KeyboardInterrupt):
        _bake(procedural_mesh("cup"), cache)
    assert list(tmp_path.iterdir()) == []  # neither an entry nor a temp file


def test_cache_dir_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("PHYSCENE_CACHE", str(tmp_path))
    assert BakeCache().root == tmp_path / "assets"


# ------------------------------------------------------------------ mesh files and folders


def test_bad_mesh_files_name_the_file(tmp_path):
    empty = tmp_path / "empty.glb"
    empty.write_bytes(b"")
    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(b"glTF\x02\x00\x00\x00 not really")
    text = tmp_path / "notes.obj"
    text.write_text("this is a shopping list, not a mesh\n")
    for path in (empty, garbage, text, tmp_path / "missing.obj"):
        with pytest.raises(AssetFileError, match=path.name):
            load_mesh_file(path)


def test_flat_mesh_is_refused_by_name():
    plane = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="sheet"):
        bake_mesh_asset(plane, asset_id="sheet", category="paper", source="test", resolution=8, n_points=8)


def test_mesatask_folder_with_annotation(tmp_path):
    lib_dir = tmp_path / "Assets_library"
    lib_dir.mkdir()
    # a glTF mug-ish cylinder: Y up, metres (8 cm wide, 10 cm tall)
    cyl = trimesh.creation.cylinder(radius=0.04, height=0.10, sections=24)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, (1, 0, 0)))  # its axis along +y
    cyl.export(lib_dir / "a1b2c3.glb")
    trimesh.creation.box(extents=(0.3, 0.02, 0.2)).export(lib_dir / "d4e5f6.glb")
    (tmp_path / "Asset_annotation.json").write_text(
        json.dumps(
            {
                "a1b2c3": {"category": "Coffee Mugs", "description": "A white mug."},
                "d4e5f6": {"category": "picture frame", "description": "A wooden frame."},
            }
        )
    )
    lib = AssetLibrary(resolution=10, n_points=32)
    assert lib.add_folder(lib_dir) == 2
    mug = lib.resolve("coffee_mug", asset_id="a1b2c3").asset
    assert mug.category == "coffee_mug" and mug.description == "A white mug."
    np.testing.assert_allclose(mug.extents, (8.0, 8.0, 10.0), atol=0.05)  # Z up, cm
    frame = lib.resolve("picture_frame").asset
    assert frame.asset_id == "d4e5f6" and frame.source.startswith("folder:")
    np.testing.assert_allclose(frame.extents, (30.0, 20.0, 2.0), atol=1e-6)  # glTF up (y, 2 cm) is z


def test_plain_obj_folder_reads_categories_from_file_names(tmp_path):
    trimesh.creation.icosphere(2).export(tmp_path / "orange_01.obj")
    lib = AssetLibrary(resolution=8, n_points=16)
    lib.add_folder(tmp_path)
    assert lib.resolve("orange").asset.asset_id == "orange_01"


# ------------------------------------------------------------------ CLI


def test_cli_list_json(capsys):
    assert main(["assets", "list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert {"category", "asset_id", "source"} == set(rows[0])
    ids = {r["asset_id"] for r in rows}
    assert {"primitive:box", "procedural:mug", "procedural:basket"} <= ids
    assert len(rows) == len(CATEGORY_PRIORS) + 3


def test_cli_bake_into_a_cache_dir(tmp_path, capsys):
    code = main(
        [
            "assets",
            "bake",
            "--category",
            "book",
            "--category",
            "cup",
            f"cache_dir={tmp_path}",
            "resolution=10",
            "n_points=32",
        ]
    )
    assert code == 0
    assert len(list(tmp_path.glob("*.npz"))) == 2
    assert main(["assets", "bake", "--category", "no_such_thing"]) == 2


def test_primitive_asset_contract():
    a = primitive_asset("cylinder", resolution=16, n_points=100)
    assert a.sdf.shape == (16, 16, 16) and a.points.shape[1] == 3 and a.source == "primitive"


def test_malformed_annotation_names_the_file(tmp_path):
    trimesh.creation.box().export(tmp_path / "abc.glb")
    (tmp_path / "Asset_annotation.json").write_text("{not json")
    with pytest.raises(AssetFileError, match="Asset_annotation.json"):
        AssetLibrary().add_folder(tmp_path)


def test_default_library_is_built_once_and_lists_every_category():
    from physcene.assets import default_library

    lib = default_library()
    assert lib is default_library()
    assert set(CATEGORY_PRIORS) | {"box", "cylinder", "sphere"} <= set(lib.categories())
