"""Baseline generators for ``physcene eval``: reference data, reference + TTO, zero-shot LLM through
an endpoint with the paper's Prompt 3, and a non-learned heuristic placer.

A generator maps benchmark items (:class:`~physcene.eval.harness.BenchmarkItem`) to one result
each: a :class:`~physcene.scene.Scene`, or a :class:`~physcene.ctrc.ParseError` when a model's
output did not parse (a value, never an exception).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import numpy as np

from physcene.scene import TABLE, Scene

__all__ = ["PROMPT_3", "heuristic_place", "objects_cluster", "zero_shot_prompt"]

# Paper appendix, Prompt 3 (Layout Generation by Zero-shot LLM), verbatim with the listing's
# line-break hyphens joined.
PROMPT_3 = """You are tasked with generating a scene graph layout for a tabletop arrangement based on the following instructions and parameters. 

### TASK:
Your primary goal is to output a **VALID JSON OBJECT** that strictly follows the specified format between the `<json>` tokens. This JSON must represent the scene graph layout for objects placed on a tabletop.

### INPUT PARAMETERS:
1. **Tabletop Information:**
   - The tabletop's dimensions are defined by the "item_placement_zone" with the following boundaries:  
     **item_placement_zone**: <item_placement_zone>
     Units are in centimeters (cm).

2. **Placement Instructions:**
   - Follow the natural language instructions to determine the placement of objects:  
     **Instructions**: "<instructions>"

3. **Objects Cluster:**
   - The objects to be placed on the tabletop are listed below. Each object must have:  
     - A **unique instance name**.
     - **Reasonable dimensions** (width, depth, height in cm).
     - A **position** within the specified tabletop boundaries.
     - A **z_rotation** (rotation around the vertical axis in radians). If not specified, assume `z_rotation = 0.0`.
     - A **short description** that explains the object's purpose or appearance.  
     **Objects cluster**: <Objects cluster>

### OUTPUT REQUIREMENTS:
- You must output a **VALID JSON OBJECT** strictly between the `<json>` tokens.  
  (not <json>xxx</json>)
- The JSON must have the following structure:

<json>
{
    "item_placement_zone": [
        x_min,
        x_max,
        y_min,
        y_max
    ],
    "objects": [
        {
            "instance": "unique_object_name",
            "z_rotation": float,
            "size": [width, depth, height],
            "position": [x, y, z],
            "description": "short description of the object"
        },
        ...
    ]
}
<json>

### DETAILED GUIDELINES:
1. **Object Placement:**
   - Ensure that all objects are placed within the boundaries of the `item_placement_zone`.
   - Follow the placement logic specified in the instructions. For example:  
     - If an object should be placed in a corner, position it near the respective boundary.  
     - If objects need to be grouped closely, ensure their positions are adjacent within reasonable spacing (e.g., 2-5 cm).  

2. **Object Properties:**
   - Assign **realistic dimensions** to each object based on its type. For instance:  
     - A woven basket might have dimensions like `[20.0, 15.0, 12.0]` (width, depth, height).  
     - A lotion bottle might have dimensions like `[5.0, 5.0, 15.0]`.
   - Use **intuitive and consistent instance names** (e.g., "woven_basket_0", "lotion_bottle_1").
   - Set the `z_rotation` to `0.0` unless the object is explicitly rotated in the instructions.

3. **Avoid Overlapping:**
   - Ensure objects do not overlap or extend beyond the tabletop boundaries.
   - Maintain logical spacing between objects unless the instructions specify otherwise.

4. **Avoid Suspension:**
    - Ensure that the items are firmly placed on the table. The position of each asset is the center coordinate, so the z value cannot be zero. If it is on the table, it should be half of the asset's height.
    - If there is a stacking situation, the z coordinate of the upper asset should be the sum of the z coordinate of the lower asset and half of the height of both assets.

5. **Output Validation:**
   - Ensure the JSON is valid by checking for correct syntax (e.g., no trailing commas, proper nesting of keys and values).

IMPORTANT:
The JSON output MUST be placed between the <json> tokens.
If you encounter ambiguity, use logical reasoning to infer the most likely placement or dimensions.
DO NOT include any additional text or explanations outside the <json> tokens in the output."""  # noqa: E501, W291


def objects_cluster(scene: Scene) -> list[dict]:
    """The requested objects as MesaTask lists them: instance name and description (no poses)."""
    return [{"instance": o.instance_id, "description": o.description or o.category.replace("_", " ")}
            for o in scene.objects]


def zero_shot_prompt(reference: Scene) -> str:
    """Prompt 3 filled with the reference's zone, instruction and object cluster."""
    zone = [round(v, 2) for v in reference.zone.to_list()]
    return (PROMPT_3.replace("<item_placement_zone>", json.dumps(zone))
            .replace("<instructions>", reference.instruction)
            .replace("<Objects cluster>", json.dumps(objects_cluster(reference))))


def heuristic_place(reference: Scene, seed: int = 0, gap_cm: float = 1.0, cell_cm: float = 1.0) -> Scene:
    """A non-learned placer: every requested object (its size from the request) stands on the
    table at a uniformly random free spot of the zone, largest footprint first, yaw 0 or 90°
    (whichever fits), ``gap_cm`` apart, with no stacking, containment or other semantics. Objects
    for which no free spot is left are dropped. Occupancy is a ``cell_cm`` grid; free spots come
    from a summed-area table, so a placement is O(grid)."""
    rng = np.random.default_rng(seed)
    z = reference.zone
    nx, ny = int(math.floor(z.width / cell_cm)), int(math.floor(z.depth / cell_cm))
    occ = np.zeros((nx, ny), dtype=np.int32)
    restricted = np.zeros_like(occ)
    for r in reference.restricted_zones:
        i0, i1 = int((r.xmin - z.xmin) // cell_cm), int(math.ceil((r.xmax - z.xmin) / cell_cm))
        j0, j1 = int((r.ymin - z.ymin) // cell_cm), int(math.ceil((r.ymax - z.ymin) / cell_cm))
        restricted[max(i0, 0):max(i1, 0), max(j0, 0):max(j1, 0)] = 1
    occ |= restricted
    placed = []
    order = sorted(reference.objects, key=lambda o: -o.size[0] * o.size[1])
    for o in order:
        options = []
        for yaw, (w, d) in ((0.0, o.size[:2]), (0.5 * math.pi, o.size[1::-1])):
            kw, kd = int(math.ceil((w + gap_cm) / cell_cm)), int(math.ceil((d + gap_cm) / cell_cm))
            if kw > nx or kd > ny:
                continue
            sat = np.zeros((nx + 1, ny + 1), dtype=np.int64)
            sat[1:, 1:] = occ.cumsum(0).cumsum(1)
            window = sat[kw:, kd:] - sat[:-kw, kd:] - sat[kw:, :-kd] + sat[:-kw, :-kd]  # (nx-kw+1, ny-kd+1)
            free = np.argwhere(window == 0)
            if len(free):
                options.append((yaw, kw, kd, free))
        if not options:
            continue  # no room left: the placer drops it (CwT will notice)
        yaw, kw, kd, free = options[int(rng.integers(len(options)))]
        i, j = free[int(rng.integers(len(free)))]
        occ[i:i + kw, j:j + kd] = 1
        cx = z.xmin + (i + 0.5 * kw) * cell_cm
        cy = z.ymin + (j + 0.5 * kd) * cell_cm
        placed.append(o.moved(center=(cx, cy, 0.5 * o.size[2]), yaw=yaw, parent=TABLE, relation="near"))
    by_order = {o.instance_id: k for k, o in enumerate(reference.objects)}
    placed.sort(key=lambda o: by_order[o.instance_id])
    return reference.with_objects(placed)


def heuristic_generator(references: Sequence[Scene], seed: int = 0) -> list[Scene]:
    """:func:`heuristic_place` over a benchmark, one seed per scene."""
    return [heuristic_place(r, seed=seed * 100003 + k) for k, r in enumerate(references)]
