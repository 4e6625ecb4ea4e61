"""How full the tables are, and how close table-level neighbours stand: clean, noisy and generated layouts.

    python -m physcene.eval.analysis.crowding --n 200 \
        sft=runs/small/ablation/sft pada=runs/small/ablation/pada \
        [--split test] [--out FILE]

Per difficulty level, over the table-level objects (parent ``root_zone``) of each scene:
``crowd`` = their summed footprint (width × depth) over the free zone area (the placement zone less
its restricted zones); ``gap`` = each object's distance to its nearest table-level neighbour,
max(x gap, y gap) of their yawed axis-aligned boxes (negative: the boxes overlap in both x and y, by
at least that much). Rows: ``clean`` (the split's layouts as planned, before annotation noise),
``noisy`` (the reference the records carry) and each ``NAME=DIR`` of generated ``layout.json`` files
named by record id (``physcene eval``'s layout folders) or a ``NAME=FILE.jsonl.gz`` of layout records
(the ablation's and the studies' row files, ``{"id", "layout"}`` per line). The boxes are a
conservative stand-in for the meshes; the collision metrics (SCR/ACR) use the SDFs.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from physcene.data.benchmark import DataConfig, build_scenes
from physcene.data.splits import plan_split
from physcene.eval.analysis import add_split_arguments
from physcene.layout import layout_record_lines, load_layout, read_layout
from physcene.scene import TABLE, Scene


def table_level(scene: Scene) -> list:
    return [o for o in scene.objects if o.parent in (None, TABLE)]


def crowd(scene: Scene) -> float:
    z = scene.zone
    free = (z.xmax - z.xmin) * (z.ymax - z.ymin) - sum(
        (r.xmax - r.xmin) * (r.ymax - r.ymin) for r in scene.restricted_zones)
    return sum(o.size[0] * o.size[1] for o in table_level(scene)) / free


def nearest_gaps(scene: Scene) -> list[float]:
    boxes = [o.aabb() for o in table_level(scene)]
    out = []
    for i, a in enumerate(boxes):
        gaps = [max(b[0] - a[1], a[0] - b[1], b[2] - a[3], a[2] - b[3])
                for j, b in enumerate(boxes) if j != i]
        if gaps:
            out.append(min(gaps))
    return out


def level_rows(scenes: list[tuple[int, Scene]]) -> dict:
    rows = {}
    for level in sorted({lv for lv, _ in scenes}):
        group = [s for lv, s in scenes if lv == level]
        gaps = np.array([g for s in group for g in nearest_gaps(s)])
        rows[str(level)] = {
            "n": len(group),
            "table_level_objects_mean": round(statistics.fmean(len(table_level(s)) for s in group), 1),
            "crowd_median": round(statistics.median(crowd(s) for s in group), 3),
            "gap_median_cm": round(float(np.median(gaps)), 2) if gaps.size else None,
            "gap_p10_cm": round(float(np.percentile(gaps, 10)), 2) if gaps.size else None,
            "overlapping_share": round(float((gaps < 0).mean()), 3) if gaps.size else None,
        }
    return rows


def layouts_by_id(path: Path, wanted) -> dict[str, Scene]:
    """Each layout in ``path`` whose record id is in ``wanted``: a folder of ``<id>.json`` files, or a
    JSONL (``.gz``) of ``{"id", "layout"}`` records (a null layout, one that did not parse, is left out)."""
    if path.name.endswith((".jsonl", ".jsonl.gz")):
        records = (json.loads(line) for _, line in layout_record_lines(path))
        return {str(r["id"]): load_layout(r["layout"], source=str(path)) for r in records
                if str(r.get("id")) in wanted and r.get("layout") is not None}
    return {p.stem: read_layout(p) for p in sorted(path.glob("*.json")) if p.stem in wanted}


def generated_layouts(path: Path, level_of: dict[str, int]) -> list[tuple[int, Scene]]:
    """(level, scene) of each layout in ``path`` whose id is in ``level_of`` (:func:`layouts_by_id`)."""
    return [(level_of[rid], scene) for rid, scene in layouts_by_id(path, level_of).items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("layouts", nargs="*",
                        help="NAME=DIR of generated layout.json files, or NAME=FILE.jsonl[.gz] of "
                             "layout records")
    add_split_arguments(parser, n=200, device=False)
    args = parser.parse_args()
    config = DataConfig()
    clean, noisy, level_of = [], [], {}
    for item in plan_split(args.split, args.n, args.seed):
        c, nz, _, _ = build_scenes(args.split, args.seed, item, config)
        clean.append((item.level, c))
        noisy.append((item.level, nz))
        level_of[f"{args.split}-{item.index:05d}"] = item.level
    rows = {"clean": level_rows(clean), "noisy": level_rows(noisy)}
    result = {"split": args.split, "n": args.n, "rows": rows}
    for spec in args.layouts:
        name, _, folder = spec.partition("=")
        scenes = generated_layouts(Path(folder), level_of)
        if not scenes:
            raise SystemExit(f"{spec}: no layout file named after one of the first {args.n} "
                             f"records of {args.split!r}")
        result["rows"][name] = level_rows(scenes)
    for name, rows in result["rows"].items():
        for level, r in rows.items():
            print(f"{name:10s} L{level} n={r['n']:3d} objects {r['table_level_objects_mean']:5.1f} "
                  f"crowd {r['crowd_median']:.2f}  gap median {r['gap_median_cm']:6.2f} "
                  f"p10 {r['gap_p10_cm']:6.2f} cm"
                  f"  overlapping {r['overlapping_share']:.2f}")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
