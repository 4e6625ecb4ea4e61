"""The engine of several checkouts side by side in one run: one worker process per tree, calls
interleaved round by round, the ratio of each pair's times per round (median) — noise of a shared
machine hits every tree alike.

    git worktree add /tmp/before <commit>
    python benchmarks/ab_engine.py --device cuda --scenes 512 before=/tmp/before after=.

Each worker imports physcene from its tree (PYTHONPATH), packs ``bench_scenes(scenes, 16)`` and
times ``evaluate`` (forward) and ``evaluate(with_grad=True)``, ``--reps`` calls per figure. Prints
one JSON object: per tree the median ms, per consecutive pair of trees the median ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def worker(device: str, n_scene: int, reps: int) -> None:
    import torch

    from physcene.physics import PhysicsEngine

    try:
        from physcene.commands.bench.reward import bench_scenes
    except ImportError:  # a checkout from before the bench package
        from physcene.commands.bench import bench_scenes
    torch.set_num_threads(1)
    engine = PhysicsEngine(device=device)
    batch = engine.pack(bench_scenes(n_scene, 16, 0))
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    for _ in range(3):
        engine.evaluate(batch), engine.evaluate(batch, with_grad=True)
    sync()
    print("ready", flush=True)
    for line in sys.stdin:
        grad = line.strip() == "g"
        start = time.perf_counter()
        for _ in range(reps):
            engine.evaluate(batch, with_grad=grad)
        sync()
        print((time.perf_counter() - start) / reps, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trees", nargs="*", help="NAME=PATH of each checkout, in order")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", type=int, default=128)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        return worker(args.device, args.scenes, args.reps)
    if len(args.trees) < 2:
        parser.error("give at least two NAME=PATH trees")
    trees = dict(t.split("=", 1) for t in args.trees)
    workers = {}
    for name, path in trees.items():
        path = os.path.abspath(path)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([path, os.environ.get("PYTHONPATH", "")]),
                   OMP_NUM_THREADS="1")
        p = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--worker", "--device", args.device,
                              "--scenes", str(args.scenes), "--reps", str(args.reps)],
                             cwd=path, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL, text=True)
        while (line := p.stdout.readline()) and line.strip() != "ready":
            pass
        workers[name] = p
    times = {(n, k): [] for n in trees for k in "fg"}
    for r in range(args.rounds):
        order = list(trees) if r % 2 == 0 else list(reversed(list(trees)))
        for k in "fg":
            for n in order:
                workers[n].stdin.write(k + "\n")
                workers[n].stdin.flush()
                times[(n, k)].append(float(workers[n].stdout.readline()))
    names = list(trees)
    out = {"device": args.device, "scenes": args.scenes, "objects": 16, "rounds": args.rounds}
    for k, label in (("f", "forward"), ("g", "forward+grad")):
        for n in names:
            out[f"{n}_{label}_ms_median"] = 1e3 * statistics.median(times[(n, k)])
        for a, b in zip(names, names[1:]):
            out[f"{b}/{a}_{label}_ratio_median"] = statistics.median(
                y / x for x, y in zip(times[(a, k)], times[(b, k)]))
    print(json.dumps(out, indent=1))
    for p in workers.values():
        p.stdin.close()
        p.wait()


if __name__ == "__main__":
    main()
