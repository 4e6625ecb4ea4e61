"""Scene-type definitions for the synthetic MesaTask-style benchmark (centimetres).

One :class:`SceneTypeSpec` per table type: the item-placement-zone size range, the category
vocabulary with relative frequencies (sizes come from :data:`physcene.assets.CATEGORY_PRIORS`),
the typical hierarchies (:class:`GroupSpec`: a base object with children ``on`` or ``in`` it),
anchors that most scenes of the type have, arrangement styles and restricted zones (sinks).

Six in-distribution types (the paper's Table 5) and four out-of-distribution types (the paper's
OOD benchmark). Names are the paper's, lower case, as in :mod:`physcene.assets.categories`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from physcene.assets.categories import CATEGORY_PRIORS
from physcene.assets.categories import IID_SCENE_TYPES as _ASSET_IID
from physcene.assets.categories import OOD_SCENE_TYPES as _ASSET_OOD

__all__ = [
    "ARRANGEMENT_STYLES",
    "GroupSpec",
    "OOD_SCENE_TYPES",
    "SCENE_TYPES",
    "SCENE_TYPE_SPECS",
    "SceneTypeSpec",
    "STANDING",
    "spec_for",
]

ARRANGEMENT_STYLES = ("clusters", "back_row", "place_settings", "scatter")

# Categories that stand upright when they go ``in`` a container (pen in a holder, toothbrush in
# a cup): their prior is given lying on the table, so their longest axis becomes the height.
STANDING = frozenset(
    {"pen", "pencil", "toothbrush", "spoon", "fork", "knife", "chopsticks", "comb", "lipstick", "toothpaste"}
)


@dataclass(frozen=True)
class GroupSpec:
    """A typical hierarchy: ``base`` with ``children`` stacked on it or put in it.

    ``children`` holds (relation, categories to choose from, min count, max count); for
    ``relation == "on"`` the children form one stack (each on the previous one) when ``stack``
    is true, else they stand side by side on the base's top.
    """

    name: str
    """Readable name used by the instruction grammar, e.g. ``"stacked books"``."""
    base: tuple[str, ...]
    """Categories the base may be (chosen by the frequencies of the type's vocabulary)."""
    children: tuple[tuple[str, tuple[str, ...], int, int], ...]
    """(relation ``"on"``/``"in"``, categories, min count, max count) per child slot."""
    weight: float = 1.0
    """Relative frequency among the type's groups."""
    stack: bool = False
    """``on`` children pile up (book on book on book) instead of standing side by side."""
    phrase: str = ""
    """How an instruction may mention the group ("pens in a holder")."""


@dataclass(frozen=True)
class SceneTypeSpec:
    """Everything the generator needs to know about one table type (cm)."""

    name: str
    """Scene type name, e.g. ``"office table"``."""
    zone_width_cm: tuple[float, float]
    """Range of the item placement zone's width (x)."""
    zone_depth_cm: tuple[float, float]
    """Range of the zone's depth (y)."""
    vocabulary: dict[str, float]
    """Table-level categories and their relative frequencies."""
    groups: tuple[GroupSpec, ...]
    """Typical hierarchies."""
    group_rate: float
    """Probability that the next unit placed is a group rather than a single object."""
    anchors: tuple[tuple[str, float], ...] = ()
    """(category or ``group:<name>``, probability) placed first: the type's focal objects."""
    styles: dict[str, float] = field(default_factory=lambda: {"clusters": 1.0, "scatter": 1.0})
    """Arrangement styles and their frequencies (see ``ARRANGEMENT_STYLES``)."""
    sink: tuple[tuple[float, float], tuple[float, float]] | None = None
    """Sink (restricted zone) size range ((w lo, w hi), (d lo, d hi)), or None."""
    level_weights: tuple[float, ...] | None = None
    """OOD only: frequency of levels 1..5 (IID types follow Table 5)."""

    def __post_init__(self):
        unknown = [c for c in self.vocabulary if c not in CATEGORY_PRIORS]
        for g in self.groups:
            unknown += [c for c in g.base if c not in CATEGORY_PRIORS]
            for rel, cats, lo, hi in g.children:
                if rel not in ("on", "in") or not (0 <= lo <= hi):
                    raise ValueError(f"{self.name}: bad child slot {rel, cats, lo, hi} in group {g.name!r}")
                unknown += [c for c in cats if c not in CATEGORY_PRIORS]
        if unknown:
            raise ValueError(f"{self.name}: categories without a size prior: {sorted(set(unknown))}")
        bad = set(self.styles) - set(ARRANGEMENT_STYLES)
        if bad:
            raise ValueError(f"{self.name}: unknown arrangement styles {sorted(bad)}")

    def group(self, name: str) -> GroupSpec:
        for g in self.groups:
            if g.name == name:
                return g
        raise KeyError(f"{self.name}: no group {name!r}")


def _g(name, base, children, weight=1.0, stack=False, phrase=""):
    return GroupSpec(
        name,
        tuple(base),
        tuple((r, tuple(c), lo, hi) for r, c, lo, hi in children),
        weight,
        stack,
        phrase or name,
    )


# Hierarchies shared by several types -------------------------------------------------------------
_BOOK_STACK = _g("stacked books", ["book"], [("on", ["book"], 1, 3)], 1.0, True, "a stack of books")
_CANDLE_BOOK = _g(
    "candle on a book", ["book"], [("on", ["candle"], 1, 1)], 0.6, phrase="a candle resting on a book"
)
_PLANT_BOOKS = _g(
    "plant on books",
    ["book"],
    [("on", ["book"], 0, 1), ("on", ["plant"], 1, 1)],
    0.5,
    True,
    "a plant raised on books",
)
_PEN_HOLDER = _g(
    "pens in a holder",
    ["pen_holder"],
    [("in", ["pen", "pencil"], 1, 3)],
    1.2,
    phrase="pens gathered in a holder",
)
_CUP_SAUCER = _g(
    "cup on a saucer", ["saucer"], [("on", ["teacup", "cup"], 1, 1)], 1.0, phrase="a cup on its saucer"
)
_MUG_COASTER = _g(
    "mug on a coaster",
    ["coaster"],
    [("on", ["mug", "glass", "cup"], 1, 1)],
    0.8,
    phrase="a drink on a coaster",
)
_FRUIT_BOWL = _g(
    "fruit in a bowl", ["bowl"], [("in", ["apple", "orange", "lemon"], 1, 3)], 1.0, phrase="a bowl of fruit"
)
_FRUIT_BASKET = _g(
    "fruit basket",
    ["basket"],
    [("in", ["apple", "orange", "lemon", "banana"], 1, 4)],
    0.6,
    phrase="a basket of fruit",
)
_TOOTHBRUSH = _g(
    "toothbrush in a cup",
    ["toothbrush_cup"],
    [("in", ["toothbrush", "toothpaste"], 1, 2)],
    1.2,
    phrase="toothbrushes in a cup",
)
_SOAP_DISH = _g(
    "soap on a dish", ["soap_dish"], [("in", ["soap", "sponge"], 1, 1)], 1.0, phrase="soap on its dish"
)
_LAPTOP_STAND = _g(
    "laptop on a stand",
    ["monitor_stand"],
    [("on", ["laptop"], 1, 1)],
    0.8,
    phrase="a laptop raised on a stand",
)
_MONITOR_STAND = _g(
    "monitor on a stand", ["monitor_stand"], [("on", ["monitor"], 1, 1)], 0.5, phrase="a monitor on a riser"
)
_NOTEBOOK_PEN = _g(
    "pen on a notebook", ["notebook"], [("on", ["pen", "pencil"], 1, 1)], 0.8, phrase="a notebook with a pen"
)
_MAGAZINES = _g("magazine pile", ["magazine"], [("on", ["magazine"], 1, 2)], 0.7, True, "a pile of magazines")
_TRAY_DRINKS = _g(
    "tea tray", ["tray"], [("in", ["teacup", "saucer", "spoon", "lemon"], 1, 3)], 0.6, phrase="a tea tray"
)
_VANITY_TRAY = _g(
    "vanity tray",
    ["tray"],
    [("in", ["lipstick", "comb", "glasses", "perfume"], 1, 3)],
    0.8,
    phrase="a tray of cosmetics",
)
_JEWELRY = _g(
    "jewelry box with glasses",
    ["jewelry_box"],
    [("on", ["glasses"], 1, 1)],
    0.4,
    phrase="glasses laid on the jewelry box",
)
_BOARD = _g(
    "cutting board",
    ["cutting_board"],
    [("on", ["knife", "lemon", "banana", "apple"], 1, 2)],
    1.2,
    phrase="a cutting board ready for prep",
)
_PLATE_CUTLERY = _g(
    "plate with cutlery",
    ["plate"],
    [("in", ["fork", "spoon", "knife"], 1, 2)],
    0.8,
    phrase="plates with cutlery",
)
_PLATE_FRUIT = _g(
    "fruit on a plate", ["plate"], [("in", ["banana", "lemon"], 1, 2)], 0.5, phrase="fruit on a plate"
)
_PLACE_SETTING = _g(
    "place setting",
    ["placemat"],
    [
        ("on", ["plate"], 1, 1),
        ("on", ["fork", "knife", "spoon"], 1, 2),
        ("on", ["glass", "wine_glass", "napkin"], 0, 1),
    ],
    1.5,
    phrase="place settings",
)
_NAPKIN_CUTLERY = _g(
    "cutlery on a napkin",
    ["napkin"],
    [("on", ["fork", "knife", "spoon", "chopsticks"], 1, 2)],
    0.6,
    phrase="cutlery laid on napkins",
)
_TOWEL_SOAP = _g("folded towel", ["towel"], [("on", ["soap", "towel"], 1, 1)], 0.6, True, "a folded towel")
_CONSOLE = _g(
    "controller on the console",
    ["game_console"],
    [("on", ["game_controller", "remote"], 1, 1)],
    1.0,
    phrase="the game console and its controller",
)
_OPEN_BOX = _g(
    "box of supplies",
    ["open_box"],
    [("in", ["pen", "scissors", "sticky_notes", "calculator"], 1, 3)],
    0.6,
    phrase="a box of supplies",
)
_PHONE_BOOK = _g(
    "phone on a book",
    ["book"],
    [("on", ["phone", "glasses", "keys"], 1, 1)],
    0.7,
    phrase="a book with the phone on top",
)
_TOILETRY_BASKET = _g(
    "toiletry basket",
    ["basket"],
    [("in", ["lotion_bottle", "soap", "comb", "towel"], 1, 3)],
    0.5,
    phrase="a basket of toiletries",
)
_POT = _g("pot with a spoon", ["pot"], [("in", ["spoon"], 1, 1)], 0.4, phrase="a pot and ladle")


def _spec(name, zw, zd, vocab, groups, group_rate, anchors=(), styles=None, sink=None, level_weights=None):
    return SceneTypeSpec(
        name=name,
        zone_width_cm=zw,
        zone_depth_cm=zd,
        vocabulary=dict(vocab),
        groups=tuple(groups),
        group_rate=group_rate,
        anchors=tuple(anchors),
        styles=dict(styles or {"clusters": 1.0, "scatter": 1.0}),
        sink=sink,
        level_weights=level_weights,
    )


SCENE_TYPE_SPECS: dict[str, SceneTypeSpec] = {
    s.name: s
    for s in (
        _spec(
            "coffee table",
            (80, 130),
            (45, 70),
            {
                "mug": 1.0,
                "teacup": 0.6,
                "glass": 0.6,
                "bowl": 0.5,
                "vase": 0.6,
                "book": 1.0,
                "magazine": 0.9,
                "remote": 0.9,
                "candle": 0.8,
                "plant": 0.6,
                "phone": 0.7,
                "tissue_box": 0.5,
                "teapot": 0.5,
                "apple": 0.3,
                "orange": 0.3,
                "game_controller": 0.3,
                "laptop": 0.2,
                "tablet": 0.4,
                "napkin": 0.3,
                "coaster": 0.5,
                "glasses": 0.3,
                "bottle": 0.3,
                "basket": 0.2,
            },
            [
                _BOOK_STACK,
                _CANDLE_BOOK,
                _PLANT_BOOKS,
                _CUP_SAUCER,
                _MUG_COASTER,
                _FRUIT_BOWL,
                _MAGAZINES,
                _TRAY_DRINKS,
                _PHONE_BOOK,
            ],
            0.4,
            anchors=(("group:tea tray", 0.25), ("vase", 0.3)),
            styles={"clusters": 2.0, "scatter": 1.0, "back_row": 0.5},
        ),
        _spec(
            "office table",
            (100, 160),
            (55, 80),
            {
                "keyboard": 1.0,
                "mouse": 1.0,
                "monitor": 0.8,
                "laptop": 0.7,
                "lamp": 0.7,
                "mug": 0.9,
                "book": 0.8,
                "notebook": 0.9,
                "pen": 0.8,
                "pencil": 0.4,
                "sticky_notes": 0.6,
                "stapler": 0.5,
                "scissors": 0.4,
                "calculator": 0.5,
                "phone": 0.7,
                "headphones": 0.5,
                "plant": 0.5,
                "bottle": 0.5,
                "glasses": 0.3,
                "picture_frame": 0.3,
                "clock": 0.3,
                "speaker": 0.3,
                "tablet": 0.3,
                "router": 0.2,
                "coffee_maker": 0.1,
            },
            [
                _PEN_HOLDER,
                _BOOK_STACK,
                _LAPTOP_STAND,
                _MONITOR_STAND,
                _NOTEBOOK_PEN,
                _MUG_COASTER,
                _PLANT_BOOKS,
                _OPEN_BOX,
                _CUP_SAUCER,
                _PHONE_BOOK,
            ],
            0.35,
            anchors=(("monitor", 0.45), ("keyboard", 0.55), ("group:pens in a holder", 0.4)),
            styles={"back_row": 2.0, "clusters": 1.0, "scatter": 0.5},
        ),
        _spec(
            "dressing table",
            (80, 120),
            (40, 55),
            {
                "mirror": 0.9,
                "perfume": 1.0,
                "lipstick": 1.0,
                "lotion_bottle": 0.9,
                "comb": 0.7,
                "hairbrush": 0.7,
                "jar": 0.6,
                "tissue_box": 0.5,
                "candle": 0.4,
                "vase": 0.3,
                "picture_frame": 0.4,
                "lamp": 0.3,
                "glasses": 0.4,
                "jewelry_box": 0.6,
                "phone": 0.4,
                "wallet": 0.3,
                "basket": 0.2,
            },
            [_VANITY_TRAY, _JEWELRY, _CANDLE_BOOK, _TOWEL_SOAP],
            0.25,
            anchors=(("mirror", 0.6), ("group:vanity tray", 0.3)),
            styles={"back_row": 2.0, "clusters": 1.5, "scatter": 0.5},
        ),
        _spec(
            "dining table",
            (120, 180),
            (75, 100),
            {
                "plate": 0.9,
                "bowl": 0.8,
                "glass": 0.9,
                "wine_glass": 0.6,
                "fork": 0.7,
                "knife": 0.6,
                "spoon": 0.6,
                "chopsticks": 0.3,
                "napkin": 0.5,
                "vase": 0.6,
                "candle": 0.6,
                "bottle": 0.6,
                "salt_shaker": 0.7,
                "teapot": 0.4,
                "jar": 0.3,
                "apple": 0.3,
                "orange": 0.3,
                "basket": 0.3,
                "tray": 0.2,
            },
            [
                _PLACE_SETTING,
                _FRUIT_BOWL,
                _PLATE_CUTLERY,
                _NAPKIN_CUTLERY,
                _CUP_SAUCER,
                _FRUIT_BASKET,
                _PLATE_FRUIT,
            ],
            0.45,
            anchors=(("vase", 0.35), ("group:fruit in a bowl", 0.3)),
            styles={"place_settings": 2.5, "clusters": 1.0, "scatter": 0.5},
        ),
        _spec(
            "kitchen counter",
            (120, 200),
            (55, 65),
            {
                "kettle": 0.7,
                "toaster": 0.6,
                "coffee_maker": 0.5,
                "cutting_board": 0.6,
                "knife": 0.6,
                "pot": 0.4,
                "bowl": 0.7,
                "plate": 0.6,
                "mug": 0.7,
                "glass": 0.5,
                "jar": 0.9,
                "bottle": 0.8,
                "salt_shaker": 0.6,
                "sponge": 0.5,
                "banana": 0.5,
                "apple": 0.4,
                "lemon": 0.4,
                "orange": 0.3,
                "teapot": 0.3,
                "plant": 0.3,
                "towel": 0.4,
                "spoon": 0.4,
                "basket": 0.3,
            },
            [_BOARD, _FRUIT_BOWL, _FRUIT_BASKET, _SOAP_DISH, _POT, _PLATE_FRUIT, _PLATE_CUTLERY],
            0.35,
            anchors=(("group:cutting board", 0.45), ("kettle", 0.3)),
            styles={"back_row": 2.0, "clusters": 1.5, "scatter": 0.5},
            sink=((40, 60), (30, 42)),
        ),
        _spec(
            "bathroom vanity",
            (70, 140),
            (45, 60),
            {
                "toothpaste": 0.8,
                "lotion_bottle": 1.0,
                "soap": 0.6,
                "towel": 0.7,
                "perfume": 0.6,
                "jar": 0.6,
                "comb": 0.6,
                "hairbrush": 0.5,
                "tissue_box": 0.5,
                "candle": 0.5,
                "mirror": 0.3,
                "cup": 0.4,
                "basket": 0.3,
                "plant": 0.2,
                "phone": 0.2,
            },
            [_TOOTHBRUSH, _SOAP_DISH, _TOWEL_SOAP, _TOILETRY_BASKET],
            0.35,
            anchors=(("group:toothbrush in a cup", 0.55), ("group:soap on a dish", 0.4)),
            styles={"back_row": 2.0, "clusters": 1.5, "scatter": 0.5},
            sink=((32, 50), (28, 38)),
        ),
        # Out-of-distribution types (never in train/test) -------------------------------------------
        _spec(
            "cashier counter",
            (100, 160),
            (50, 70),
            {
                "cash_register": 0.6,
                "card_reader": 0.9,
                "receipt_printer": 0.7,
                "calculator": 0.6,
                "phone": 0.6,
                "sticky_notes": 0.6,
                "pen": 0.7,
                "wallet": 0.4,
                "plant": 0.4,
                "monitor": 0.4,
                "keyboard": 0.4,
                "mouse": 0.3,
                "scissors": 0.4,
                "stapler": 0.5,
                "mug": 0.5,
                "bottle": 0.4,
                "notebook": 0.5,
            },
            [_PEN_HOLDER, _OPEN_BOX, _NOTEBOOK_PEN, _MUG_COASTER],
            0.3,
            anchors=(("cash_register", 0.7), ("card_reader", 0.5)),
            styles={"back_row": 2.0, "clusters": 1.0},
            level_weights=(0.08, 0.42, 0.35, 0.12, 0.03),
        ),
        _spec(
            "nightstand",
            (40, 60),
            (35, 50),
            {
                "lamp": 1.0,
                "clock": 0.8,
                "phone": 0.8,
                "glasses": 0.6,
                "book": 0.8,
                "glass": 0.6,
                "candle": 0.4,
                "picture_frame": 0.5,
                "tissue_box": 0.4,
                "lotion_bottle": 0.3,
                "keys": 0.4,
                "wallet": 0.3,
                "remote": 0.3,
                "notebook": 0.3,
                "pen": 0.3,
            },
            [_BOOK_STACK, _PHONE_BOOK, _MUG_COASTER, _CANDLE_BOOK],
            0.35,
            anchors=(("lamp", 0.7),),
            styles={"back_row": 1.5, "clusters": 1.0},
            level_weights=(0.3, 0.5, 0.2, 0.0, 0.0),
        ),
        _spec(
            "side table",
            (45, 70),
            (45, 70),
            {
                "lamp": 0.8,
                "plant": 0.7,
                "book": 0.8,
                "magazine": 0.6,
                "vase": 0.6,
                "candle": 0.6,
                "remote": 0.6,
                "mug": 0.6,
                "picture_frame": 0.5,
                "clock": 0.3,
                "glasses": 0.4,
                "phone": 0.5,
                "tablet": 0.3,
                "speaker": 0.2,
                "tissue_box": 0.3,
                "keys": 0.3,
            },
            [_BOOK_STACK, _CANDLE_BOOK, _PLANT_BOOKS, _MUG_COASTER, _MAGAZINES, _CUP_SAUCER],
            0.4,
            anchors=(("lamp", 0.5),),
            styles={"clusters": 1.5, "scatter": 1.0},
            level_weights=(0.25, 0.5, 0.25, 0.0, 0.0),
        ),
        _spec(
            "tv stand",
            (120, 180),
            (40, 55),
            {
                "television": 0.2,
                "speaker": 0.9,
                "remote": 0.8,
                "router": 0.5,
                "plant": 0.6,
                "picture_frame": 0.6,
                "clock": 0.4,
                "book": 0.6,
                "open_box": 0.3,
                "candle": 0.4,
                "vase": 0.4,
                "game_controller": 0.5,
                "headphones": 0.3,
            },
            [_CONSOLE, _BOOK_STACK, _PLANT_BOOKS, _CANDLE_BOOK],
            0.35,
            anchors=(("television", 0.85),),
            styles={"back_row": 2.0, "clusters": 1.0},
            level_weights=(0.12, 0.45, 0.33, 0.08, 0.02),
        ),
    )
}

SCENE_TYPES: tuple[str, ...] = tuple(_ASSET_IID)
"""The six in-distribution scene types, in Table 5 order."""
OOD_SCENE_TYPES: tuple[str, ...] = tuple(_ASSET_OOD)
"""The four out-of-distribution scene types."""


def spec_for(scene_type: str) -> SceneTypeSpec:
    """The spec of ``scene_type`` (case-insensitive, ``_`` read as a space)."""
    key = scene_type.strip().lower().replace("_", " ")
    try:
        return SCENE_TYPE_SPECS[key]
    except KeyError:
        raise ValueError(f"unknown scene type {scene_type!r}; known: {', '.join(SCENE_TYPE_SPECS)}") from None
