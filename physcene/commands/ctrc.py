"""``physcene ctrc``: MesaTask layout.json ⇄ CTRC completion text.

    physcene ctrc LAYOUT.json                 # print the CTRC completion (plan + layered JSON)
    physcene ctrc LAYOUT.json --prompt        # print the generation prompt for that layout
    physcene ctrc --decode COMPLETION.txt     # print the absolute layout as MesaTask layout.json
    physcene ctrc LAYOUT.json on_gap_cm=0.5   # graph thresholds (configs/graph.yaml) as overrides

A broken input exits with status 2 and one line naming the file, the object and the field;
nothing is printed to stdout and no ``--output`` file is written.
"""

from __future__ import annotations

import sys
from pathlib import Path

from physcene.ctrc import ParseError, build_prompt, completion_text, parse
from physcene.graph import GraphConfig, build_hierarchy
from physcene.layout import dumps_layout, load_layout, parse_json, read_layout, write_layout
from physcene.scene import SceneError, Zone

NAME = "ctrc"
HELP = "Print the CTRC completion of a MesaTask layout.json, or (--decode) parse a completion to layout.json"
SETTINGS = "configs/graph.yaml (docs/scene_language.md)"


class CompletionError(ValueError):
    """A completion file that does not parse; the message names the file and the reason."""


def add_arguments(parser) -> None:
    parser.add_argument("input", help="a MesaTask layout.json, or with --decode a completion text file "
                                      "('-' reads stdin)")
    parser.add_argument("--decode", action="store_true",
                        help="parse a CTRC (or Prompt-3 flat JSON) completion and print layout.json")
    parser.add_argument("--zone", metavar="XMIN,XMAX,YMIN,YMAX",
                        help="with --decode: the task's item_placement_zone in cm "
                             "(overrides the completion's)")
    parser.add_argument("--prompt", action="store_true",
                        help="print the CTRC generation prompt for the layout instead of its completion")
    parser.add_argument("-o", "--output", metavar="PATH", help="write to PATH (atomically) instead of stdout")


def _read_text(name: str) -> str:
    if name == "-":
        return sys.stdin.read()
    path = Path(name)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise CompletionError(f"{name}: not UTF-8 text ({exc.reason})") from None


def _zone(text: str | None) -> Zone | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise SceneError(f"expected four comma-separated numbers, got {text!r}", field="--zone") from None
    return Zone.from_list(values, field="--zone")


def _one_line(message: str) -> str:
    return " ".join(message.split())


def run(args) -> int:
    if args.decode:
        zone = _zone(args.zone)
        result = parse(_read_text(args.input), zone=zone)
        if isinstance(result, ParseError):
            raise CompletionError(_one_line(f"{args.input}: {result.reason}"))
        if args.output:
            write_layout(result, args.output)
            return 0
        sys.stdout.write(dumps_layout(result))
        return 0

    graph_config = GraphConfig.load(args.overrides)  # checked even when unused
    source = "<stdin>" if args.input == "-" else args.input
    if args.input == "-":
        scene = load_layout(parse_json(sys.stdin.read(), source=source, allow_nan=False), source=source,
                            bounded=True)
    else:
        scene = read_layout(args.input, bounded=True)
    if args.prompt:
        text = build_prompt(scene.instruction, scene.scene_type, scene.zone, scene.objects,
                            restricted_zones=scene.restricted_zones) + "\n"
    else:
        if not scene.has_hierarchy:
            scene = build_hierarchy(scene, graph_config)
        text = completion_text(scene)
    if args.output:
        out = Path(args.output)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(out)
    else:
        sys.stdout.write(text)
    return 0
