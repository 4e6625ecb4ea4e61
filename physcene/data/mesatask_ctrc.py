"""MesaTask-CTRC construction (the paper's Algorithm 1) for any MesaTask-format layout.

For one layout: the hierarchical scene graph is extracted from the absolute boxes
(:func:`physcene.graph.build_hierarchy`: in ≻ on ≻ near), the objects are ordered anchor-first
(:func:`physcene.graph.anchor_order`), every box is made relative to its parent and every object
gets its templated sub-instruction (:func:`physcene.ctrc.completion_text`); the instruction
comes from the layout itself, an endpoint (Prompts 1-2) or the template grammar. The result is
one JSONL record ``{id, scene_type, level, instruction, prompt, completion, layout, ...}``.

:func:`import_layout_tree` runs this over a real MesaTask-10k ``Layout_info`` tree.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from physcene.ctrc import DECIMALS, build_prompt, completion_text
from physcene.data.instructions import EndpointInstructor, check_instruction, template_instruction
from physcene.data.splits import level_of
from physcene.graph import GraphConfig, build_hierarchy
from physcene.layout import iter_layout_tree, layout_to_dict
from physcene.scene import TABLE, Scene

__all__ = ["ctrc_record", "dumps_record", "hierarchy_agreement", "import_layout_tree"]


def hierarchy_agreement(intended: Scene, extracted: Scene) -> float:
    """Fraction of objects whose extracted (parent, relation) equals the intended one (1.0 if empty)."""
    if len(intended) == 0:
        return 1.0
    got = {o.instance_id: (o.parent, o.relation) for o in extracted.objects}
    same = sum(got.get(o.instance_id) == (o.parent or TABLE, o.relation or "near") for o in intended.objects)
    return same / len(intended)


def ctrc_record(
    scene: Scene,
    *,
    record_id: str,
    rng: np.random.Generator,
    instruction: str | None = None,
    instructor: EndpointInstructor | None = None,
    prompt_objects: bool = True,
    graph_config: GraphConfig | None = None,
    decimals: int = DECIMALS,
) -> dict:
    """One MesaTask-CTRC record of ``scene`` (Algorithm 1 over its absolute boxes).

    The hierarchy is always rebuilt from geometry (any hierarchy ``scene`` carries is the
    intent and is only compared, in ``hierarchy_agreement``). The instruction is, in order:
    ``instruction``, the layout's own, the endpoint's (Prompts 1-2; falls back to the grammar if
    the endpoint fails), the grammar's.
    """
    plain = scene.with_objects(o.moved(parent=None, relation=None) for o in scene.objects)
    hierarchy = build_hierarchy(plain, graph_config)
    record: dict = {}
    text = instruction or scene.instruction or None
    if text is None and instructor is not None:
        try:
            record["description"], text = instructor.instruct(hierarchy)
        except RuntimeError as exc:
            record["instruction_fallback"] = str(exc)
    if text is None:
        text = template_instruction(scene, rng)
    problem = check_instruction(text)
    if problem and text != scene.instruction:
        raise ValueError(f"record {record_id}: instruction {text!r}: {problem}")
    hierarchy = Scene(
        zone=hierarchy.zone,
        objects=hierarchy.objects,
        scene_type=hierarchy.scene_type,
        instruction=text,
        restricted_zones=hierarchy.restricted_zones,
        meta=dict(hierarchy.meta),
    )
    record.update(
        {
            "id": record_id,
            "scene_type": scene.scene_type,
            "level": level_of(max(len(scene), 1)),
            "n_objects": len(scene),
            "instruction": text,
            "prompt": build_prompt(
                text,
                scene.scene_type,
                scene.zone,
                objects=list(hierarchy.objects) if prompt_objects else None,
            ),
            "completion": completion_text(hierarchy, decimals=decimals),
            "layout": layout_to_dict(hierarchy),
        }
    )
    if scene.has_hierarchy:
        record["hierarchy_agreement"] = round(hierarchy_agreement(scene, hierarchy), 6)
    return record


def dumps_record(record: dict) -> str:
    """One JSONL line: sorted keys, no NaN, UTF-8 text (byte-identical for equal records)."""
    return json.dumps(record, sort_keys=True, ensure_ascii=False, allow_nan=False, separators=(",", ":"))


def import_layout_tree(
    root,
    *,
    seed: int = 0,
    instructor: EndpointInstructor | None = None,
    prompt_objects: bool = True,
    skip_errors: bool = False,
    decimals: int = DECIMALS,
) -> Iterator[tuple[Path, dict]]:
    """(path, record) for every ``Layout_info/<table_type>/<scene>/layout.json`` under ``root``.

    Ids are ``<table_type>/<scene>`` (the folders); the table type folder names the scene type
    (``office_table`` -> ``office table``). Empty layouts are skipped (no level exists for them).
    """
    from physcene.data.splits import record_rng

    for k, (path, scene) in enumerate(iter_layout_tree(root, skip_errors=skip_errors)):
        if len(scene) == 0:
            continue
        record_id = f"{path.parent.parent.name}/{path.parent.name}"
        yield (
            path,
            ctrc_record(
                scene,
                record_id=record_id,
                rng=record_rng(seed, "import", k),
                instructor=instructor,
                prompt_objects=prompt_objects,
                decimals=decimals,
            ),
        )
