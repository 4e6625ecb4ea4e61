"""Where the time of one engine call goes: GPU kernel time vs host (launch) overhead.

    python benchmarks/profile_engine.py --device cuda --scenes 512 --objects 16
    python benchmarks/profile_engine.py --narrowphase buckets worklist --lanes 8 16 32 64
    python benchmarks/profile_engine.py --narrowphase worklist --lanes 32 --graph off on
    python benchmarks/profile_engine.py --narrowphase worklist --lanes 16 32 --block-dim 64 128 256

Runs ``PhysicsEngine.evaluate`` (forward, and forward + gradient) on the bench scenes of
``physcene bench reward`` under ``torch.profiler`` and prints, per Warp kernel, the summed device
time, next to the wall time of the whole call. Wall minus kernel time is what CUDA graphs or
fewer launches could save.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from itertools import product

import torch
from narrowphase_buckets import BucketsEngine
from torch.profiler import ProfilerActivity, profile

from physcene.assets import AssetLibrary
from physcene.commands.bench import bench_scenes
from physcene.physics import PhysicsEngine


def kernel_times(fn, repeat: int) -> dict[str, float]:
    """Mean device milliseconds per call of each CUDA kernel that ``fn`` launches."""
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(repeat):
            fn()
        torch.cuda.synchronize()
    times: dict[str, float] = {}
    for event in prof.key_averages():
        device_us = getattr(event, "device_time_total", 0.0) or getattr(event, "cuda_time_total", 0.0)
        if device_us > 0:
            times[event.key[:60]] = device_us / 1000.0 / repeat
    return times


def wall_ms(fn, repeat: int) -> float:
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    torch.cuda.synchronize()
    return (time.perf_counter() - t0) * 1000.0 / repeat


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--scenes", type=int, default=512)
    parser.add_argument("--objects", type=int, default=16)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--repeat", type=int, default=50)
    parser.add_argument("--lanes", type=int, nargs="+", default=[16, 32, 64, 128],
                        help="narrowphase threads per (pair, direction) to compare")
    parser.add_argument("--narrowphase", nargs="+", default=["buckets", "worklist"],
                        choices=("buckets", "worklist"),
                        help="the engine's work list and/or the variant of benchmarks/narrowphase_buckets.py")
    parser.add_argument("--block-dim", type=int, nargs="+", default=[256],
                        help="CUDA threads per narrowphase block (physics.yaml: narrowphase_block_dim)")
    parser.add_argument("--graph", nargs="+", choices=("off", "on"), default=["off"],
                        help="without and/or with the captured launch graph (configs/physics.yaml: graph)")
    args = parser.parse_args()
    library = AssetLibrary(n_points=args.points)
    library.add_primitives()
    scenes = bench_scenes(args.scenes, args.objects)
    # the engine's work list and the buckets variant that lost to it (benchmarks/narrowphase_buckets.py)
    engines = {"worklist": PhysicsEngine(library, args.device),
               "buckets": BucketsEngine(library, args.device)}
    batches = {name: engines[name].pack(scenes) for name in args.narrowphase}
    report = {}
    sweep = product(args.narrowphase, args.lanes, args.block_dim, args.graph)
    for narrowphase, lanes, block_dim, graph in sweep:
        engine, batch = engines[narrowphase], batches[narrowphase]
        engine.config = replace(engine.config, lanes_cuda=lanes, lanes_cpu=lanes, graph=graph == "on",
                                narrowphase_block_dim=block_dim)
        for name, grad in (("forward", False), ("forward+grad", True)):
            fn = lambda grad=grad, engine=engine, batch=batch: engine.evaluate(batch, with_grad=grad)  # noqa: E731
            for _ in range(3):
                fn()
            kernels = kernel_times(fn, args.repeat)
            label = f"{narrowphase} lanes={lanes} block_dim={block_dim}{' graph' if graph == 'on' else ''}"
            report[f"{label} {name}"] = {
                "wall_ms": wall_ms(fn, args.repeat), "kernel_ms_total": sum(kernels.values()),
                "kernels_ms": dict(sorted(kernels.items(), key=lambda kv: -kv[1]))}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
