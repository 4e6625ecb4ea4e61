"""Assets: shapes with baked SDF grids and surface points (see :mod:`physcene.assets.asset`).

Public API: :class:`Asset`, :func:`primitive_asset`, :class:`AssetLibrary` (``resolve`` ->
:class:`Retrieval`), :func:`default_library`, :data:`CATEGORY_PRIORS` (:class:`SizePrior`),
:func:`procedural_mesh`, :func:`sample_sdf`. Docs: docs/assets.md.
"""

from physcene.assets.asset import Asset, grid_coordinates
from physcene.assets.bake import BakeUnavailableError, bake_mesh_asset, normalise_mesh, sign_method_for
from physcene.assets.cache import BakeCache, default_cache_dir
from physcene.assets.categories import (
    CATEGORY_ALIASES,
    CATEGORY_PRIORS,
    IID_SCENE_TYPES,
    OOD_SCENE_TYPES,
    SIZE_SIGMA_FLOOR,
    SizePrior,
    canonical_category,
    categories_for_scene_type,
)
from physcene.assets.library import AssetEntry, AssetLibrary, Retrieval, default_library
from physcene.assets.mesh_folder import AssetFileError, load_mesh_file, normalise_category, scan_mesh_folder
from physcene.assets.primitives import PRIMITIVES, primitive_asset
from physcene.assets.procedural import PROCEDURAL_BUILDERS, procedural_mesh
from physcene.assets.surface import sample_sdf, surface_points

__all__ = [
    "CATEGORY_ALIASES", "CATEGORY_PRIORS", "IID_SCENE_TYPES", "OOD_SCENE_TYPES", "PRIMITIVES",
    "PROCEDURAL_BUILDERS", "SIZE_SIGMA_FLOOR", "Asset", "AssetEntry", "AssetFileError", "AssetLibrary",
    "BakeCache", "BakeUnavailableError", "Retrieval", "SizePrior", "bake_mesh_asset", "canonical_category",
    "categories_for_scene_type", "default_cache_dir", "default_library", "grid_coordinates",
    "load_mesh_file", "normalise_category", "normalise_mesh", "primitive_asset", "procedural_mesh",
    "sample_sdf", "scan_mesh_folder", "sign_method_for", "surface_points",
]
