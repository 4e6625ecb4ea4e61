"""``physcene export``: a layout as a simulator-ready scene (metres).

    physcene export scene/layout.json --format mjcf -o out/      # out/scene.xml + out/meshes/*.obj
    physcene export scene/layout.json --format urdf -o out/      # out/scene.json + one URDF per object
    physcene export scene/layout.json --format glb -o out/       # out/scene.glb (with the table)
    physcene export scene/layout.json --format sceneeval -o out/ # out/scene_state.json + out/assets/*.glb
    physcene export scene/layout.json --format usd -o out/       # out/scene.usda (needs the [usd] extra)
    physcene export data.jsonl:3 --format all -o out/            # record 3 (1-based line): glb, mjcf, urdf

``key=value`` overrides go to ``configs/export.yaml`` (densities, decomposition, solver settings).
"""

from __future__ import annotations

from pathlib import Path

from physcene.commands import add_json, print_json
from physcene.export import FORMATS, SIMULATOR_FORMATS, ExportConfig, ExportError, export

NAME = "export"
HELP = ("Export a layout to GLB, MJCF (MuJoCo), URDF + scene.json (SAPIEN/ManiSkill), SceneEval's scene "
        "state or USD (Isaac Sim), in metres")
SETTINGS = "configs/export.yaml (docs/export.md)"


def add_arguments(parser) -> None:
    parser.add_argument("layout", help="a MesaTask layout.json, or FILE.jsonl:LINE for one record "
                                       "of a dataset")
    parser.add_argument("--format", dest="formats", required=True, choices=[*FORMATS, "all"],
                        action="append", help="output format (repeatable; 'all' for glb, mjcf and urdf)")
    parser.add_argument("-o", "--output", required=True, metavar="DIR", help="output folder")
    add_json(parser, "the files written")


def run(args) -> int:
    from physcene.commands.settle import read_inputs

    items = read_inputs([args.layout])
    if len(items) != 1:
        raise ExportError(f"{args.layout!r} holds {len(items)} layouts; export takes one "
                          "(name a JSONL record as FILE.jsonl:LINE)")
    (label, scene, error), = items
    if error is not None:
        raise ExportError(error)
    config = ExportConfig.load(args.overrides)
    formats = SIMULATOR_FORMATS if "all" in args.formats else tuple(dict.fromkeys(args.formats))
    out = Path(args.output)
    written = []
    for fmt in formats:
        # Each format in its own folder when several are asked for: their mesh files differ.
        path = export(scene, out / fmt if len(formats) > 1 else out, fmt, config=config)
        written.append({"format": fmt, "path": path})
        if not args.json:
            print(f"{label}: {fmt} -> {path}")
    if args.json:
        print_json({"layout": label, "outputs": written})
    return 0
