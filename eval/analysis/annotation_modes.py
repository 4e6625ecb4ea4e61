"""Which annotator a layout model imitates: SCR on the scenes its data annotated carefully or carelessly.

    python -m physcene.eval.analysis.annotation_modes --n 866 \
        small_sft=docs/results/base_small/noisy_greedy_cpu/sft_plan.jsonl.gz [--split test] [--out FILE]

The synthetic data (:mod:`physcene.data.noise`) annotates a share of each level's scenes carefully
(``careful_by_level``: no neighbours pushed into each other) and the rest carelessly (neighbour pairs
pushed 1.8-5.5 cm into each other). A model is prompted with the request alone, which does not say how
its scene was annotated. Were a model to reproduce the data's mixture, its SCR on the careful scenes'
requests would be the reference's there; a model that writes every scene the careless way collides as
often on the careful scenes' requests as on the others'. Rows: ``clean`` (the layouts as planned, before
the noise), ``reference`` (the noisy layouts the records carry) and each ``NAME=FILE`` (a JSONL (``.gz``)
of ``{"id", "layout"}`` records, or a folder of ``<id>.json`` layouts). Per level and over all: the number
of scenes and the SCR of the careful and the careless ones, and the median of the colliding scenes'
deepest pair (cm). Scenes whose layout did not parse are left out of a row (its ``n`` says how many count).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from physcene.data.benchmark import DataConfig, build_scenes
from physcene.data.splits import plan_split
from physcene.eval.analysis import add_split_arguments
from physcene.eval.analysis.crowding import layouts_by_id
from physcene.eval.metrics import deepest_pairs
from physcene.files import write_atomic

__all__ = ["annotation_rows"]

GROUPS = ("careful", "careless")


def _summary(entries: list[tuple[int, bool, float]]) -> dict:
    """``entries``: (level, careful, deepest pair cm) of scenes -> n, SCR and the colliding scenes'
    median deepest pair of each group, and the group shares."""
    out = {"n": len(entries)}
    for group in GROUPS:
        depths = [d for _, careful, d in entries if careful == (group == "careful")]
        hits = [d for d in depths if d > 0]
        out[group] = {"n": len(depths), "scr": len(hits) / len(depths) if depths else None,
                      "median_deepest_cm": statistics.median(hits) if hits else None}
    out["scr"] = sum(d > 0 for *_, d in entries) / len(entries) if entries else None
    return out


def annotation_rows(entries: list[tuple[int, bool, float]]) -> dict:
    """Per level (``"1"``..) and ``"all"``: :func:`_summary` of the (level, careful, depth) entries."""
    levels = sorted({lv for lv, *_ in entries})
    return {**{str(lv): _summary([e for e in entries if e[0] == lv]) for lv in levels},
            "all": _summary(entries)}


def _share(x: float | None) -> str:
    return "  -  " if x is None else f"{x:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("layouts", nargs="*", help="NAME=FILE.jsonl[.gz] of layout records, or NAME=DIR")
    add_split_arguments(parser)
    args = parser.parse_args()
    specs = [spec.partition("=") for spec in args.layouts]
    bad = [name + eq + path for name, eq, path in specs if not (name and eq and path)]
    if bad:
        parser.error(f"expected NAME=FILE or NAME=DIR, got {bad}")
    from physcene.physics import PhysicsEngine  # here: Warp loads after the arguments are checked

    config, engine = DataConfig(), PhysicsEngine(device=args.device)
    level_of, careful_of, clean, noisy = {}, {}, [], []
    for item in plan_split(args.split, args.n, args.seed):
        c, nz, noise, _ = build_scenes(args.split, args.seed, item, config)
        rid = f"{args.split}-{item.index:05d}"
        level_of[rid], careful_of[rid] = item.level, bool(noise.careful)
        clean.append(c)
        noisy.append(nz)
    ids = list(level_of)
    rows = {}
    for name, scenes, scene_ids in (("clean", clean, ids), ("reference", noisy, ids)):
        depths = deepest_pairs(scenes, engine)
        rows[name] = annotation_rows([(level_of[i], careful_of[i], d) for i, d in zip(scene_ids, depths)])
    for name, _, path in specs:
        found = layouts_by_id(Path(path), level_of)
        if not found:
            parser.error(f"{name}={path}: no layout of one of the first {args.n} records of {args.split!r}")
        depths = deepest_pairs(list(found.values()), engine)
        rows[name] = annotation_rows([(level_of[rid], careful_of[rid], d) for rid, d in zip(found, depths)])
    result = {"what": __doc__.splitlines()[0], "split": args.split, "n": args.n, "seed": args.seed,
              "careful_by_level": list(config.noise.careful_by_level), "rows": rows,
              "commands": ["python -m physcene.eval.analysis.annotation_modes " + " ".join(
                  [*args.layouts, "--split", args.split, "--n", str(args.n), "--seed", str(args.seed)])]}
    for name, by_level in rows.items():
        for level, r in by_level.items():
            cells = "  ".join(f"{g} n={r[g]['n']:3d} scr={_share(r[g]['scr'])}" for g in GROUPS)
            print(f"{name:12s} L{level:3s} n={r['n']:3d} scr={_share(r['scr'])}  {cells}")
    if args.out:
        write_atomic(Path(args.out), json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
