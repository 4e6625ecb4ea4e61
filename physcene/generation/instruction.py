"""Reading a text instruction: the scene type, the objects it names, their counts and stated relations.

``read_instruction("a dining table set for two, with plates, glasses, a vase and a bowl of fruit")``
finds the scene type (its name or a word that implies it: "desk", "bedside", "sink"), every
category the instruction names through the category vocabulary (:data:`CATEGORY_PRIORS`, its
aliases and the everyday words below: "fruit", "cutlery", "screen"), the count of each ("two
mugs", "a vase", plural without a number: the number of diners of "set for N", else two), and the
in/on relations it states ("a pen in the pen holder", "a mug on the saucer", "a bowl of fruit").
Words it could not place are listed in :attr:`Instruction.unknown` so the user sees what was
ignored. The reading is a pure function of the text; choosing among a word's categories ("fruit":
apple, orange or lemon) is left to the generator's random draw.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from physcene.assets.categories import CATEGORY_ALIASES, CATEGORY_PRIORS
from physcene.data.scene_types import SCENE_TYPE_SPECS

__all__ = ["Instruction", "Mention", "Relation", "read_instruction"]

# Words that name a scene type, longest first when matched; the type names themselves are added.
_SCENE_WORDS = {
    "desk": "office table", "office": "office table", "workstation": "office table",
    "dining": "dining table", "dinner": "dining table", "breakfast": "dining table", "lunch": "dining table",
    "kitchen": "kitchen counter", "countertop": "kitchen counter", "cooking": "kitchen counter",
    "bathroom": "bathroom vanity", "washbasin": "bathroom vanity", "sink": "bathroom vanity",
    "dressing": "dressing table", "makeup": "dressing table", "vanity": "dressing table",
    "coffee table": "coffee table", "living room": "coffee table", "lounge": "coffee table",
    "cashier": "cashier counter", "checkout": "cashier counter", "shop counter": "cashier counter",
    "bedside": "nightstand", "night stand": "nightstand", "bedside table": "nightstand",
    "end table": "side table", "tv": "tv stand", "television stand": "tv stand", "media console": "tv stand",
    "entertainment": "tv stand",
}

# Everyday words for categories beyond CATEGORY_ALIASES; a tuple lets the generator choose.
_WORDS: dict[str, tuple[str, ...]] = {
    "fruit": ("apple", "orange", "lemon"), "fruits": ("apple", "orange", "lemon"),
    "cutlery": ("fork", "knife", "spoon"), "silverware": ("fork", "knife", "spoon"),
    "utensils": ("fork", "knife", "spoon"), "computer": ("laptop",), "notepad": ("notebook",),
    "screen": ("monitor",), "display": ("monitor",), "tumbler": ("glass",), "plant pot": ("plant",),
    "houseplant": ("plant",), "succulent": ("plant",), "flowers": ("vase",), "flower vase": ("vase",),
    "toothbrush holder": ("toothbrush_cup",), "lotion": ("lotion_bottle",), "hand cream": ("lotion_bottle",),
    "cologne": ("perfume",), "brush": ("hairbrush",), "reading glasses": ("glasses",),
    "spectacles": ("glasses",), "controller": ("game_controller",), "gamepad": ("game_controller",),
    "console": ("game_console",), "register": ("cash_register",), "till": ("cash_register",),
    "card terminal": ("card_reader",), "payment terminal": ("card_reader",), "printer": ("receipt_printer",),
    "salt": ("salt_shaker",), "pepper": ("salt_shaker",), "shaker": ("salt_shaker",),
    "chopping board": ("cutting_board",), "coffee machine": ("coffee_maker",), "pan": ("pot",),
    "saucepan": ("pot",), "place mat": ("placemat",), "mat": ("placemat",), "serviette": ("napkin",),
    "jewellery box": ("jewelry_box",), "headset": ("headphones",), "modem": ("router",),
    "photo": ("picture_frame",), "photograph": ("picture_frame",), "frame": ("picture_frame",),
    "tissue": ("tissue_box",), "notes": ("sticky_notes",), "post-it": ("sticky_notes",), "box": ("open_box",),
    "holder": ("pen_holder",), "stand": ("monitor_stand",), "riser": ("monitor_stand",),
}

_NUMBERS = {"a": 1, "an": 1, "one": 1, "single": 1, "two": 2, "pair": 2, "couple": 2, "three": 3,
            "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8, "nine": 9, "ten": 10, "both": 2,
            "few": 3, "several": 3, "some": 2}
_IN_WORDS = {"in", "inside", "into", "within"}
_ON_WORDS = {"on", "onto", "atop", "upon"}
# Words between a preposition and its object that do not break the relation ("in the", "on top of").
_LINKERS = {"the", "a", "an", "its", "their", "his", "her", "my", "our", "top", "of", "small", "big",
            "large", "little", "round", "white", "wooden", "glass", "ceramic", "empty"}
# Words of an instruction that carry no layout content (verbs, moods, articles, connectives).
_FILLER = set("""
a an the and or with without for of to in on at by from into onto inside atop upon near next beside
behind front left right middle center centre corner edge side back close some few several many
set setup up arrange arranged lay laid out place placed put make prepare organize organise tidy neat
clean cozy cosy simple nice small big large little table top tabletop please i me my we our us you
your it its their them there here is are be ready where can grab reach easy within hand nearby use
using just only also each every all both pair couple one two three four five six seven eight nine ten
single people person guests guest diners diner plus set-up morning evening night quiet relaxing
warm modern minimal minimalist everyday daily work working home some lots plenty full stocked area
space spot surface over under around between beneath below above across along against while that this
these those which what so as than then too very really little bit kind sort like want need have has
""".split())


@dataclass(frozen=True)
class Mention:
    """One object the instruction names."""

    word: str
    """The words as written ("plates", "bowl of fruit" names two mentions)."""
    categories: tuple[str, ...]
    """Categories the word may mean (one, or a choice such as fruit: apple, orange, lemon)."""
    count: int | None
    """Stated count, or None when the instruction gives none."""
    plural: bool
    """Written in the plural."""
    start: int
    """Index of its first word in :attr:`Instruction.words`."""
    end: int
    """Index after its last word."""


@dataclass(frozen=True)
class Relation:
    """A stated relation: mention ``child`` goes ``relation`` (in/on) mention ``parent``."""

    child: int
    """Index into :attr:`Instruction.mentions`."""
    parent: int
    """Index into :attr:`Instruction.mentions`."""
    relation: str
    """``in`` or ``on``, as the scene model names it (on a plate or tray reads ``in``: it rests in
    the cavity; in a book or a saucer reads ``on``: it has no cavity)."""


@dataclass(frozen=True)
class Instruction:
    """What :func:`read_instruction` understood."""

    text: str
    """The instruction as given."""
    scene_type: str
    """A name of :data:`SCENE_TYPE_SPECS`."""
    scene_type_stated: bool
    """Whether the text named the scene type (else it was inferred from the objects)."""
    words: tuple[str, ...]
    """The lower-cased words the reading worked on."""
    mentions: tuple[Mention, ...]
    """Objects named, in order."""
    relations: tuple[Relation, ...]
    """Stated in/on relations."""
    diners: int | None = None
    """N of "set for N" / "for N people", else None."""
    unknown: tuple[str, ...] = field(default=())
    """Words that neither name an object, a count, a relation nor the scene type, nor are filler."""
    only: bool = False
    """The instruction asks for the named objects alone ("only", "just"): nothing is filled in."""

    def summary(self) -> dict:
        """A JSON-ready account of the reading (printed by ``physcene generate``)."""
        return {
            "scene_type": self.scene_type, "scene_type_stated": self.scene_type_stated,
            "objects": [{"word": m.word, "categories": list(m.categories), "count": m.count}
                        for m in self.mentions],
            "relations": [{"child": self.mentions[r.child].word, "relation": r.relation,
                           "parent": self.mentions[r.parent].word} for r in self.relations],
            "diners": self.diners, "not_understood": list(self.unknown),
        }


def _singular(word: str) -> list[str]:
    """Candidate singular forms of an English word ("knives" -> knife, "glasses" -> glass)."""
    out = [word]
    if word.endswith("ves"):
        out += [word[:-3] + "fe", word[:-3] + "f"]
    if word.endswith("ies"):
        out.append(word[:-3] + "y")
    if word.endswith("es"):
        out.append(word[:-2])
    if word.endswith("s") and not word.endswith("ss"):
        out.append(word[:-1])
    return out


def _vocabulary() -> dict[str, tuple[str, ...]]:
    """Phrase (space-separated words) -> categories."""
    vocab = {c.replace("_", " "): (c,) for c in CATEGORY_PRIORS}
    vocab.update({a.replace("_", " "): (c,) for a, c in CATEGORY_ALIASES.items()})
    vocab.update(_WORDS)
    vocab["wine glass"] = ("wine_glass",)
    return vocab


_VOCAB = _vocabulary()
_LONGEST = max(len(p.split()) for p in [*_VOCAB, *_SCENE_WORDS, *SCENE_TYPE_SPECS])
_TYPE_WORDS = {w for name in SCENE_TYPE_SPECS for w in name.split()}
_TOKEN = re.compile(r"[a-z0-9]+(?:[-'][a-z0-9]+)*")


def _lookup(words: list[str], scene_type: str | None) -> tuple[tuple[str, ...], bool] | None:
    """Categories of a phrase and whether it is plural; ``glasses`` is drinking glasses unless the
    scene type only knows eyeglasses (dressing table, nightstand, office, side table)."""
    phrase = " ".join(words)
    if phrase == "glasses":
        vocab = SCENE_TYPE_SPECS[scene_type].vocabulary if scene_type else {}
        eyes = "glasses" in vocab and "glass" not in vocab
        return (("glasses",) if eyes else ("glass",)), not eyes
    if phrase in _VOCAB:
        return _VOCAB[phrase], phrase in ("fruits", "cutlery", "silverware", "utensils", "flowers")
    head, last = words[:-1], words[-1]
    for single in _singular(last)[1:]:
        key = " ".join([*head, single])
        if key in _VOCAB:
            return _VOCAB[key], True
    return None


def _find_scene_type(words: list[str]) -> tuple[str | None, set[int]]:
    names = {n: n for n in SCENE_TYPE_SPECS} | _SCENE_WORDS
    for size in range(_LONGEST, 0, -1):
        for i in range(len(words) - size + 1):
            phrase = " ".join(words[i:i + size])
            if phrase in names:
                return names[phrase], set(range(i, i + size))
    return None, set()


def _infer_scene_type(categories: list[tuple[str, ...]]) -> str:
    """The scene type whose vocabulary holds the named categories best (coffee table on a tie)."""
    def fit(name: str) -> float:
        spec = SCENE_TYPE_SPECS[name]
        return sum(max(spec.vocabulary.get(c, 0.0) + (0.5 if name in CATEGORY_PRIORS[c].scene_types else 0.0)
                       for c in cats) for cats in categories)

    return max(SCENE_TYPE_SPECS, key=lambda n: (fit(n), n == "coffee table"))


def _relations(words: list[str], mentions: list[Mention]) -> list[Relation]:
    out = []
    for k in range(len(mentions) - 1):
        a, b = mentions[k], mentions[k + 1]
        between = words[a.end:b.start]
        if not between:
            continue
        head, rest = between[0], between[1:]
        if not all(w in _LINKERS for w in rest):
            continue
        if head in _IN_WORDS | _ON_WORDS:
            child, parent = k, k + 1
        elif head == "of" and not rest and CATEGORY_PRIORS[a.categories[0]].role == "container":
            child, parent = k + 1, k  # "a bowl of fruit", "a cup of pens"
        else:
            continue
        # the parent's shape decides the word the scene model uses: a cavity holds (in), a flat
        # top carries (on); nothing goes in or on an ordinary object (a lamp): read as nearby
        role = CATEGORY_PRIORS[mentions[parent].categories[0]].role
        if role != "object":
            out.append(Relation(child, parent, "in" if role == "container" else "on"))
    return out


def read_instruction(text: str, scene_type: str | None = None) -> Instruction:
    """Read ``text`` (see the module docstring). ``scene_type`` overrides the one the text names."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError("the instruction is empty: say what the table should hold, e.g. "
                         "'a desk with a laptop, a mug and a pen in the pen holder'")
    words = _TOKEN.findall(text.lower())
    stated, used = _find_scene_type(words)
    if scene_type is not None:
        key = scene_type.strip().lower().replace("_", " ")
        if key not in SCENE_TYPE_SPECS:
            raise ValueError(f"unknown scene type {scene_type!r}; known: {', '.join(SCENE_TYPE_SPECS)}")
        stated = key
    mentions: list[Mention] = []
    i = 0
    while i < len(words):
        if i in used:
            i += 1
            continue
        for size in range(min(_LONGEST, len(words) - i), 0, -1):
            span = range(i, i + size)
            if used & set(span):
                continue
            found = _lookup(words[i:i + size], stated)
            if found is not None:
                cats, plural = found
                count = _count_before(words, i, used)
                mentions.append(Mention(" ".join(words[i:i + size]), cats, count, plural, i, i + size))
                used |= set(span)
                i += size
                break
        else:
            i += 1
    diners = None
    match = re.search(r"\bfor (\w+)(?: (?:people|persons|guests|diners))?\b", " ".join(words))
    if match and match.group(1) in _NUMBERS and match.group(1) not in ("a", "an", "some", "few"):
        diners = _NUMBERS[match.group(1)]
        used |= {k for k, w in enumerate(words) if w == match.group(1)}
    counted = {m.start - 1 for m in mentions if m.count is not None} | {m.start - 2 for m in mentions
                                                                          if m.count is not None}
    unknown = tuple(dict.fromkeys(
        w for k, w in enumerate(words)
        if k not in used and k not in counted and w not in _FILLER and w not in _NUMBERS and not w.isdigit()
        and w not in _SCENE_WORDS and w not in _TYPE_WORDS))
    resolved = stated or _infer_scene_type([m.categories for m in mentions] or [("mug",)])
    return Instruction(text=text, scene_type=resolved, scene_type_stated=stated is not None,
                       words=tuple(words), mentions=tuple(mentions),
                       relations=tuple(_relations(words, mentions)),
                       diners=diners, unknown=unknown, only=bool({"only", "just"} & set(words)))


def _count_before(words: list[str], i: int, used: set[int]) -> int | None:
    """The number written just before word ``i`` ("two mugs", "3 pens", "two white mugs")."""
    for back in (1, 2):
        k = i - back
        if k < 0 or k in used:
            return None
        w = words[k]
        if w.isdigit():
            return max(1, min(int(w), 12))
        if w in _NUMBERS:
            return _NUMBERS[w]
        if w not in _LINKERS:
            return None
    return None
