"""Which pairs collide in an ablation's generated layouts, how deep, and what a contact tolerance changes.

    python docs/results/collision_kinds.py runs/small/ablation [ROW ...] [--out FILE.json]

Reads each row's parsed layouts (``ablation.layouts``: ``<dir>/<row>/<id>.json``, MesaTask layout with
``parent`` / ``relation`` per object), scores them with the engine (CPU), and sorts every colliding
pair (depth > 0) by where it sits in the scene graph: parent and child (``on`` / ``in``), siblings on
the table (both ``near``), siblings in or on one parent, or objects of different subtrees. Prints the
pairs, their share and median depth per kind, and the SCR at small penetration thresholds (resting
contacts written at 2 decimals touch exactly, and the sampled SDF reads some of them as 1e-3 cm deep).
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from physcene.eval.metrics import physics_from_score

from physcene.layout import read_layout
from physcene.physics import PhysicsEngine
from physcene.scene import TABLE

THRESHOLDS_CM = (0.0, 0.001, 0.01, 0.1, 0.5)


def pair_kind(a: str, b: str, parent: dict, relation: dict) -> str:
    if parent.get(a) == b or parent.get(b) == a:
        child = a if parent.get(a) == b else b
        return f"parent-child ({relation.get(child)})"
    if parent.get(a) == parent.get(b):
        return "siblings on the table" if parent.get(a) == TABLE else "siblings in/on one parent"
    return "different subtrees"


def row_figures(directory: Path, engine: PhysicsEngine) -> dict:
    files = sorted(directory.glob("*.json"))
    scenes, graphs = [], []
    for f in files:
        raw = json.loads(f.read_text())
        graphs.append(({o["instance"]: o.get("parent") for o in raw["objects"]},
                       {o["instance"]: o.get("relation") for o in raw["objects"]}))
        scenes.append(read_layout(f))
    physics = []
    for k in range(0, len(scenes), 16):
        physics += physics_from_score(scenes[k:k + 16], engine.score(scenes[k:k + 16]))
    kinds, depths = Counter(), defaultdict(list)
    for scene, p, (parent, relation) in zip(scenes, physics, graphs):
        ids = [o.instance_id for o in scene.objects]
        for i, j, d in p.pair_depths:
            kind = pair_kind(ids[i], ids[j], parent, relation)
            kinds[kind] += 1
            depths[kind].append(d)
    n = max(sum(kinds.values()), 1)
    per_scene = [len(p.pair_depths) for p in physics]
    return {
        "scenes": len(scenes), "colliding_pairs": sum(kinds.values()),
        "colliding_pairs_per_scene_median": float(np.median(per_scene)),
        "scenes_with_one_colliding_pair": sum(c == 1 for c in per_scene),
        "scr_by_threshold_cm": {str(t): float(np.mean([p.colliding_pairs(t) > 0 for p in physics]))
                                for t in THRESHOLDS_CM},
        "kinds": {k: {"pairs": c, "share": round(c / n, 3),
                      "depth_median_cm": round(float(np.median(depths[k])), 3),
                      "deeper_than_0.5cm": round(float(np.mean(np.array(depths[k]) > 0.5)), 3)}
                  for k, c in kinds.most_common()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("layouts", type=Path, help="the ablation's layouts folder (ablation.layouts)")
    parser.add_argument("rows", nargs="*", help="rows to read (default: every subfolder)")
    parser.add_argument("--out", type=Path, help="write the figures as JSON here")
    args = parser.parse_args()
    rows = args.rows or sorted(p.name for p in args.layouts.iterdir() if p.is_dir())
    engine = PhysicsEngine()
    result = {}
    for row in rows:
        result[row] = row_figures(args.layouts / row, engine)
        r = result[row]
        print(f"{row}: {r['colliding_pairs']} colliding pairs in {r['scenes']} scenes (median "
              f"{r['colliding_pairs_per_scene_median']:.0f} a scene); SCR by threshold "
              f"{r['scr_by_threshold_cm']}", flush=True)
        for kind, k in r["kinds"].items():
            print(f"  {kind}: {k['pairs']} ({100 * k['share']:.0f} %), median depth "
                  f"{k['depth_median_cm']} cm, {100 * k['deeper_than_0.5cm']:.0f} % deeper than 0.5 cm",
                  flush=True)
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
