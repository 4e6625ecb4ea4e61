"""``physcene data``: build the benchmark (synthetic splits, or MesaTask-CTRC from real layouts).

    physcene data synth --out DIR [--split train|test|ood] [--n N] [--seed S] [key=value ...]
    physcene data import-mesatask LAYOUT_INFO_DIR --out DIR [--seed S]
    physcene data measure RECORDS.jsonl[.gz] --out OUT.jsonl[.gz] [--device D] [--batch-size B]

``key=value`` overrides go to ``configs/data.yaml`` (e.g. ``noise.pair_rate=0.3``,
``record.workers=4``). Each run writes ``<split>.jsonl``, ``<split>_stats.json`` and
``<split>_stats.md`` in DIR, all three renamed into place once complete (an interrupted run leaves
the previous files or none; the same command writes them again, byte for byte).

``measure`` scores each record's layout with the physics engine and writes the records again with
``reference_physics``: ``{"collision_free": bool, "deepest_cm": float}`` (its deepest penetrating
pair, 0 when collision-free), what a physics-conditioned SFT (``model.physics_conditioned``) reads.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from physcene.commands import add_json, add_quiet, print_json
from physcene.config import load_config
from physcene.data.benchmark import DataConfig, split_files, split_stats, write_split
from physcene.data.instructions import EndpointInstructor
from physcene.data.mesatask_ctrc import dumps_record, import_layout_tree
from physcene.data.splits import select_test
from physcene.eval.metrics import measure_reference
from physcene.files import write_atomic_many

NAME = "data"
HELP = "Build benchmark data: synthetic MesaTask-style splits or MesaTask-CTRC from real layouts"
SETTINGS = "configs/data.yaml (docs/data.md)"


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="data_command", metavar="ACTION")
    sub.required = True
    synth = sub.add_parser("synth", help="Generate a synthetic split (JSONL + stats)")
    synth.add_argument("--out", required=True, help="Output folder")
    synth.add_argument(
        "--split", default="test", choices=["train", "test", "ood"], help="Which split (default: test)"
    )
    synth.add_argument(
        "--n", type=int, default=None, help="Number of scenes (default: train 9429, test 866, ood 200)"
    )
    synth.add_argument("--seed", type=int, default=0, help="Seed (same seed -> byte-identical files)")
    synth.add_argument("--workers", type=int, default=None, help="Worker processes (default: config)")
    synth.add_argument(
        "--measure",
        choices=["auto", "yes", "no"],
        default=None,
        help="Score every scene with the engine for the reference SCR/ACR (auto: test and ood only)",
    )
    add_quiet(synth, legacy=("--no-progress",))
    add_json(synth, "the files written and the split's stats")
    imp = sub.add_parser(
        "import-mesatask", help="Build MesaTask-CTRC records from a MesaTask-10k Layout_info tree"
    )
    imp.add_argument("layout_info", help="Layout_info folder (or the MesaTask-10K folder containing it)")
    imp.add_argument("--out", required=True, help="Output folder")
    imp.add_argument("--seed", type=int, default=0, help="Seed of the instruction grammar and the split")
    imp.add_argument(
        "--test-size",
        type=int,
        default=866,
        help="Scenes held out as test, stratified like Table 5 where the data allows (0: none)",
    )
    imp.add_argument("--skip-errors", action="store_true", help="Skip unreadable layout files")
    imp.add_argument("--measure", action="store_true", help="Measure the reference SCR/ACR with the engine")
    add_quiet(imp)
    add_json(imp, "the files written")
    meas = sub.add_parser("measure", help="Records again with their measured physics (reference_physics)")
    meas.add_argument("records", help="A JSONL (.gz) of records with a 'layout' (synth, import-mesatask)")
    meas.add_argument("--out", required=True, help="The records again, with reference_physics (.gz: gzipped)")
    meas.add_argument("--device", default=None, help="The engine's device (default: cuda when there is one)")
    meas.add_argument("--batch-size", type=int, default=256, help="Scenes scored at once (default: 256)")
    add_quiet(meas)


def _config(args):
    config = DataConfig.load(args.overrides)
    if getattr(args, "workers", None):
        config = replace(config, workers=int(args.workers))
    return config


def _instructor(args):
    endpoint = load_config("data", args.overrides).record.endpoint
    if endpoint.base_url and endpoint.model:
        return EndpointInstructor(
            base_url=str(endpoint.base_url), model=str(endpoint.model), api_key_env=str(endpoint.api_key_env)
        )
    return None


def _run_synth(args) -> int:
    if args.n is not None and args.n < 1:
        raise ValueError(f"--n must be at least 1, got {args.n}")
    config = _config(args)
    measure = None if args.measure in (None, "auto") else args.measure == "yes"
    if args.measure == "auto":
        measure = args.split in ("test", "ood")
    stats = write_split(
        args.out, args.split, args.n, args.seed, config, progress=not args.quiet, measure=measure,
        measurer=measure_reference,
    )
    out = Path(args.out)
    if args.json:
        print_json({"file": out / f"{args.split}.jsonl", "stats_json": out / f"{args.split}_stats.json",
                    "stats_md": out / f"{args.split}_stats.md", "stats": stats})
        return 0
    print(
        f"wrote {out / (args.split + '.jsonl')} ({stats['n']} scenes, "
        f"{stats['distinct_instructions']} distinct instructions) in {stats['generation_seconds']:.1f} s"
    )
    ref = stats.get("reference")
    if ref:
        c = ref["collision"]["0cm"]
        print(f"reference: SCR(0cm) {100 * c['SCR']:.1f} %  ACR(0cm) {100 * c['ACR']:.2f} %")
    print(f"stats: {out / (args.split + '_stats.md')}")
    return 0


def _run_import(args) -> int:
    root = Path(args.layout_info)
    if not root.is_dir():
        raise FileNotFoundError(f"{str(root)!r} is not a directory (expected MesaTask's Layout_info)")
    config = _config(args)
    records = [
        r
        for _, r in tqdm(
            import_layout_tree(
                root,
                seed=args.seed,
                instructor=_instructor(args),
                prompt_objects=config.prompt_objects,
                decimals=config.decimals,
                skip_errors=args.skip_errors,
            ),
            desc="import",
            unit="scene",
            file=sys.stderr,
            disable=args.quiet,
        )
    ]
    if not records:
        raise ValueError(
            f"no layout.json files under {str(root)!r} (expected <table_type>/<scene>/layout.json)"
        )
    test_idx = set(select_test([(r["scene_type"], r["level"]) for r in records], args.test_size, args.seed))
    out = Path(args.out)
    written = []
    for split, chosen in (
        ("train", [r for k, r in enumerate(records) if k not in test_idx]),
        ("test", [r for k, r in enumerate(records) if k in test_idx]),
    ):
        for r in chosen:
            r["split"] = split
        stats = split_stats(chosen, measurer=measure_reference if args.measure and chosen else None)
        stats.update(split=split, seed=args.seed, file=f"{split}.jsonl", source=str(root))
        write_atomic_many(split_files(out, split, [dumps_record(r) for r in chosen], stats))
        written.append({"split": split, "file": out / f"{split}.jsonl", "n": len(chosen),
                        "stats_json": out / f"{split}_stats.json", "stats_md": out / f"{split}_stats.md"})
        if not args.json:
            print(f"wrote {out / (split + '.jsonl')} ({len(chosen)} scenes)")
    if args.json:
        print_json({"splits": written})
    return 0


def _run_measure(args) -> int:
    from physcene.eval.metrics import deepest_pairs
    from physcene.layout import json_records, load_layout, write_layout_records
    from physcene.physics import PhysicsEngine  # here: Warp loads after the arguments are checked

    src, out = Path(args.records), Path(args.out)
    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be at least 1, got {args.batch_size}")
    if out.resolve() == src.resolve():
        raise ValueError(f"--out {out} is the records file itself: write the measured records elsewhere")
    records, scenes = [], []
    for number, rec in json_records(src):
        if not isinstance(rec, dict) or not isinstance(rec.get("layout"), dict):
            raise ValueError(f"{src}:{number}: a record needs a 'layout' object to measure")
        scenes.append(load_layout(rec["layout"], source=f"{src}:{number}"))
        records.append(rec)
    engine = PhysicsEngine(**({"device": args.device} if args.device else {}))
    depths = deepest_pairs(scenes, engine, batch_size=args.batch_size, progress=not args.quiet)
    for rec, depth in zip(records, depths):
        rec["reference_physics"] = {"collision_free": depth == 0.0, "deepest_cm": round(float(depth), 4)}
    write_layout_records(records, out)
    free = sum(d == 0.0 for d in depths)
    print(f"wrote {out}: {len(records)} records, {free} collision-free "
          f"({100 * free / max(len(records), 1):.1f} %)")
    return 0


def run(args) -> int:
    if args.data_command == "synth":
        return _run_synth(args)
    if args.data_command == "measure":
        return _run_measure(args)
    return _run_import(args)
