"""Quickstart: an instruction in; a checked, repaired, rendered and exported tabletop layout out.

    python examples/quickstart.py [OUT_DIR]          (docs/generate.md)
"""

import sys
from pathlib import Path

import physcene

out = Path(sys.argv[1] if len(sys.argv) > 1 else "quickstart-out")
scene = physcene.generate("a desk with a laptop, two mugs and a pen in the pen holder", seed=1)[0].scene
print("generated:", ", ".join(scene.ids()))

# Push the second mug into the first one, to give the checker and the repair something to find.
first, second = [o for o in scene.objects if o.category == "mug"][:2]
moved = second.moved(center=(first.center[0] + 4.0, first.center[1], second.center[2]))
scene = scene.with_objects(moved if o is second else o for o in scene.objects)
print("check:", physcene.check(scene)["pairs"])  # [{"a": "4_mug_0", "b": "4_mug_1", "depth_cm": ...}]

fixed, report = physcene.repair(scene)
print("repaired:", physcene.check(fixed)["pairs"], f"largest move {report['max_displacement_cm']:.1f} cm")
physcene.save_layout(fixed, out / "layout.json")
physcene.render(fixed, out / "desk.png")
print("MuJoCo:", physcene.export(fixed, out / "mjcf", "mjcf"))
