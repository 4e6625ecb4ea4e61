"""``physcene repair``: hierarchy-constrained test-time optimisation of layouts (physcene.tto).

    physcene repair scene/layout.json -o fixed/layout.json     # report: fixed/layout.report.json
    physcene repair scene/layout.json -o fixed/                # a folder: fixed/layout.json
    physcene repair Layout_info/ -o Fixed/                     # mirrors the tree; Fixed/repair_report.json
    physcene repair data.jsonl -o fixed.jsonl                  # field "layout" (and "completion",
                                                               # re-written); fixed.report.json
    physcene repair docs/results/ablation/s0/sft.jsonl.gz -o sft_tto.jsonl.gz   # a table row's layouts
                                                               # (gzipped; an unparsed output passes through)
    physcene repair IN -o OUT --device cuda steps=200 lambda_rel=10   # configs/tto.yaml overrides

The output mirrors the input's structure and format. The report holds, per scene, the penetration
energy before/after (cm), the deepest pair before/after, the largest displacement (cm), the
relations kept and what could not be satisfied.
"""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

from physcene.commands import add_json, add_quiet, print_json
from physcene.ctrc import MAX_DECIMALS, completion_text, decimals_of
from physcene.files import write_atomic
from physcene.layout import RECORD_FILES, layout_record_lines, layout_to_dict, load_layout, parse_json
from physcene.scene import SceneError
from physcene.tto import TTOConfig, repair, summarize

NAME = "repair"
HELP = "Repair layouts by hierarchy-constrained test-time optimisation (layout.json, a tree, or JSONL)"
SETTINGS = "configs/tto.yaml (docs/tto.md)"


class RepairInputError(ValueError):
    """The repair input or output path is unusable; the message names it."""


def add_arguments(parser) -> None:
    parser.add_argument("input", help="a MesaTask layout.json, a directory tree of layout.json files, "
                                      "or a JSONL dataset (.jsonl or .jsonl.gz) whose records carry a "
                                      "'layout' object")
    parser.add_argument("-o", "--output", required=True, metavar="OUT",
                        help="where the repaired layouts go (same structure and format as the input)")
    parser.add_argument("--device", default=None, help="torch device: cpu (default), cuda, cuda:N")
    parser.add_argument("--decimals", type=int, default=None,
                        help="JSONL: digits after the point of the re-written 'completion' column "
                             "(default: each record's own, read from its completion)")
    add_quiet(parser)
    add_json(parser, "the paths written, the summary and the per-scene reports")


def _read_json(path: Path) -> dict:
    try:
        return parse_json(path.read_text(encoding="utf-8"), source=str(path))
    except UnicodeDecodeError as exc:
        raise SceneError(f"not a JSON layout ({exc})", source=str(path)) from None


def _merged(raw: dict, scene) -> dict:
    """The input layout dict with the repaired poses; keys the scene model does not know are kept."""
    kept = {k: v for k, v in raw.items() if k != "sink_zone"}  # folded into restricted_zone
    return {**kept, **layout_to_dict(scene)}


def _repaired_columns(record: dict, raw: dict, scene, decimals: int | None) -> dict:
    """A JSONL record's columns that follow its layout: ``layout``, and the CTRC ``completion``
    (``physcene data`` records) written again from the repaired scene — at ``decimals``, or at the
    precision it had — so that a training set whose layouts were repaired teaches the new poses."""
    columns = {"layout": _merged(raw, scene)}
    completion = record.get("completion")
    if isinstance(completion, str):
        columns["completion"] = completion_text(
            scene, decimals=decimals_of(completion) if decimals is None else decimals)
    return columns


def _report_path(out: Path) -> Path:
    return out.with_name(out.name.removesuffix(".gz").rsplit(".", 1)[0] + ".report.json")


def _items_file(src: Path):
    raw = _read_json(src)
    return [(str(src.name), raw, load_layout(raw, source=str(src), bounded=True))]


def _items_tree(src: Path):
    items = []
    for path in sorted(src.rglob("layout.json")):
        rel = path.relative_to(src)
        parts = path.relative_to(src / "Layout_info" if (src / "Layout_info").is_dir() else src).parts
        scene_type = parts[-3].replace("_", " ") if len(parts) >= 3 else None
        raw = _read_json(path)
        items.append((str(rel), raw, load_layout(raw, source=str(path), scene_type=scene_type, bounded=True)))
    if not items:
        raise RepairInputError(f"no layout.json under {str(src)!r}")
    return items


def _items_jsonl(src: Path):
    """(record, layout dict, scene) per record; a table row's record of an output that did not parse
    (``layout`` null beside its ``parse_error``: ``physcene.train.ablation.layout_records``) has no
    layout and no scene, and passes through unrepaired. A gzipped file is a table row's layouts: its
    layouts load as ``physcene eval --generator file:`` loads them (a model's output as it was scored,
    sizes and positions unbounded), so its repair is the table's ``sft+tto`` of those layouts; a dataset
    (``.jsonl``) is held to the layout files' bounds."""
    bounded = not src.name.endswith(".gz")
    try:
        lines = layout_record_lines(src)
    except (OSError, UnicodeDecodeError, EOFError) as exc:  # a bad gzip stream is an OSError
        raise RepairInputError(f"{src}: cannot be read ({exc})") from None
    items = []
    for line_no, line in lines:
        where = f"{src}:{line_no}"
        record = parse_json(line, source=where)
        layout = record.get("layout") if isinstance(record, dict) else None
        if layout is None and isinstance(record, dict) and "parse_error" in record:
            items.append((record, None, None))
            continue
        if isinstance(layout, str):
            layout = parse_json(layout, source=f"{where} field 'layout'")
        if not isinstance(layout, dict):
            raise RepairInputError(f"{where}: expected a record with a 'layout' object")
        items.append((record, layout, load_layout(layout, source=where, bounded=bounded)))
    return items


def run(args) -> int:
    from physcene.physics import PhysicsEngine  # here: Warp loads only when the command runs

    src, out = Path(args.input), Path(args.output)
    if args.decimals is not None and not 0 <= args.decimals <= MAX_DECIMALS:
        raise RepairInputError(f"--decimals must be from 0 to {MAX_DECIMALS}, got {args.decimals}")
    if not src.exists():
        raise FileNotFoundError(f"repair input {str(src)!r} does not exist")
    overrides = list(args.overrides) + ([f"device={args.device}"] if args.device else [])
    config = TTOConfig.load(overrides)
    if src.is_dir():
        mode, items = "tree", _items_tree(src)
    elif src.name.endswith(RECORD_FILES):
        mode, items = "jsonl", _items_jsonl(src)
    else:
        mode, items = "file", _items_file(src)
    # -o names a folder when it is one or ends with a slash (newdir/): the output goes inside
    if mode != "tree" and (out.is_dir() or args.output.endswith(("/", os.sep))):
        out = out / src.name
    repaired = repair([scene for *_, scene in items if scene is not None], config,
                      PhysicsEngine(device=config.device), progress=not args.quiet)
    order = iter(repaired)
    results = [None if scene is None else next(order) for *_, scene in items]  # aligned with items
    reports = []
    if mode == "tree":
        for (rel, raw, _), result in zip(items, results):
            path = out / rel
            _write_json(path, _merged(raw, result.scene))
            reports.append({"layout": rel, **result.report.as_dict()})
        report_path = out / "repair_report.json"
    elif mode == "jsonl":
        lines = []
        for k, ((record, raw, _), result) in enumerate(zip(items, results)):
            if result is None:  # an output that did not parse: as it was
                lines.append(json.dumps(record, ensure_ascii=False))
                reports.append({"record": k, "id": record.get("id"), "skipped": "no layout (parse_error)"})
                continue
            columns = _repaired_columns(record, raw, result.scene, args.decimals)
            lines.append(json.dumps({**record, **columns}, ensure_ascii=False))
            reports.append({"record": k, "id": record.get("id"), **result.report.as_dict()})
        text = "\n".join(lines) + ("\n" if lines else "")
        # gzipped when the name ends in .gz, byte-identical for the same records (no timestamp)
        _write_text(out, gzip.compress(text.encode(), mtime=0) if out.name.endswith(".gz") else text)
        report_path = _report_path(out)
    else:
        (_, raw, _), result = items[0], results[0]
        _write_json(out, _merged(raw, result.scene))
        reports.append({"layout": str(src), **result.report.as_dict()})
        report_path = _report_path(out)
    _write_text(report_path, json.dumps(reports, indent=1, ensure_ascii=False) + "\n")
    if args.json:
        print_json({"input": src, "output": out, "report": report_path,
                    "summary": summarize(repaired),
                    "collision_depth_cm": config.collision_depth_cm, "scenes": reports})
    else:
        print(_summary(repaired, config), f"report: {report_path}")
    return 0


def _summary(results, config) -> str:
    s = summarize(results)
    return (f"repaired {s['scenes']} scene(s): {s['collision_free']:.1%} without a pair deeper than "
            f"{config.collision_depth_cm} cm (every pair), in/on kept {s['in_on_kept']:.1%}, "
            f"near kept {s['near_kept']:.1%}, median max displacement "
            f"{s['median_max_displacement_cm']:.2f} cm;")


def _write_json(path: Path, data) -> None:
    _write_text(path, json.dumps(data, indent=2, ensure_ascii=False, allow_nan=False) + "\n")


def _write_text(path: Path, text: str | bytes) -> None:
    """Atomic write (:func:`physcene.files.write_atomic`): an interrupted repair leaves no half file."""
    write_atomic(path, text)
