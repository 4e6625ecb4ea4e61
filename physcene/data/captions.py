"""Caption bank: short object descriptions in the style of MesaTask's asset annotations.

A description is composed from a category's shape words, material words and features
("Cylindrical ceramic mug with a curved handle."); categories without an entry get a generic
one built from their size class. Deterministic given the RNG.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CAPTION_BANK", "describe"]

# category -> (shapes, materials, features)
CAPTION_BANK: dict[str, tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]] = {
    "mug": (
        ("cylindrical", "straight-walled", "slightly tapered"),
        ("ceramic", "stoneware", "enamel"),
        ("with a curved handle", "with a glossy glaze", "with a thick rim"),
    ),
    "cup": (
        ("cylindrical", "tapered", "rounded"),
        ("ceramic", "porcelain", "plastic"),
        ("with a smooth rim", "with a matte finish", "without a handle"),
    ),
    "teacup": (
        ("shallow", "rounded", "bell-shaped"),
        ("porcelain", "bone china", "ceramic"),
        ("with a delicate handle", "with a flared rim", "with a thin wall"),
    ),
    "glass": (
        ("cylindrical", "tall", "tumbler-shaped"),
        ("clear glass", "ribbed glass", "frosted glass"),
        ("with a heavy base", "with straight sides", "with a thin rim"),
    ),
    "wine_glass": (
        ("stemmed", "tulip-shaped", "round-bowled"),
        ("clear glass", "crystal"),
        ("with a long slender stem", "with a wide foot", "with a tapered bowl"),
    ),
    "bowl": (
        ("round", "deep", "shallow", "wide"),
        ("ceramic", "wooden", "porcelain", "glass"),
        ("with a curved wall", "with a low foot ring", "with a smooth glaze"),
    ),
    "plate": (
        ("round", "flat", "rimmed"),
        ("ceramic", "porcelain", "stoneware"),
        ("with a raised edge", "with a wide rim", "with a plain finish"),
    ),
    "tray": (
        ("rectangular", "oval", "shallow"),
        ("wooden", "metal", "woven", "lacquered"),
        ("with raised edges", "with side handles", "with a flat base"),
    ),
    "basket": (
        ("rectangular", "round", "deep"),
        ("woven", "wicker", "rattan", "seagrass"),
        ("with a carry handle", "with a tight weave", "with reinforced edges"),
    ),
    "pen_holder": (
        ("cylindrical", "square", "hexagonal"),
        ("metal mesh", "wooden", "ceramic", "plastic"),
        ("with an open top", "with a weighted base", "with a single compartment"),
    ),
    "toothbrush_cup": (
        ("cylindrical", "tapered", "round"),
        ("ceramic", "glass", "bamboo", "plastic"),
        ("with an open top", "with a smooth finish", "with a thick base"),
    ),
    "soap_dish": (
        ("oval", "rectangular", "shallow"),
        ("ceramic", "bamboo", "stone", "plastic"),
        ("with drainage ridges", "with a raised lip", "with a flat base"),
    ),
    "book": (
        ("rectangular", "thick", "thin"),
        ("hardcover", "paperback", "cloth-bound"),
        ("with a printed spine", "with worn edges", "with a plain cover"),
    ),
    "notebook": (
        ("rectangular", "slim", "compact"),
        ("spiral-bound", "leather-bound", "paper"),
        ("with lined pages", "with an elastic band", "with a soft cover"),
    ),
    "laptop": (
        ("thin", "rectangular", "slim"),
        ("aluminium", "plastic"),
        ("closed lid", "with a brushed finish", "with rounded corners"),
    ),
    "monitor": (
        ("flat", "widescreen", "slim-bezel"),
        ("plastic", "metal"),
        ("on a round stand", "on a rectangular foot", "with thin bezels"),
    ),
    "keyboard": (
        ("low-profile", "full-size", "compact"),
        ("plastic", "aluminium"),
        ("with chiclet keys", "with mechanical keys", "with a wrist rest edge"),
    ),
    "mouse": (
        ("ergonomic", "rounded", "compact"),
        ("plastic", "rubberised"),
        ("with a scroll wheel", "with two buttons", "wireless"),
    ),
    "lamp": (
        ("adjustable", "slender", "domed"),
        ("metal", "ceramic", "brass"),
        ("with a fabric shade", "with an arm that bends", "with a round base"),
    ),
    "plant": (
        ("small", "leafy", "bushy", "trailing"),
        ("potted", "ceramic-potted", "terracotta-potted"),
        ("with green foliage", "with broad leaves", "with thin stems"),
    ),
    "vase": (
        ("tall", "slender", "round-bellied"),
        ("glass", "ceramic", "porcelain"),
        ("with a narrow neck", "with a flared lip", "with a smooth glaze"),
    ),
    "candle": (
        ("pillar", "round", "tall", "short"),
        ("wax", "scented wax"),
        ("with a single wick", "in a glass holder", "with a smooth surface"),
    ),
    "bottle": (
        ("tall", "cylindrical", "slim"),
        ("glass", "plastic", "stainless steel"),
        ("with a screw cap", "with a narrow neck", "with a printed label"),
    ),
    "lotion_bottle": (
        ("tall", "oval", "cylindrical"),
        ("plastic", "frosted plastic"),
        ("with a pump top", "with a flip cap", "with a printed label"),
    ),
    "perfume": (
        ("faceted", "rectangular", "round"),
        ("glass", "crystal"),
        ("with a spray nozzle", "with a heavy cap", "with a square base"),
    ),
    "jar": (
        ("round", "squat", "tall"),
        ("glass", "ceramic", "plastic"),
        ("with a screw lid", "with a cork stopper", "with a wide mouth"),
    ),
}


_GENERIC_SHAPES = {
    "small": ("small", "compact", "handheld"),
    "medium": ("medium-sized", "sturdy", "simple"),
    "large": ("large", "bulky", "wide"),
}
_GENERIC_FEATURES = (
    "with a smooth surface",
    "with rounded edges",
    "with a matte finish",
    "with a plain design",
    "with a clean outline",
    "with a subtle texture",
)


def describe(category: str, size_cm, rng: np.random.Generator) -> str:
    """A one-sentence description of an object of ``category`` with extents ``size_cm`` (w, d, h)."""
    name = category.replace("_", " ")
    shapes, materials, features = CAPTION_BANK.get(category, ((), (), ()))
    if shapes:
        shape = shapes[int(rng.integers(len(shapes)))]
        material = materials[int(rng.integers(len(materials)))]
        feature = features[int(rng.integers(len(features)))]
        text = f"{shape} {material} {name} {feature}"
    else:
        extent = max(float(v) for v in size_cm)
        cls = "small" if extent < 12 else "medium" if extent < 35 else "large"
        pool = _GENERIC_SHAPES[cls]
        text = f"{pool[int(rng.integers(len(pool)))]} {name} {_GENERIC_FEATURES[int(rng.integers(6))]}"
    return text[0].upper() + text[1:] + "."
