"""Near-contacts or overlaps: the SCR a file's layouts would read with a margin kept between neighbours.

    python -m physcene.eval.analysis.margins docs/results/ablation_phys_refresh/s1/pada.jsonl.gz \
        --margins 0 0.5 1 2 [--split test] [--n 866] [--out FILE]

Each table-level object (parent ``root_zone``) that carries no other object has its width and depth
made ``c`` cm smaller, its centre, height and yaw kept: where a generator had placed every such object
``c / 2`` cm further from its neighbours on each side. The layouts are then scored by the physics
engine as ``physcene eval`` scores them (SCR: a scene with any interpenetrating pair). Objects that
carry others keep their size (shrinking a container would push its contents into its walls), and so
do the carried objects. Where the SCR falls steeply with ``c``, the collisions left are near-contacts
that a clearance in the placement (or the reward) would remove; where it barely moves, they are
overlaps of several centimetres. Reported per ``c``: SCR overall and by level, and the share of
scenes that collide through table-level pairs only.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from physcene.data.splits import plan_split
from physcene.eval.analysis import add_split_arguments
from physcene.eval.analysis.crowding import layouts_by_id
from physcene.scene import TABLE, Scene

__all__ = ["with_margin", "margin_rows"]


def with_margin(scene: Scene, margin_cm: float) -> Scene:
    """``scene`` with each childless table-level object's width and depth ``margin_cm`` smaller (at
    least 0.1 cm; a negative margin makes them larger)."""
    carriers = {o.parent for o in scene.objects}
    objects = []
    for o in scene.objects:
        if o.parent in (None, TABLE) and o.instance_id not in carriers:
            w, d, h = o.size
            o = replace(o, size=(max(w - margin_cm, 0.1), max(d - margin_cm, 0.1), h))
        objects.append(o)
    return replace(scene, objects=tuple(objects))


def margin_rows(scenes: list[tuple[int, Scene]], margins, engine, batch: int = 128) -> dict:
    """Per margin: ``scr``, ``scr_by_level`` and ``table_pairs_only`` (the share of scenes whose every
    interpenetrating pair is two table-level objects) of ``scenes`` ((level, scene) pairs)."""
    levels = np.array([level for level, _ in scenes])
    rows = {}
    for margin in margins:
        moved = [with_margin(s, float(margin)) for _, s in scenes]
        pairs = []
        for k in range(0, len(moved), batch):
            pairs += engine.score(moved[k:k + batch]).pairs
        colliding = np.array([len(p) > 0 for p in pairs])
        table_only = np.array([
            bool(p) and all(s.objects[i].parent in (None, TABLE) and s.objects[j].parent in (None, TABLE)
                            for i, j, _ in p)
            for s, p in zip(moved, pairs)])
        rows[f"{float(margin):g}"] = {
            "scr": round(float(colliding.mean()), 4),
            "scr_by_level": {str(lv): round(float(colliding[levels == lv].mean()), 4)
                             for lv in sorted(set(levels.tolist()))},
            "table_pairs_only": round(float(table_only.mean()), 4),
        }
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("layouts", help="a JSONL[.gz] of {id, layout} records, or a folder of <id>.json")
    parser.add_argument("--margins", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0])
    add_split_arguments(parser)
    args = parser.parse_args()
    level_of = {f"{args.split}-{item.index:05d}": item.level
                for item in plan_split(args.split, args.n, args.seed)}
    found = layouts_by_id(Path(args.layouts), level_of)
    if not found:
        raise SystemExit(f"{args.layouts}: no layout of the first {args.n} records of {args.split!r}")
    from physcene.physics import PhysicsEngine

    scenes = [(level_of[rid], scene) for rid, scene in sorted(found.items())]
    rows = margin_rows(scenes, args.margins, PhysicsEngine(device=args.device))
    for margin, row in rows.items():
        by_level = " / ".join(f"{100 * v:.1f}" for v in row["scr_by_level"].values())
        print(f"margin {margin:>4s} cm: SCR {100 * row['scr']:.1f}% (levels {by_level}), "
              f"table-level pairs only {100 * row['table_pairs_only']:.1f}%")
    if args.out:
        Path(args.out).write_text(json.dumps({"layouts": args.layouts, "split": args.split, "n": len(scenes),
                                              "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
