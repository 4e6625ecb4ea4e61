"""Splits and their stratification: the paper's Table 5 (scene type × difficulty level).

Levels by object count N: 1 (1-4), 2 (5-8), 3 (9-12), 4 (13-16), 5 (17+). The test split
reproduces Table 5 exactly (866 scenes); the train split follows the same type × level
proportions (largest-remainder rounding to 9,429 by default); the OOD split has 50 scenes per
OOD type with that type's own level mix. Every plan is a pure function of its arguments, so
record ``i`` of a split always gets the same (type, level, N).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physcene.data.scene_types import OOD_SCENE_TYPES, SCENE_TYPES, spec_for

__all__ = [
    "DEFAULT_SIZES",
    "LEVEL_RANGES",
    "SPLITS",
    "TABLE5",
    "PlanItem",
    "level_of",
    "plan_split",
    "select_test",
    "record_rng",
    "stratified_counts",
]

SPLITS = ("train", "test", "ood")
DEFAULT_SIZES = {"train": 9429, "test": 866, "ood": 200}

# Object-count range per level (inclusive); level 5 is open-ended, the generator caps it.
LEVEL_RANGES = {1: (1, 4), 2: (5, 8), 3: (9, 12), 4: (13, 16), 5: (17, 22)}

# The paper's Table 5: test scenes per scene type and level 1..5 (totals 115/149/156/163/134/149).
TABLE5: dict[str, tuple[int, int, int, int, int]] = {
    "coffee table": (6, 47, 41, 15, 6),
    "office table": (3, 54, 57, 25, 10),
    "dressing table": (7, 59, 60, 22, 8),
    "dining table": (7, 63, 56, 26, 11),
    "kitchen counter": (5, 56, 52, 16, 5),
    "bathroom vanity": (7, 59, 58, 23, 2),
}

_SPLIT_CODE = {"train": 1, "test": 2, "ood": 3, "import": 4}


def level_of(n_objects: int) -> int:
    """Difficulty level 1..5 of a scene with ``n_objects`` objects (1-4, 5-8, 9-12, 13-16, 17+)."""
    n = int(n_objects)
    if n < 1:
        raise ValueError(f"a scene needs at least one object, got n_objects={n_objects!r}")
    return min(5, (n - 1) // 4 + 1)


@dataclass(frozen=True)
class PlanItem:
    """What record ``index`` of a split will be."""

    index: int
    scene_type: str
    level: int
    n_objects: int


def record_rng(seed: int, split: str, index: int) -> np.random.Generator:
    """The RNG of one record, seeded from (seed, split, index) so parallel workers agree."""
    return np.random.default_rng([int(seed), _SPLIT_CODE[split], int(index)])


def _largest_remainder(weights: np.ndarray, total: int) -> np.ndarray:
    """Integer counts proportional to ``weights`` summing to ``total`` (ties by position)."""
    w = np.asarray(weights, dtype=np.float64)
    quota = w / w.sum() * total
    counts = np.floor(quota).astype(np.int64)
    order = np.lexsort((np.arange(len(w)), -(quota - counts)))
    counts[order[: total - counts.sum()]] += 1
    return counts


def stratified_counts(split: str, n: int | None = None) -> dict[tuple[str, int], int]:
    """{(scene_type, level): count} of a split of ``n`` scenes (default size when None).

    ``test`` at its default size is Table 5 itself; other sizes scale Table 5 (or the OOD level
    mixes) by largest remainders, so the proportions are as close as integers allow.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    n = DEFAULT_SIZES[split] if n is None else int(n)
    if n < 1:
        raise ValueError(f"--n must be at least 1, got {n}")
    if split == "ood":
        per_type = _largest_remainder(np.ones(len(OOD_SCENE_TYPES)), n)
        out: dict[tuple[str, int], int] = {}
        for t, n_t in zip(OOD_SCENE_TYPES, per_type):
            levels = _largest_remainder(np.asarray(spec_for(t).level_weights), int(n_t)) if n_t else [0] * 5
            out.update({(t, lv): int(c) for lv, c in zip(range(1, 6), levels) if c > 0})
        return out
    cells = [(t, lv) for t in SCENE_TYPES for lv in range(1, 6)]
    weights = np.array([TABLE5[t][lv - 1] for t, lv in cells], dtype=np.float64)
    counts = _largest_remainder(weights, n)
    return {cell: int(c) for cell, c in zip(cells, counts) if c > 0}


def plan_split(split: str, n: int | None = None, seed: int = 0) -> list[PlanItem]:
    """The ordered plan of a split: one :class:`PlanItem` per record.

    Cells are interleaved by a seeded shuffle so that any prefix of the file is a mix of types
    and levels; the object count N is drawn uniformly within the level's range.
    """
    counts = stratified_counts(split, n)
    cells = [cell for cell, c in counts.items() for _ in range(c)]
    rng = np.random.default_rng([int(seed), _SPLIT_CODE[split], 0xC0FFEE])
    order = rng.permutation(len(cells))
    plan = []
    for index, k in enumerate(order):
        scene_type, level = cells[k]
        lo, hi = LEVEL_RANGES[level]
        if level == 5:  # dense scenes thin out quickly above 17 objects
            n_obj = lo + min(int(rng.geometric(0.35)) - 1, hi - lo)
        else:
            n_obj = int(rng.integers(lo, hi + 1))
        plan.append(PlanItem(index, scene_type, level, n_obj))
    return plan


def select_test(cells: list[tuple[str, int]], test_size: int = 866, seed: int = 0) -> list[int]:
    """Indices of the records held out as test: per (scene_type, level) cell, Table 5's count
    (scaled to ``test_size``) or all the cell has, drawn with a seeded permutation.

    ``cells`` gives each record's (scene_type, level); types outside Table 5 stay in train.
    """
    if test_size <= 0:
        return []
    want = stratified_counts("test", test_size)
    by_cell: dict[tuple[str, int], list[int]] = {}
    for k, (scene_type, level) in enumerate(cells):
        by_cell.setdefault((scene_type.strip().lower().replace("_", " "), int(level)), []).append(k)
    rng = np.random.default_rng([int(seed), _SPLIT_CODE["import"], 0x7E57])
    chosen: list[int] = []
    for cell in sorted(want):
        pool = by_cell.get(cell, [])
        take = min(want[cell], len(pool))
        chosen += [pool[int(i)] for i in rng.permutation(len(pool))[:take]]
    return sorted(chosen)
