"""``physcene view``: the scenes of a path in the browser (viser; the ``[view]`` extra).

    physcene view examples/office_table.layout.json            # http://127.0.0.1:8080
    physcene view data.jsonl --port 8081                        # a scene picker over the records
    physcene view physcene-eval/                                # eval results: one variant per method
    physcene view fixed/layout.json --before scene/layout.json  # repair output: before/after switch

Penetrating pairs are red with their depth written between them, floating objects orange; the
scene graph's in / on / near edges are toggled in the side panel (docs/view.md).
"""

from __future__ import annotations

import sys
import time

NAME = "view"
HELP = "Show layouts in the browser: meshes, penetrating pairs, floating objects, scene graph (viser)"


def add_arguments(parser) -> None:
    parser.add_argument("path", help="a layout.json, a JSONL dataset, a folder of layouts or an eval "
                                     "results folder (with layouts/)")
    parser.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1; 0.0.0.0 to share on the network)")
    parser.add_argument("--before", default=None, metavar="PATH",
                        help="the input of a repair: a before/after switch against PATH")
    parser.add_argument("--device", default="cpu", help="physics engine device (default cpu)")


def run(args) -> int:
    try:
        import viser  # noqa: F401  (the [view] extra: named before anything is loaded)
    except ImportError:
        print("physcene view: error: needs viser: pip install 'physcene[view]'", file=sys.stderr)
        return 2
    from physcene.physics import PhysicsEngine
    from physcene.view import SceneViewer, load_items

    items = load_items(args.path, before=args.before)
    viewer = SceneViewer(items, host=args.host, port=args.port, engine=PhysicsEngine(device=args.device))
    print(f"physcene view: {len(items)} scene(s) at http://{args.host}:{args.port}", flush=True)
    try:
        while True:
            time.sleep(3600)
    finally:
        viewer.stop()
