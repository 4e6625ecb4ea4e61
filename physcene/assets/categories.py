"""Tabletop categories and their size priors, shared by the data generator, the judge and the engine.

Every category name is lower_snake_case and singular (``mug``, ``book``, ``pen_holder``). A prior
gives the object's typical box [w, d, h] in centimetres as it usually stands on a table (w along
the object's own x, d along y, h up), a spread (one standard deviation per axis, cm), the scene
types it belongs to and its role in the hierarchy:

- ``container``: has a real cavity that other objects go ``in`` (mug, bowl, basket, pen holder);
- ``support``: a flat top that other objects go ``on`` (book, laptop, cutting board, saucer);
- ``object``: anything else.

Scene types use the paper's names in lower case: six in-distribution (``coffee table``,
``office table``, ``dressing table``, ``dining table``, ``kitchen counter``, ``bathroom vanity``)
and four out-of-distribution (``cashier counter``, ``nightstand``, ``side table``, ``tv stand``).
Sizes are measured or catalogue figures for ordinary household items.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

import numpy as np

__all__ = ["CATEGORY_ALIASES", "CATEGORY_PRIORS", "IID_SCENE_TYPES", "OOD_SCENE_TYPES", "ROLES",
           "SIZE_SIGMA_FLOOR", "SizePrior", "canonical_category", "categories_for_scene_type"]

ROLES = ("container", "support", "object")

SIZE_SIGMA_FLOOR = 0.15
"""A prior's spread in log space is never taken below this (std / mean): ±15 % is ordinary variety."""

COFFEE, OFFICE, DRESSING, DINING = "coffee table", "office table", "dressing table", "dining table"
KITCHEN, BATHROOM = "kitchen counter", "bathroom vanity"
CASHIER, NIGHTSTAND, SIDE, TV = "cashier counter", "nightstand", "side table", "tv stand"
IID_SCENE_TYPES = (COFFEE, OFFICE, DRESSING, DINING, KITCHEN, BATHROOM)
OOD_SCENE_TYPES = (CASHIER, NIGHTSTAND, SIDE, TV)


@dataclass(frozen=True)
class SizePrior:
    """Typical size of one category (cm) and where it appears."""

    mean_cm: tuple[float, float, float]
    """Mean box [w, d, h] in cm, object frame, as the object usually stands."""
    std_cm: tuple[float, float, float]
    """One standard deviation per axis, cm."""
    scene_types: tuple[str, ...]
    """Scene types (IID and OOD names above) where the category is common."""
    role: str
    """``container``, ``support`` or ``object``."""

    def __post_init__(self):
        if self.role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {self.role!r}")
        if len(self.mean_cm) != 3 or len(self.std_cm) != 3 or min(self.mean_cm) <= 0:
            raise ValueError(f"bad size prior {self.mean_cm} ± {self.std_cm}")
        unknown = set(self.scene_types) - set(IID_SCENE_TYPES) - set(OOD_SCENE_TYPES)
        if unknown:
            raise ValueError(f"unknown scene types {sorted(unknown)}")

    def aligned(self, size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``size`` (w, d, h cm) and the prior, dimension by dimension in ascending order (an object
        may lie or stand either way: a book on its side, a pen upright in its holder): the sorted
        size, the matching prior means and their log-space spreads max(std / mean, SIZE_SIGMA_FLOOR)."""
        order = np.argsort(self.mean_cm)
        mean = np.asarray(self.mean_cm, dtype=np.float64)[order]
        sigma = np.maximum(np.asarray(self.std_cm, dtype=np.float64)[order] / mean, SIZE_SIGMA_FLOOR)
        return np.sort(np.asarray(size, dtype=np.float64)), mean, sigma

    def band_cm(self, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """The sizes within ``tolerance`` spreads of the mean in log space, per ascending dimension:
        (low, high) = mean · exp(∓tolerance · sigma), cm (the rule judge's OSR does not penalise them).
        Computed once per prior and tolerance (the reward's size guard asks per object); read-only."""
        return _band_cm(self, float(tolerance))

    def outside_band_cm(self, size, tolerance: float) -> float:
        """How far (cm, summed over the dimensions) ``size`` lies outside :meth:`band_cm`; 0 inside."""
        low, high = self.band_cm(tolerance)
        size = np.sort(np.asarray(size, dtype=np.float64))  # ascending, as the band's dimensions
        return float((np.maximum(low - size, 0.0) + np.maximum(size - high, 0.0)).sum())

    def low_ratio(self, size, tolerance: float) -> float:
        """The smallest ratio of ``size`` to the low edge of :meth:`band_cm`, dimension by dimension in
        ascending order: below 1, some dimension is smaller than the band allows (a flattened box: ~0)."""
        low, _ = self.band_cm(tolerance)
        return float((np.sort(np.asarray(size, dtype=np.float64)) / low).min())


@functools.lru_cache(maxsize=1024)
def _band_cm(prior: SizePrior, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    _, mean, sigma = prior.aligned(prior.mean_cm)
    band = mean * np.exp(-tolerance * sigma), mean * np.exp(tolerance * sigma)
    for edge in band:
        edge.setflags(write=False)
    return band


def canonical_category(category: str) -> str:
    """Lower-snake, alias-resolved category name (``Coffee Mug`` -> ``mug``)."""
    key = re.sub(r"[^a-z0-9]+", "_", category.strip().lower()).strip("_")
    return CATEGORY_ALIASES.get(key, key)


def _p(mean, std, scene_types, role="object") -> SizePrior:
    return SizePrior(tuple(float(v) for v in mean), tuple(float(v) for v in std), tuple(scene_types), role)


_ALL = IID_SCENE_TYPES + OOD_SCENE_TYPES
_DRINK = (COFFEE, OFFICE, DINING, KITCHEN, NIGHTSTAND, SIDE, CASHIER)
_DESK = (OFFICE, CASHIER, NIGHTSTAND, SIDE)
_MEAL = (DINING, KITCHEN, COFFEE)
_WASH = (BATHROOM, DRESSING)
_LIVING = (COFFEE, SIDE, TV, NIGHTSTAND)

CATEGORY_PRIORS: dict[str, SizePrior] = {
    # containers: real cavities (open top, walls, floor)
    "mug": _p((12.0, 8.5, 9.5), (1.5, 1.0, 1.2), _DRINK, "container"),
    "cup": _p((8.0, 8.0, 10.0), (1.0, 1.0, 1.5), _DRINK, "container"),
    "teacup": _p((11.0, 8.5, 6.5), (1.2, 1.0, 0.8), (COFFEE, DINING, SIDE), "container"),
    "glass": _p((7.5, 7.5, 12.0), (1.0, 1.0, 2.0), (DINING, KITCHEN, COFFEE, NIGHTSTAND), "container"),
    "wine_glass": _p((8.5, 8.5, 20.0), (1.0, 1.0, 2.5), (DINING, COFFEE), "container"),
    "bowl": _p((15.0, 15.0, 6.5), (3.0, 3.0, 1.5), _MEAL, "container"),
    "pot": _p((30.0, 22.0, 14.0), (4.0, 3.0, 3.0), (KITCHEN,), "container"),
    "basket": _p((30.0, 22.0, 25.0), (6.0, 4.0, 5.0), (KITCHEN, DINING, COFFEE, BATHROOM, SIDE), "container"),
    "pen_holder": _p((8.0, 8.0, 10.0), (1.5, 1.5, 1.5), (OFFICE, CASHIER), "container"),
    "vase": _p((12.0, 12.0, 25.0), (3.0, 3.0, 6.0), (COFFEE, DINING, SIDE, TV, DRESSING), "container"),
    "plate": _p((25.0, 25.0, 2.5), (3.0, 3.0, 0.5), _MEAL, "container"),
    "tray": _p((40.0, 28.0, 4.0), (6.0, 4.0, 1.0), (COFFEE, DINING, KITCHEN, DRESSING, SIDE), "container"),
    "open_box": _p((25.0, 18.0, 10.0), (6.0, 4.0, 3.0), (OFFICE, CASHIER, TV, KITCHEN), "container"),
    "soap_dish": _p((12.0, 9.0, 2.5), (2.0, 1.5, 0.5), (BATHROOM, KITCHEN), "container"),
    "toothbrush_cup": _p((7.5, 7.5, 10.5), (1.0, 1.0, 1.5), (BATHROOM,), "container"),
    "jewelry_box": _p((18.0, 12.0, 7.0), (3.0, 2.0, 1.5), (DRESSING, NIGHTSTAND), "container"),
    # supports: flat tops other objects go on
    "book": _p((22.0, 16.0, 3.0), (4.0, 3.0, 1.5), (OFFICE, COFFEE, NIGHTSTAND, SIDE, TV), "support"),
    "notebook": _p((21.0, 15.0, 1.5), (2.0, 1.5, 0.5), (OFFICE, CASHIER, NIGHTSTAND), "support"),
    "magazine": _p((28.0, 21.0, 0.6), (2.0, 1.5, 0.3), (COFFEE, SIDE, TV), "support"),
    "laptop": _p((33.0, 23.0, 2.0), (3.0, 2.0, 0.5), (OFFICE, COFFEE), "support"),
    "tablet": _p((24.0, 17.0, 0.8), (2.5, 1.5, 0.2), (OFFICE, COFFEE, NIGHTSTAND, SIDE), "support"),
    "cutting_board": _p((35.0, 25.0, 2.0), (5.0, 4.0, 0.5), (KITCHEN,), "support"),
    "saucer": _p((14.0, 14.0, 1.5), (1.5, 1.5, 0.3), (COFFEE, DINING, OFFICE), "support"),
    "coaster": _p((10.0, 10.0, 0.5), (1.0, 1.0, 0.2), (COFFEE, OFFICE, SIDE, NIGHTSTAND), "support"),
    "placemat": _p((45.0, 30.0, 0.3), (3.0, 3.0, 0.1), (DINING,), "support"),
    "napkin": _p((20.0, 20.0, 0.5), (4.0, 4.0, 0.3), (DINING, COFFEE), "support"),
    "monitor_stand": _p((50.0, 22.0, 10.0), (8.0, 3.0, 2.0), (OFFICE,), "support"),
    "towel": _p((30.0, 20.0, 6.0), (5.0, 4.0, 2.0), (BATHROOM, KITCHEN), "support"),
    "game_console": _p((30.0, 25.0, 6.0), (4.0, 4.0, 2.0), (TV,), "support"),
    # irregular shapes
    "lamp": _p((16.0, 16.0, 40.0), (4.0, 4.0, 8.0), (OFFICE, NIGHTSTAND, SIDE, DRESSING)),
    "headphones": _p((18.0, 8.0, 20.0), (2.0, 2.0, 2.0), (OFFICE, NIGHTSTAND, TV)),
    "plant": _p((15.0, 15.0, 30.0), (5.0, 5.0, 10.0), (OFFICE, COFFEE, SIDE, TV, KITCHEN, CASHIER)),
    "teapot": _p((22.0, 14.0, 15.0), (3.0, 2.0, 2.0), (COFFEE, DINING, KITCHEN)),
    "kettle": _p((22.0, 16.0, 24.0), (3.0, 2.0, 3.0), (KITCHEN,)),
    "monitor": _p((55.0, 20.0, 42.0), (8.0, 3.0, 6.0), (OFFICE, CASHIER)),
    "television": _p((97.0, 22.0, 62.0), (15.0, 4.0, 9.0), (TV,)),
    "banana": _p((19.0, 6.0, 4.0), (2.0, 1.0, 0.5), (KITCHEN, DINING, COFFEE)),
    "glasses": _p((14.5, 5.0, 4.0), (1.0, 1.0, 0.8), (NIGHTSTAND, DRESSING, OFFICE, SIDE)),
    "mirror": _p((25.0, 12.0, 35.0), (5.0, 3.0, 8.0), (DRESSING, BATHROOM)),
    "picture_frame": _p((15.0, 10.0, 20.0), (3.0, 2.0, 4.0), (NIGHTSTAND, SIDE, OFFICE, TV, DRESSING)),
    "clock": _p((15.0, 7.0, 15.0), (3.0, 1.5, 3.0), (NIGHTSTAND, SIDE, OFFICE, TV)),
    "scissors": _p((20.0, 8.0, 1.2), (2.0, 1.0, 0.3), (OFFICE, KITCHEN, CASHIER)),
    "stapler": _p((15.0, 4.0, 6.0), (2.0, 0.8, 1.0), (OFFICE, CASHIER)),
    # everyday objects
    "pen": _p((14.0, 1.2, 1.2), (1.0, 0.2, 0.2), (OFFICE, CASHIER, NIGHTSTAND)),
    "pencil": _p((17.5, 0.8, 0.8), (1.5, 0.1, 0.1), (OFFICE,)),
    "toothbrush": _p((19.0, 2.0, 2.5), (1.0, 0.4, 0.5), (BATHROOM,)),
    "toothpaste": _p((19.0, 4.5, 3.5), (2.0, 0.8, 0.8), (BATHROOM,)),
    "soap": _p((9.0, 6.0, 3.0), (1.0, 0.8, 0.5), (BATHROOM, KITCHEN)),
    "comb": _p((18.0, 5.0, 1.0), (2.0, 1.0, 0.3), (DRESSING, BATHROOM)),
    "hairbrush": _p((23.0, 7.0, 5.0), (2.0, 1.0, 1.0), (DRESSING, BATHROOM)),
    "perfume": _p((7.0, 4.0, 10.0), (1.5, 1.0, 2.0), (DRESSING, BATHROOM)),
    "lipstick": _p((2.0, 2.0, 8.0), (0.3, 0.3, 1.0), (DRESSING,)),
    "apple": _p((8.0, 8.0, 7.5), (1.0, 1.0, 1.0), (KITCHEN, DINING, COFFEE, OFFICE)),
    "orange": _p((7.5, 7.5, 7.0), (1.0, 1.0, 1.0), (KITCHEN, DINING, COFFEE)),
    "lemon": _p((8.0, 6.0, 6.0), (1.0, 0.8, 0.8), (KITCHEN, DINING)),
    "candle": _p((7.0, 7.0, 10.0), (2.0, 2.0, 4.0), (DINING, COFFEE, BATHROOM, SIDE, NIGHTSTAND)),
    "keyboard": _p((44.0, 14.0, 3.0), (4.0, 2.0, 0.8), (OFFICE, CASHIER)),
    "mouse": _p((6.5, 11.0, 4.0), (0.8, 1.0, 0.6), (OFFICE, CASHIER)),
    "phone": _p((7.5, 15.5, 0.9), (0.5, 1.0, 0.2), _ALL),
    "remote": _p((5.0, 19.0, 2.5), (0.8, 2.0, 0.5), (COFFEE, TV, NIGHTSTAND, SIDE)),
    "game_controller": _p((16.0, 10.0, 6.0), (1.5, 1.0, 1.0), (TV, COFFEE)),
    "speaker": _p((10.0, 10.0, 18.0), (3.0, 3.0, 5.0), (TV, OFFICE, SIDE, NIGHTSTAND)),
    "calculator": _p((9.0, 16.0, 1.5), (1.0, 2.0, 0.5), (OFFICE, CASHIER)),
    "sticky_notes": _p((7.6, 7.6, 2.0), (0.5, 0.5, 0.8), (OFFICE, CASHIER)),
    "bottle": _p((7.0, 7.0, 24.0), (1.5, 1.5, 5.0), (DINING, KITCHEN, OFFICE, COFFEE, NIGHTSTAND)),
    "lotion_bottle": _p((6.0, 4.5, 18.0), (1.0, 1.0, 3.0), (BATHROOM, DRESSING, NIGHTSTAND)),
    "jar": _p((9.0, 9.0, 12.0), (2.0, 2.0, 3.0), (KITCHEN, DINING, BATHROOM, DRESSING)),
    "salt_shaker": _p((4.0, 4.0, 9.0), (0.8, 0.8, 1.5), (DINING, KITCHEN)),
    "spoon": _p((17.0, 4.0, 2.0), (2.0, 0.8, 0.5), _MEAL),
    "fork": _p((19.0, 2.5, 1.5), (1.5, 0.4, 0.4), _MEAL),
    "knife": _p((22.0, 2.0, 1.0), (2.0, 0.4, 0.3), _MEAL),
    "chopsticks": _p((24.0, 1.5, 0.8), (1.0, 0.3, 0.2), (DINING,)),
    "wallet": _p((11.0, 9.0, 2.0), (1.0, 1.0, 0.5), (NIGHTSTAND, SIDE, CASHIER, DRESSING)),
    "keys": _p((8.0, 4.0, 1.0), (1.5, 1.0, 0.3), (NIGHTSTAND, SIDE, OFFICE)),
    "tissue_box": _p((24.0, 12.0, 9.0), (2.0, 1.0, 2.0), (COFFEE, NIGHTSTAND, BATHROOM, DRESSING, SIDE)),
    "sponge": _p((10.0, 7.0, 3.0), (1.0, 0.8, 0.5), (KITCHEN,)),
    "toaster": _p((28.0, 18.0, 20.0), (3.0, 2.0, 2.0), (KITCHEN,)),
    "coffee_maker": _p((20.0, 25.0, 35.0), (4.0, 4.0, 5.0), (KITCHEN, OFFICE)),
    "cash_register": _p((40.0, 40.0, 25.0), (5.0, 5.0, 5.0), (CASHIER,)),
    "card_reader": _p((8.0, 15.0, 5.0), (1.0, 2.0, 1.5), (CASHIER,)),
    "receipt_printer": _p((15.0, 20.0, 14.0), (2.0, 2.0, 2.0), (CASHIER,)),
    "router": _p((20.0, 14.0, 4.0), (4.0, 3.0, 1.5), (TV, OFFICE)),
}

# Common names that are not the canonical one; retrieval maps them before any fuzzy matching.
CATEGORY_ALIASES: dict[str, str] = {
    "desk_lamp": "lamp", "table_lamp": "lamp", "coffee_mug": "mug", "tea_cup": "teacup",
    "drinking_glass": "glass", "water_glass": "glass", "cellphone": "phone", "smartphone": "phone",
    "mobile_phone": "phone", "cell_phone": "phone", "tv": "television", "remote_control": "remote",
    "eyeglasses": "glasses", "sunglasses": "glasses", "potted_plant": "plant", "flower_pot": "plant",
    "water_bottle": "bottle", "wine_bottle": "bottle", "photo_frame": "picture_frame",
    "alarm_clock": "clock", "computer_mouse": "mouse", "pen_cup": "pen_holder", "dish": "plate",
    "storage_box": "open_box", "tissues": "tissue_box", "soap_bar": "soap",
}


def categories_for_scene_type(scene_type: str) -> list[str]:
    """Categories whose prior lists ``scene_type`` (case-insensitive, ``_`` read as a space)."""
    key = scene_type.strip().lower().replace("_", " ")
    return sorted(c for c, p in CATEGORY_PRIORS.items() if key in p.scene_types)
