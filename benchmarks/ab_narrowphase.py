"""Narrowphase variants timed interleaved on one batch: robust medians on a noisy, shared machine.

    python benchmarks/ab_narrowphase.py --device cpu --scenes 256 --objects 12 --points 256 \
        --variants buckets/16 buckets/1 worklist/1 worklist/4 --rounds 12
    python benchmarks/ab_narrowphase.py --device cuda --scenes 512 --objects 16 --points 1024 \
        --variants buckets/32 worklist/16 worklist/32 worklist/32/graph --rounds 20
    python benchmarks/ab_narrowphase.py --scenes 1 --objects 3 --points 64 \
        --variants worklist/1 worklist/1/graph

``physcene bench reward --narrowphase ... --lanes ...`` times each variant in one block of calls;
here every round calls each variant once (forward, then forward + gradient), so load that
changes during the run hits all variants alike. Times: wall (device synchronised) and, on the
CPU, process CPU time; medians over the rounds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace

import torch
from narrowphase_buckets import BucketsEngine

from physcene.assets import AssetLibrary
from physcene.commands.bench import bench_scenes
from physcene.physics import PhysicsConfig, PhysicsEngine


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", type=int, default=256)
    parser.add_argument("--objects", type=int, default=12)
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=12)
    parser.add_argument("--variants", nargs="+", default=["buckets/16", "worklist/1"],
                        help="NARROWPHASE/LANES[/graph], e.g. worklist/32 worklist/32/graph")
    args = parser.parse_args()
    device = torch.device(args.device)
    library = AssetLibrary(n_points=args.points)
    library.add_primitives()
    scenes = bench_scenes(args.scenes, args.objects)
    # the engine's work list and the buckets variant that lost to it (benchmarks/narrowphase_buckets.py)
    engines = {"worklist": PhysicsEngine(library, device), "buckets": BucketsEngine(library, device)}
    batches = {name: engine.pack(scenes) for name, engine in engines.items()}
    key = "lanes_cuda" if device.type == "cuda" else "lanes_cpu"
    base = PhysicsConfig.load()
    variants = {}
    for v in args.variants:
        name, lanes, *graph = v.split("/")
        if graph not in ([], ["graph"]):
            raise SystemExit(f"variant {v!r}: expected NARROWPHASE/LANES or NARROWPHASE/LANES/graph")
        if name not in engines:
            raise SystemExit(f"variant {v!r}: narrowphase {name!r} is one of {', '.join(engines)}")
        variants[v] = (name, replace(base, graph=bool(graph), **{key: int(lanes)}))

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    times = {(v, g): ([], []) for v in variants for g in (False, True)}
    for name, config in variants.values():  # JIT and warm-up (a graph variant captures on its second call)
        engine, batch = engines[name], batches[name]
        engine.config = config
        for _ in range(3):
            for grad in (False, True):
                engine.evaluate(batch, with_grad=grad)
    for _ in range(args.rounds):
        for v, (name, config) in variants.items():
            engine, batch = engines[name], batches[name]
            engine.config = config
            for grad in (False, True):
                sync()
                t0, c0 = time.perf_counter(), time.process_time()
                engine.evaluate(batch, with_grad=grad)
                sync()
                times[(v, grad)][0].append(time.perf_counter() - t0)
                times[(v, grad)][1].append(time.process_time() - c0)
    report = {v: {("forward+grad" if g else "forward"): {"wall_ms": statistics.median(w) * 1e3,
                                                          "cpu_ms": statistics.median(c) * 1e3}
                  for (u, g), (w, c) in times.items() if u == v} for v in variants}
    print(json.dumps({"device": str(device), "scenes": args.scenes, "objects": args.objects,
                      "points": args.points, "rounds": args.rounds, "variants": report}, indent=1))


if __name__ == "__main__":
    main()
