"""``physcene settle``: the MuJoCo settle test (physcene.settle) over layouts.

    physcene settle scene/layout.json                # one layout
    physcene settle Layout_info/ data.jsonl --json   # a tree of layout.json files, a JSONL dataset
    physcene settle data.jsonl settle.duration_s=4 mujoco.timestep=0.001   # configs/export.yaml
    physcene settle data.jsonl --workers 8 --json > settle.json           # scenes in 8 processes

PATH is a layout.json, a directory (searched recursively for layout.json) or a JSONL file whose
records carry a ``layout`` object (a record is named ``FILE:LINE``). A scene is stable when every
object moved ≤ 1 cm and turned ≤ 0.1 rad over 2 s. ``--json`` prints
``{"scenes": [{"path", "stable", "objects": [{"id", "moved_cm", "turned_rad", "stable"}]}],
"stability_rate", "object_stability_rate"}``; an unreadable layout is a record with ``"error"``
(and ``"stable": null``), left out of the rates. Exit 0 whatever the stability; 2 when some input
was unreadable (each named on stderr).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path

from physcene.commands import add_quiet, json_safe
from physcene.commands.check import collect
from physcene.export import ExportConfig
from physcene.scene import Scene
from physcene.settle import SettleConfig, object_stability_rate, settle_many, stability_rate

NAME = "settle"
HELP = "Simulate layouts in MuJoCo for 2 s and report which objects stay put (stability rate)"
SETTINGS = "configs/export.yaml: settle.* and mujoco.* (docs/export.md)"


def add_arguments(parser) -> None:
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="layout.json, a directory of layout.json files, or a JSONL dataset")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    parser.add_argument("--workers", type=int, default=1,
                        help="processes to simulate scenes in parallel (default 1)")
    add_quiet(parser)


def read_inputs(paths: Sequence[str]) -> list[tuple[str, Scene | None, str | None]]:
    """(label, scene, error) for every layout named by ``paths``, read the way ``physcene check``
    reads them; ``FILE.jsonl:LINE`` names one record. Unreadable layouts carry an error message."""
    items = []
    for raw in paths:
        head, _, line = raw.rpartition(":")
        if not Path(raw).exists() and head.endswith(".jsonl") and line.isdigit() and Path(head).is_file():
            found = [i for i in collect([head]) if i.path == raw]
            items.extend(found or [_NoRecord(raw)])
        else:
            items.extend(collect([raw]))
    return [(i.path, i.scene, i.error) for i in items]


class _NoRecord:
    def __init__(self, raw: str):
        self.path, self.scene, self.error = raw, None, f"{raw}: no layout record on that line"


def run(args) -> int:
    export_config = ExportConfig.load(args.overrides)  # a bad setting fails before any reading
    config = SettleConfig.load(args.overrides)
    items = read_inputs(args.paths)
    readable = [(label, scene) for label, scene, error in items if error is None]
    errors = [error for _, _, error in items if error is not None]
    if args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    results = settle_many([scene for _, scene in readable], config=config, export_config=export_config,
                          paths=[label for label, _ in readable], workers=args.workers,
                          progress=not args.quiet)
    rate, object_rate = stability_rate(results), object_stability_rate(results)
    for error in errors:  # named on stderr; the readable scenes are still reported
        print(f"physcene settle: error: {error}", file=sys.stderr)
    if args.json:
        records = [r.to_dict() for r in results]
        records += [{"path": label, "stable": None, "objects": [], "error": error}
                    for label, _, error in items if error is not None]
        # strict JSON: a diverged simulation's NaN motion is null
        print(json.dumps(json_safe({"scenes": records, "stability_rate": rate,
                                    "object_stability_rate": object_rate}), allow_nan=False))
        return 2 if errors else 0
    for r in results:
        moving = [o for o in r.objects if not o.stable]
        verdict = "stable" if r.stable else "UNSTABLE" + (" (simulation diverged)" if r.diverged else "")
        print(f"{r.path}: {verdict}, {len(r.objects)} objects, max moved {r.max_moved_cm:.2f} cm")
        for o in moving:
            print(f"    {o.instance_id}: moved {o.moved_cm:.2f} cm, turned {o.turned_rad:.3f} rad")
    stable = sum(r.stable for r in results)
    print(f"stability rate: {stable}/{len(results)} scenes = {100 * rate:.1f} %; "
          f"objects {100 * object_rate:.1f} % stable")
    return 2 if errors else 0
