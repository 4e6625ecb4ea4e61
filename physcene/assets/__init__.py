"""Assets: shapes with baked SDF grids and surface points (see :mod:`physcene.assets.asset`)."""

from physcene.assets.asset import Asset, grid_coordinates
from physcene.assets.categories import (
    CATEGORY_ALIASES,
    CATEGORY_PRIORS,
    IID_SCENE_TYPES,
    OOD_SCENE_TYPES,
    SizePrior,
    categories_for_scene_type,
)
from physcene.assets.primitives import PRIMITIVES, primitive_asset

__all__ = ["CATEGORY_ALIASES", "CATEGORY_PRIORS", "IID_SCENE_TYPES", "OOD_SCENE_TYPES", "PRIMITIVES",
           "Asset", "SizePrior", "categories_for_scene_type", "grid_coordinates", "primitive_asset"]
