"""``physcene assets``: bake the asset library into the cache, or list it.

    physcene assets list [--json]                      category, asset id, source of every asset
    physcene assets bake [--device cuda:0] [--category mug ...] [--folder DIR ...]
    physcene assets list --folder /data/MesaTask/Assets_library resolution=32

``key=value`` overrides go to ``configs/assets.yaml`` (resolution, n_points, cache_dir, ...).
"""

from __future__ import annotations

import json
import sys
import time

from physcene.assets.cache import BakeCache
from physcene.assets.library import AssetLibrary
from physcene.commands import add_quiet
from physcene.config import load_config

NAME = "assets"
HELP = "bake the asset library's SDF grids into the cache, or list the library"
SETTINGS = "configs/assets.yaml (docs/assets.md)"


def add_arguments(parser) -> None:
    parser.add_argument("action", choices=("bake", "list"), help="what to do")
    parser.add_argument(
        "--device", default=None, help="Warp device for bakes: cpu or cuda:N (default: config)"
    )
    parser.add_argument(
        "--folder", action="append", default=[], help="also a folder of GLB/OBJ meshes (repeatable)"
    )
    parser.add_argument("--category", action="append", default=[], help="only these categories (repeatable)")
    parser.add_argument("--json", action="store_true", help="list: print JSON [{category, asset_id, source}]")
    add_quiet(parser)


def build_library(args) -> AssetLibrary:
    cfg = load_config("assets", args.overrides)
    library = AssetLibrary(
        resolution=int(cfg.resolution),
        n_points=int(cfg.n_points),
        seed=int(cfg.seed),
        device=args.device or str(cfg.device),
        cache=BakeCache(cfg.cache_dir or None),
        edge_angle_deg=float(cfg.edge_angle_deg),
    )
    library.add_primitives()
    library.add_procedural()
    for folder in [*(cfg.folders or []), *args.folder]:
        library.add_folder(folder)
    return library


def run(args) -> int:
    library = build_library(args)
    entries = library.entries()
    if args.category:
        unknown = sorted(set(args.category) - set(library.categories()))
        if unknown:
            raise ValueError(f"unknown categories {unknown}; see `physcene assets list`")
        entries = [e for e in entries if e.category in args.category]
    if args.action == "list":
        rows = [{"category": e.category, "asset_id": e.asset_id, "source": e.source} for e in entries]
        if args.json:
            print(json.dumps(rows, indent=1))
        else:
            for r in rows:
                print(f"{r['category']:20s} {r['asset_id']:32s} {r['source']}")
        return 0
    total = time.perf_counter()
    for e in entries:
        start = time.perf_counter()
        asset = library.get(e.asset_id)
        if not args.quiet:  # one progress line per asset
            print(f"{e.asset_id:32s} R={asset.resolution} P={len(asset.points)} "
                  f"{time.perf_counter() - start:.3f}s", file=sys.stderr)
    print(
        f"{len(entries)} assets ready in {time.perf_counter() - total:.1f} s; cache: "
        f"{library.cache.root if library.cache else 'off'}"
    )
    return 0
