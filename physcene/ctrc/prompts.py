"""The CTRC prompts: the generation prompt (instruction, table, zone, object list) and the paper's
zero-shot Prompt 3. The decoding constraint reads a prompt's object list and zone back
(:mod:`physcene.train.constrained.grammar`) by the labels defined here."""

from __future__ import annotations

from physcene.ctrc.grammar import LAYOUT_HEADER, PLAN_HEADER
from physcene.ctrc.writer import json_line
from physcene.layout import category_from_instance
from physcene.scene import SceneObject, Zone

__all__ = ["OBJECT_LIST_LABEL", "PHYSICS_LABEL", "ZONE_LABEL", "build_prompt", "with_physics",
           "zero_shot_prompt"]

# Labels of the prompt lines a constraint reads back: "**Object List**: mug (2), pen (1)" and
# "**item_placement_zone**: [0.0, 120.0, 0.0, 60.0] (cm; ...)".
OBJECT_LIST_LABEL = "**Object List**: "
ZONE_LABEL = "**item_placement_zone**: "


PHYSICS_LABEL = "**Layout physics**: "
"""The line a physics-conditioned model (``model.physics_conditioned``) reads after its prompt."""


def with_physics(prompt: str, collision_free: bool = True) -> str:
    """``prompt`` with the line a physics-conditioned model reads: whether the layout is collision-free.

    Its SFT states each training layout's measured state (``reference_physics``, written by ``physcene data
    measure``), so the model learns the careful and the careless layouts of its data apart; generation
    always asks for a collision-free one."""
    return f"{prompt}\n{PHYSICS_LABEL}{'collision-free' if collision_free else 'colliding'}"


def _object_list(objects) -> str:
    counts: dict[str, int] = {}
    for o in objects:
        name = o.category if isinstance(o, SceneObject) else category_from_instance(str(o))
        name = name.replace("_", " ")
        counts[name] = counts.get(name, 0) + 1
    return ", ".join(f"{name} ({n})" for name, n in counts.items())


def _zone_list(zone) -> list[float]:
    return (zone if isinstance(zone, Zone) else Zone.from_list(zone)).to_list()


def build_prompt(instruction: str, scene_type: str, zone, objects=None, *, restricted_zones=()) -> str:
    """The CTRC generation prompt: instruction, table type, placement zone, optional object list.

    ``zone``: a :class:`Zone` or [xmin, xmax, ymin, ymax] cm; ``objects``: SceneObjects,
    categories or instance ids (counted per category), or None to let the model choose;
    ``restricted_zones``: Zones or rects (sinks) where nothing may stand, listed when given.
    """
    zone_vals = [round(v, 2) + 0.0 for v in _zone_list(zone)]
    lines = [
        "Generate a physically plausible layout of objects on the tabletop: nothing may float or "
        "interpenetrate.",
        f"**Instruction**: {instruction}",
        f"**Table type**: {scene_type}",
        f"{ZONE_LABEL}{json_line(zone_vals)} (cm; origin at the near-left corner, "
        "+x right, +y away from the viewer, +z up; the table top is z = 0)",
    ]
    if restricted_zones:
        rects = [[round(v, 2) + 0.0 for v in _zone_list(z)] for z in restricted_zones]
        lines.append(f"**restricted_zone**: {json_line(rects)} (nothing may stand there)")
    if objects:
        lines.append(f"{OBJECT_LIST_LABEL}{_object_list(objects)}")
    lines += [
        "",
        f"First write {PLAN_HEADER} as a numbered plan, one step per object: the anchor "
        "(the object closest to the table centre) first, then table-level objects by proximity, "
        "each container's or support's contents right after it, bottom-up.",
        f"Then write {LAYOUT_HEADER} as JSON with \"objects\" (a root_zone entry, then one entry "
        "per object with layer, instance_id, category, parent_id, relation_type in/on/near, "
        "description, relative_bbox [xmin, xmax, ymin, ymax, zmin, zmax] in cm in the parent's "
        "frame from its (xmin, ymin) corner, z from the parent's bottom for \"in\" and its top for "
        "\"on\", and relative_rotation_deg) and \"item_placement_zone\".",
    ]
    return "\n".join(lines)


_ZERO_SHOT = """You are tasked with generating a scene graph layout for a tabletop arrangement based on the \
following instructions and parameters.

### TASK:
Your primary goal is to output a **VALID JSON OBJECT** that strictly follows the specified format between \
the `<json>` tokens. This JSON must represent the scene graph layout for objects placed on a tabletop.

### INPUT PARAMETERS:
1. **Tabletop Information:**
   - The tabletop's dimensions are defined by the "item_placement_zone" with the following boundaries:
     **item_placement_zone**: {zone}
     Units are in centimeters (cm).

2. **Placement Instructions:**
   - Follow the natural language instructions to determine the placement of objects:
     **Instructions**: "{instruction}"

3. **Objects Cluster:**
   - The objects to be placed on the tabletop are listed below. Each object must have:
     - A **unique instance name**.
     - **Reasonable dimensions** (width, depth, height in cm).
     - A **position** within the specified tabletop boundaries.
     - A **z_rotation** (rotation around the vertical axis in radians). If not specified, assume \
`z_rotation = 0.0`.
     - A **short description** that explains the object's purpose or appearance.
     **Objects cluster**: {objects}

### OUTPUT REQUIREMENTS:
- You must output a **VALID JSON OBJECT** strictly between the `<json>` tokens.
  (not <json>xxx</json>)
- The JSON must have the following structure:

<json>
{{
    "item_placement_zone": [
        x_min,
        x_max,
        y_min,
        y_max
    ],
    "objects": [
        {{
            "instance": "unique_object_name",
            "z_rotation": float,
            "size": [width, depth, height],
            "position": [x, y, z],
            "description": "short description of the object"
        }},
        ...
    ]
}}
<json>

### DETAILED GUIDELINES:
1. **Object Placement:**
   - Ensure that all objects are placed within the boundaries of the `item_placement_zone`.
   - Follow the placement logic specified in the instructions. For example:
     - If an object should be placed in a corner, position it near the respective boundary.
     - If objects need to be grouped closely, ensure their positions are adjacent within reasonable \
spacing (e.g., 2-5 cm).

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
    - Ensure that the items are firmly placed on the table. The position of each asset is the center \
coordinate, so the z value cannot be zero. If it is on the table, it should be half of the asset's height.
    - If there is a stacking situation, the z coordinate of the upper asset should be the sum of the z \
coordinate of the lower asset and half of the height of both assets.

5. **Output Validation:**
   - Ensure the JSON is valid by checking for correct syntax (e.g., no trailing commas, proper nesting of \
keys and values).

IMPORTANT:
The JSON output MUST be placed between the <json> tokens.
If you encounter ambiguity, use logical reasoning to infer the most likely placement or dimensions.
DO NOT include any additional text or explanations outside the <json> tokens in the output."""


def zero_shot_prompt(instruction: str, zone, objects) -> str:
    """The paper's Prompt 3 (zero-shot LLM layout, MesaTask flat JSON between ``<json>`` tokens)."""
    return _ZERO_SHOT.format(zone=json_line([round(v, 2) + 0.0 for v in _zone_list(zone)]),
                             instruction=instruction, objects=_object_list(objects))
