"""Assets: shapes with baked SDF grids and surface points (see :mod:`physcene.assets.asset`)."""

from physcene.assets.asset import Asset, grid_coordinates
from physcene.assets.primitives import PRIMITIVES, primitive_asset

__all__ = ["PRIMITIVES", "Asset", "grid_coordinates", "primitive_asset"]
