"""A table's rows scored again from their committed layouts, with the scoring code of this checkout.

An ablation table (``ablation.json``: rows and checkpoint rows, each naming its ``layouts``) keeps the
figures its evaluation computed. When the scoring changes (the engine, the judge, the assets the split
is synthesised on), the figures of older tables stop being what ``physcene eval --generator file:...``
recomputes from their layouts. This scores every row's layouts on the table's test split again, as the
ablation scores a row (:func:`physcene.train.ablation.table_row`), keeps what the layouts do not give
(``anchor_nll``, ``layouts``, the validation figures, ``chosen``), writes the table in place (or to
``--out``) and prints each row whose figures moved:

    python -m physcene.train.analysis.rescore docs/results/ablation_phys_credit.json

The rows of every seed are scored on one draw of the split (``test_split``: name, seed, n); a file of
another draw is refused by the ``file:`` generator's scene check.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

__all__ = ["rescore_table"]

_SCORED = ("scr", "acr", "qpr7", "qpr8", "qpr9", "judge_avg", "parse_rate", "floating", "shrunk",
           "out_of_zone", "n", "by_level", "parse_error_kinds")


def rescore_table(table: str | Path, out: str | Path | None = None, root: str | Path = ".",
                  seed: int | None = None, device: str = "cpu") -> list[dict]:
    """Score every row of ``table`` that names its layouts again (``seed``: only that seed's rows);
    write the table to ``out`` (default: in place). Returns one ``{name, seed, rl_steps, before,
    after}`` per row whose figures changed (``before``/``after``: the changed figures). ``root``: what
    the rows' ``layouts`` paths are relative to (the repository); ``device``: the physics engine's (a
    CPU and a GPU score can differ by a scene: score a table on the device its rows were scored on)."""
    from physcene.eval.harness import generate, make_judge, score_scenes
    from physcene.physics import PhysicsEngine
    from physcene.train.ablation import _load_split, check_ablation, table_row, write_ablation

    table = Path(table)
    data = check_ablation(json.loads(table.read_text()), str(table))
    split = data.get("test_split")
    if not split:
        raise ValueError(f"{table}: no test_split (name, seed, n) to score the rows on")
    items = _load_split(split)
    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine(device=device)
    changed = []
    for key in ("rows", "checkpoint_rows"):
        for row in data.get(key) or []:
            if not row.get("layouts") or (seed is not None and int(row["seed"]) != seed):
                continue
            path = Path(root) / row["layouts"]
            outputs = generate(items, f"file:{path}")
            results = score_scenes(items, outputs, judge, engine, progress=False)
            new = table_row(row["name"], items, outputs, results, engine, seed=int(row["seed"]),
                            rl_steps=int(row["rl_steps"]))
            moved = {k: (row.get(k), new.get(k)) for k in _SCORED if k in new and new.get(k) != row.get(k)}
            row.update({k: new[k] for k in _SCORED if k in new})
            if moved:
                changed.append({"name": row["name"], "seed": row["seed"], "rl_steps": row["rl_steps"],
                                "before": {k: v[0] for k, v in moved.items() if k != "by_level"},
                                "after": {k: v[1] for k, v in moved.items() if k != "by_level"}})
            was = f" (was {moved['scr'][0]:.4f})" if "scr" in moved else ""
            print(f"rescore: {row['name']} seed {row['seed']} @ {row['rl_steps']}: SCR {new['scr']:.4f}{was}",
                  file=sys.stderr)
    write_ablation(check_ablation(data, str(table)), Path(out) if out else table)
    return changed


def main(argv=None) -> int:
    prog = "python -m physcene.train.analysis.rescore"
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("table", help="an ablation table (ablation.json) whose rows name their layouts")
    parser.add_argument("--out", help="where to write the rescored table (default: in place)")
    parser.add_argument("--seed", type=int, help="only the rows of this seed (the others as they are)")
    parser.add_argument("--device", default="cpu", help="the physics engine's device (default: cpu)")
    parser.add_argument("--json", action="store_true", help="print the changed rows as JSON")
    args = parser.parse_args(argv)
    changed = rescore_table(args.table, args.out, seed=args.seed, device=args.device)
    if args.json:
        print(json.dumps({"changed": changed, "command": shlex.join([prog, *(argv or sys.argv[1:])])},
                         indent=1))
    else:
        for c in changed:
            print(f"{c['name']} seed {c['seed']} @ {c['rl_steps']}: {c['before']} -> {c['after']}")
        print(f"{len(changed)} row(s) changed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
