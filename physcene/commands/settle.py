"""``physcene settle``: the MuJoCo settle test (physcene.settle) over layouts.

    physcene settle scene/layout.json                # one layout
    physcene settle Layout_info/ data.jsonl --json   # a tree of layout.json files, a JSONL dataset
    physcene settle data.jsonl settle.duration_s=4 mujoco.timestep=0.001   # configs/export.yaml

PATH is a layout.json, a directory (searched recursively for layout.json) or a JSONL file whose
records carry a ``layout`` object (a record is named ``FILE:LINE``). A scene is stable when every
object moved ≤ 1 cm and turned ≤ 0.1 rad over 2 s. ``--json`` prints
``{"scenes": [{"path", "stable", "objects": [{"id", "moved_cm", "turned_rad", "stable"}]}],
"stability_rate", "object_stability_rate"}``. Exit 0 whatever the stability; 2 for unreadable input.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path

from physcene.layout import load_layout, read_layout
from physcene.scene import Scene, SceneError

NAME = "settle"
HELP = "Simulate layouts in MuJoCo for 2 s and report which objects stay put (stability rate)"


def add_arguments(parser) -> None:
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="layout.json, a directory of layout.json files, or a JSONL dataset")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


def _jsonl(path: Path, only_line: int | None = None) -> list[tuple[str, Scene]]:
    out = []
    with path.open(encoding="utf-8") as fh:
        for line_no, line in enumerate(fh, 1):
            if not line.strip() or (only_line is not None and line_no != only_line):
                continue
            where = f"{path}:{line_no}"
            try:
                record = json.loads(line)
            except json.JSONDecodeError as exc:
                raise SceneError(f"invalid JSON ({exc.msg})", source=where) from None
            layout = record.get("layout") if isinstance(record, dict) else None
            if isinstance(layout, str):
                try:
                    layout = json.loads(layout)
                except json.JSONDecodeError as exc:
                    raise SceneError(f"field 'layout' is not JSON ({exc.msg})", source=where) from None
            if not isinstance(layout, dict):
                raise SceneError("expected a record with a 'layout' object", source=where)
            out.append((where, load_layout(layout, source=where)))
    if only_line is not None and not out:
        raise SceneError(f"no record on line {only_line}", source=str(path))
    return out


def read_inputs(paths: Sequence[str]) -> list[tuple[str, Scene]]:
    """(label, scene) for every layout named by ``paths``; raises naming the first unreadable one."""
    items: list[tuple[str, Scene]] = []
    for raw in paths:
        path = Path(raw)
        head, _, line = raw.rpartition(":")
        if not path.exists() and head.endswith(".jsonl") and line.isdigit() and Path(head).is_file():
            items.extend(_jsonl(Path(head), int(line)))
        elif not path.exists():
            raise FileNotFoundError(f"settle input {raw!r} does not exist")
        elif path.is_dir():
            found = sorted(path.rglob("layout.json"))
            if not found:
                raise FileNotFoundError(f"no layout.json under {raw!r}")
            items.extend((str(p), read_layout(p)) for p in found)
        elif path.suffix == ".jsonl":
            items.extend(_jsonl(path))
        else:
            items.append((str(path), read_layout(path)))
    return items


def run(args) -> int:
    from tqdm import tqdm

    from physcene.export import ExportConfig
    from physcene.settle import SettleConfig, object_stability_rate, settle, stability_rate

    items = read_inputs(args.paths)
    export_config = ExportConfig.load(args.overrides)
    config = SettleConfig.load(args.overrides)
    results = []
    for label, scene in tqdm(items, desc="settle", unit="scene", disable=len(items) < 2, file=sys.stderr):
        results.append(settle(scene, config=config, export_config=export_config, path=label))
    rate, object_rate = stability_rate(results), object_stability_rate(results)
    if args.json:
        print(json.dumps({"scenes": [r.to_dict() for r in results], "stability_rate": rate,
                          "object_stability_rate": object_rate}))
        return 0
    for r in results:
        moving = [o for o in r.objects if not o.stable]
        verdict = "stable" if r.stable else "UNSTABLE" + (" (simulation diverged)" if r.diverged else "")
        print(f"{r.path}: {verdict}, {len(r.objects)} objects, max moved {r.max_moved_cm:.2f} cm")
        for o in moving:
            print(f"    {o.instance_id}: moved {o.moved_cm:.2f} cm, turned {o.turned_rad:.3f} rad")
    stable = sum(r.stable for r in results)
    print(f"stability rate: {stable}/{len(results)} scenes = {100 * rate:.1f} %; "
          f"objects {100 * object_rate:.1f} % stable")
    return 0
