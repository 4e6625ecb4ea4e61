"""The compiled CTRC reader's constants: capacities, key and word codes, status codes, hashes.

The reader knows the format by role, not by name: the caller gives the words (key names,
relation names) in the role order below (:data:`ENTRY_ROLES`, :data:`TOP_ROLES`,
:data:`WORD_ROLES`) and the numeric limits as launch arguments (:class:`ReaderLimits`), so that
the grammar is described once, on the caller's side.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

__all__ = [
    "CHUNK",
    "ENTRY_ROLES",
    "FNV_OFFSET",
    "FNV_PRIME",
    "MAX_ENTRIES",
    "STATUS",
    "S_LONG",
    "TOP_ROLES",
    "WORD_ROLES",
    "ReaderLimits",
    "category_hash",
    "keyword_table",
]

# Entries (the zone entry included) one text may hold on the fast path; more go to Python.
MAX_ENTRIES = 64
# Bytes per prescan thread.
CHUNK = wp.constant(256)
DEG = wp.constant(wp.float64(np.pi / 180.0))  # math.radians multiplies by exactly this
PI = wp.constant(wp.float64(np.pi))
TWO_PI = wp.constant(wp.float64(2.0 * np.pi))

FNV_OFFSET = 14695981039346656037
FNV_PRIME = 1099511628211
FNV_OFFSET_U64 = wp.constant(wp.uint64(FNV_OFFSET))
FNV_PRIME_U64 = wp.constant(wp.uint64(FNV_PRIME))

# The roles of the words the reader compares against, in keyword-table order (a role's index is
# its code below). The caller names each role (physcene.reward.text_batch: the grammar's words).
ENTRY_ROLES = (
    "layer",
    "instance_id",
    "category",
    "parent_id",
    "relation_type",
    "description",
    "relative_bbox",
    "relative_rotation_deg",
    "type",
    "bbox",
    "z_rotation",
)
TOP_ROLES = ("objects", "item_placement_zone")
WORD_ROLES = ("root_zone", "zone", "in", "on", "near")
K_LAYER, K_IID, K_CAT, K_PARENT, K_REL, K_DESC, K_BOX, K_ROT, K_TYPE, K_BBOX, K_ZROT = range(11)
K_OBJECTS, K_ZONE = 11, 12
W_ROOT, W_ZONE, W_IN, W_ON, W_NEAR = 13, 14, 15, 16, 17

STATUS = {
    -1: "no 'Scene Layout' marker, or a code fence / <json> token elsewhere in the text",
    -2: "JSON outside the canonical subset (syntax, nesting, literal, escape in a name)",
    -3: "unknown or repeated key",
    -4: "number outside the exact subset (exponent, > 15 digits, magnitude)",
    -5: "value the layered decoder would refuse or reinterpret (type, relation, extent, blank id)",
    -6: "hierarchy the decoder would refuse (duplicate id, unknown parent, cycle)",
    -7: "more entries than MAX_ENTRIES",
    -8: "no zone (item_placement_zone or zone entry bbox) the decoder would accept",
    -9: "category not in the engine's table yet (resolved on the host, then rescanned)",
    -10: "longer than the grammar's character limit (set on the host: the parser refuses it)",
}
S_MARKER, S_SYNTAX, S_KEY, S_NUMBER, S_VALUE, S_TREE, S_MANY, S_ZONE, S_CATEGORY, S_LONG = range(-1, -11, -1)
E_NONE = wp.constant(-100)  # entries kernel: no candidate in this slot

# Value kinds of the generic value reader.
V_STRING, V_INT, V_FLOAT, V_NULL, V_BOOL, V_ARRAY = range(6)


@dataclass(frozen=True, kw_only=True)
class ReaderLimits:
    """The format's numeric limits the reader applies (launch arguments of ``entries`` / ``walk``)."""

    max_abs_cm: float
    """|value| beyond this (cm) is refused (the parser's MAX_ABS_CM); the absolute-position check
    uses a hair less, so that a float64 ulp of difference with Python's libm never accepts what
    the parser refuses."""
    on_contact_gap_cm: float
    """An ``on`` child's z base: its support's top + this (the parser's ON_CONTACT_GAP_CM)."""

    def __post_init__(self):
        if not self.max_abs_cm > 0:
            raise ValueError(f"ReaderLimits: max_abs_cm={self.max_abs_cm}: expected > 0")
        if not self.on_contact_gap_cm >= 0:
            raise ValueError(f"ReaderLimits: on_contact_gap_cm={self.on_contact_gap_cm}: expected >= 0")

    def launch_values(self) -> tuple[float, float, float]:
        """(max |value|, max |absolute position|, on gap) as the kernels take them (float64)."""
        return (
            float(self.max_abs_cm),
            float(self.max_abs_cm * (1.0 - 1.0e-9)),
            float(self.on_contact_gap_cm),
        )


def category_hash(data: bytes) -> tuple[int, int]:
    """(FNV-1a 64-bit hash, (len << 32) | 31-polynomial 32-bit hash) of ``data``, as the kernel."""
    h, h2 = FNV_OFFSET, 0
    for b in data:
        h = ((h ^ b) * FNV_PRIME) & 0xFFFFFFFFFFFFFFFF
        h2 = (h2 * 31 + b) & 0xFFFFFFFF
    return h, (len(data) << 32) | h2


def keyword_table(
    entry_keys: Sequence[str], top_keys: Sequence[str], words: Sequence[str]
) -> tuple[np.ndarray, np.ndarray]:
    """(bytes uint8, starts int32 (K+1,)) of every word the reader compares against: the names of
    :data:`ENTRY_ROLES`, :data:`TOP_ROLES` and :data:`WORD_ROLES`, each in that role order."""
    for given, roles, what in (
        (entry_keys, ENTRY_ROLES, "entry_keys"),
        (top_keys, TOP_ROLES, "top_keys"),
        (words, WORD_ROLES, "words"),
    ):
        if len(given) != len(roles) or len(set(given)) != len(given):
            raise ValueError(
                f"keyword_table: {what}={tuple(given)}: expected {len(roles)} distinct names, "
                f"one per role of {roles}"
            )
    encoded = [w.encode() for w in (*entry_keys, *top_keys, *words)]
    starts = np.concatenate([[0], np.cumsum([len(w) for w in encoded])]).astype(np.int32)
    return np.frombuffer(b"".join(encoded), np.uint8).copy(), starts
