"""``physcene check``: penetration, floating objects and table penetration of layouts.

    physcene check scene/layout.json                    # one MesaTask layout
    physcene check Layout_info/ --json                  # every layout.json under a tree
    physcene check data.jsonl --device cuda             # a JSONL dataset (field "layout")
    physcene check docs/results/ablation/s0/pada.jsonl.gz  # gzipped JSONL too (an ablation row's layouts)
    physcene check data/                                # a data synth folder: its JSONL, not its stats
    physcene check a.json b.json margin_cm=0.2          # configs/physics.yaml overrides

Every scene is scored in one engine call. Exit status 0 whatever the collisions; 2 when an input
cannot be read (it is named, on stderr and in the scene's ``error`` field with --json).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from physcene.commands import add_quiet, print_json
from physcene.layout import RECORD_FILES, layout_record_lines, load_layout, parse_json
from physcene.scene import Scene, SceneError

NAME = "check"
HELP = "Check layouts for interpenetration, floating objects and table penetration"
SETTINGS = "configs/physics.yaml (docs/physics.md)"

# Scenes per engine call: bounds device memory for very large datasets.
_CHUNK = 4096


class CheckInputError(ValueError):
    """A path given to ``physcene check`` does not exist or is not a layout source."""


@dataclass
class _Item:
    path: str
    scene: Scene | None = None
    error: str | None = None


def add_arguments(parser) -> None:
    parser.add_argument("paths", nargs="+", metavar="PATH",
                        help="layout.json files, directories (searched recursively) or JSONL files "
                             "(.jsonl or .jsonl.gz) whose records carry a 'layout' object")
    parser.add_argument("--device", default="cpu", help="engine device: cpu (default), cuda, cuda:N")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    add_quiet(parser)


def _error(path, exc: Exception) -> str:
    """The message of ``exc``, naming ``path`` once (a SceneError from a file already names it)."""
    return str(exc) if isinstance(exc, SceneError) and exc.source else f"{path}: {exc}"


def _load_json_file(path: Path, data=None) -> _Item:
    """The layout in the JSON file ``path`` (``data``: its content, when already parsed)."""
    try:
        if data is None:
            data = parse_json(path.read_text(encoding="utf-8"), source=str(path))
        return _Item(str(path), scene=load_layout(data, source=str(path), bounded=True))
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        return _Item(str(path), error=_error(path, exc))


def _load_jsonl(path: Path) -> list[_Item]:
    try:
        lines = layout_record_lines(path)
    except (OSError, UnicodeDecodeError, EOFError) as exc:
        return [_Item(str(path), error=f"{path}: {exc}")]
    items = []
    for number, line in lines:
        where = f"{path}:{number}"
        try:
            record = parse_json(line, source=where)
            layout = record.get("layout") if isinstance(record, dict) else None
            if isinstance(layout, str):
                layout = parse_json(layout, source=where)
            if layout is None and isinstance(record, dict) and record.get("parse_error"):
                raise ValueError(f"the completion did not parse: {record['parse_error']}")
            if not isinstance(layout, dict):
                raise SceneError("the record has no 'layout' object", source=where)
            items.append(_Item(where, scene=load_layout(layout, source=where, bounded=True)))
        except (ValueError, KeyError, TypeError) as exc:
            items.append(_Item(where, error=_error(where, exc)))
    return items


def _is_layout(data) -> bool:
    """Whether parsed JSON is meant as a layout (a folder also holds stats and reports)."""
    return isinstance(data, dict) and ("item_placement_zone" in data or "objects" in data)


def _collect_dir(path: Path) -> list[_Item]:
    """The layouts under a folder: ``layout.json`` / ``*.layout.json`` files (MesaTask trees) and
    JSONL datasets (``physcene data synth``); where there are none of those, every ``*.json`` that
    holds a layout (eval's ``layouts/<method>/<id>.json``), other JSON (stats, reports) skipped."""
    files = sorted(p for p in path.rglob("*.json") if p.is_file())
    named = [p for p in files if p.name == "layout.json" or p.name.endswith(".layout.json")]
    datasets = sorted(p for p in path.rglob("*.jsonl*") if p.is_file() and p.name.endswith(RECORD_FILES))
    items = [_load_json_file(p) for p in named]
    for p in datasets:
        items.extend(_load_jsonl(p))
    if not items:
        for p in files:
            try:
                data = parse_json(p.read_text(encoding="utf-8"), source=str(p))
            except (OSError, UnicodeDecodeError, ValueError) as exc:
                items.append(_Item(str(p), error=_error(p, exc)))
                continue
            if _is_layout(data):
                items.append(_load_json_file(p, data))
    if not items:
        items.append(_Item(str(path), error=f"{path}: no layouts under this directory (layout.json, "
                                            "*.layout.json, *.jsonl datasets or .json layouts)"))
    return items


def collect(paths) -> list[_Item]:
    """Every layout named by ``paths`` (files, trees, JSONL), unreadable ones as error items."""
    items: list[_Item] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            items.extend(_collect_dir(path))
        elif path.name.endswith(RECORD_FILES):
            missing = [_Item(str(path), error=f"{path}: no such file")]
            items.extend(_load_jsonl(path) if path.is_file() else missing)
        elif path.is_file():
            items.append(_load_json_file(path))
        else:
            items.append(_Item(str(path), error=f"{path}: no such file or directory"))
    return items


def check_scenes(items: list[_Item], engine, progress: bool = False) -> list[dict]:
    """The ``scenes`` entries of the JSON report, in input order; ``progress``: a bar on stderr
    over the scenes, when there is more than one engine call."""
    ok = [k for k, it in enumerate(items) if it.scene is not None and it.scene.objects]
    # a scene without objects has nothing to collide or float: no engine call
    reports: dict[int, dict] = {
        k: {"path": it.path, "objects": 0, "pairs": [], "max_depth_cm": 0.0, "energy": 0.0, "floating": [],
            "table_penetration_cm": 0.0, "error": None}
        for k, it in enumerate(items) if it.scene is not None and not it.scene.objects}
    bar = tqdm(total=len(ok), desc="check", unit="scene", file=sys.stderr,
               disable=not progress or len(ok) <= _CHUNK)
    for lo in range(0, len(ok), _CHUNK):
        chunk = ok[lo:lo + _CHUNK]
        scenes = [items[k].scene for k in chunk]
        score = engine.score(scenes)
        energy = score.energy.cpu().tolist()
        depth = score.max_depth.cpu().tolist()
        table = score.table_penetration.cpu().tolist()
        for m, k in enumerate(chunk):
            ids = scenes[m].ids()
            reports[k] = {
                "path": items[k].path, "objects": len(ids),
                "pairs": [{"a": ids[i], "b": ids[j], "depth_cm": d} for i, j, d in score.pairs[m]],
                "max_depth_cm": depth[m], "energy": energy[m],
                "floating": [ids[i] for i in score.floating[m]],
                "table_penetration_cm": table[m], "error": None,
            }
        bar.update(len(chunk))
    bar.close()
    return [reports.get(k) or {"path": it.path, "objects": None, "pairs": [], "max_depth_cm": None,
                               "energy": None, "floating": [], "table_penetration_cm": None,
                               "error": it.error}
            for k, it in enumerate(items)]


def _line(report: dict) -> str:
    if report["error"]:
        return f"{report['path']}: ERROR {report['error']}"
    pairs = ", ".join(f"{p['a']}~{p['b']} {p['depth_cm']:.2f} cm" for p in report["pairs"]) or "none"
    floating = ", ".join(report["floating"]) or "none"
    return (f"{report['path']}: {report['objects']} objects, max depth {report['max_depth_cm']:.2f} cm, "
            f"energy {report['energy']:.2f}, table {report['table_penetration_cm']:.2f} cm; "
            f"penetrating pairs: {pairs}; floating: {floating}")


def run(args) -> int:
    from physcene.physics import PhysicsConfig, PhysicsEngine

    config = PhysicsConfig.load(args.overrides)
    items = collect(args.paths)
    needed = any(it.scene is not None and it.scene.objects for it in items)
    engine = PhysicsEngine(device=args.device, config=config) if needed else None
    reports = check_scenes(items, engine, progress=not args.quiet)
    if args.json:
        print_json({"scenes": reports})
    else:
        for report in reports:
            if not report["error"]:  # errors are printed once, on stderr
                print(_line(report))
    errors = [r["error"] for r in reports if r["error"]]
    for message in errors:
        print(f"physcene check: error: {message}", file=sys.stderr)
    return 2 if errors else 0
