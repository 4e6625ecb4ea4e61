"""Benchmark data: synthetic MesaTask-style scenes, noise, instructions, MesaTask-CTRC construction.

``synthesize(split, n=None, seed=0)`` yields records ``{id, scene_type, level, instruction,
prompt, completion, layout, ...}``; ``SCENE_TYPES`` / ``OOD_SCENE_TYPES`` name the table types;
``level_of(n_objects)`` is the paper's difficulty level (docs/data.md); ``noisy_scenes`` builds
the seeded noisy stacks TTO is measured on (:mod:`physcene.data.noisy`).
"""

from physcene.data.benchmark import DataConfig, synthesize, write_split
from physcene.data.mesatask_ctrc import ctrc_record, import_layout_tree
from physcene.data.noisy import noisy_scenes
from physcene.data.scene_types import OOD_SCENE_TYPES, SCENE_TYPES
from physcene.data.splits import TABLE5, level_of, plan_split

__all__ = [
    "DataConfig",
    "OOD_SCENE_TYPES",
    "SCENE_TYPES",
    "TABLE5",
    "ctrc_record",
    "import_layout_tree",
    "level_of",
    "noisy_scenes",
    "plan_split",
    "synthesize",
    "write_split",
]
