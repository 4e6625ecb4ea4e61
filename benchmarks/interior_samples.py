"""How many interior samples per asset: accuracy against the analytic sweep vs the engine's cost.

For each lattice size N (``PhysicsConfig.interior_per_axis``; 0 = surface samples only) the script
reads equal cubes, spheres and cylinders offset 0 ... 10 cm at five yaws (the sweep of
tests/physics/test_sound_penetration.py), without the depth cap, and reports the least reading
over ``min(overlap, half extent)`` in the deep half of the sweep (overlap ≥ half the extent: where
only interior samples can read it) and how often the reading falls as the overlap grows; then the
forward and forward + gradient time of 128 random scenes × 16 objects, the lattice sizes
interleaved in one process (docs/physics.md, "Sound penetration").

    python benchmarks/interior_samples.py --json
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch

from physcene.commands.bench.reward import bench_scenes
from physcene.physics import PhysicsConfig, PhysicsEngine
from physcene.scene import Scene, SceneObject, Zone

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "physics"))
from test_physics import PrimitiveLibrary  # noqa: E402  (the exact primitives of the tests)

ZONE = Zone(-100.0, 100.0, -100.0, 100.0)


def sweep(engine: PhysicsEngine) -> dict:
    worst, falls = math.inf, 0
    for kind in ("box", "sphere", "cylinder"):
        for yaw_deg in (0, 20, 45, 70, 135):
            yaw = math.radians(yaw_deg)
            previous = -1.0
            for k in range(41):
                overlap = k / 4
                gap = 10.0 - overlap
                objects = (SceneObject("a", kind, (0.0, 0.0, 5.0), (10.0, 10.0, 10.0), yaw),
                           SceneObject("b", kind, (gap * math.cos(yaw), gap * math.sin(yaw), 5.0),
                                       (10.0, 10.0, 10.0), yaw))
                pairs = engine.score([Scene(ZONE, objects)]).pairs[0]
                reading = max((d for _, _, d in pairs), default=0.0)
                if overlap >= 5.0:
                    worst = min(worst, reading / min(overlap, 5.0))
                falls += reading < previous - 1e-5
                previous = reading
    return {"deep_reading_over_bound_min": worst, "readings_that_fall": falls}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[0, 5, 7, 9])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    result = {"device": "cpu", "sizes": {}}
    engines = {}
    for n in args.sizes:
        engines[n] = PhysicsEngine(config=PhysicsConfig(interior_per_axis=n))
        uncapped = PhysicsConfig(interior_per_axis=n, depth_cap_ratio=0.0)
        exact = PhysicsEngine(PrimitiveLibrary(), config=uncapped)
        result["sizes"][n] = sweep(exact)
    batch = {n: e.pack(bench_scenes(128, 16, 0)) for n, e in engines.items()}
    samples = {n: int(e.packed_assets()["pt_count"].float().mean()) for n, e in engines.items()}
    times = {(n, g): [] for n in engines for g in (False, True)}
    for n, e in engines.items():
        e.evaluate(batch[n]), e.evaluate(batch[n], with_grad=True)
    for _ in range(args.rounds):
        for n, e in engines.items():
            for g in (False, True):
                t = time.perf_counter()
                e.evaluate(batch[n], with_grad=g)
                times[(n, g)].append(time.perf_counter() - t)
    for n in engines:
        result["sizes"][n].update({
            "samples_per_asset_mean": samples[n],
            "forward_ms": 1e3 * statistics.median(times[(n, False)]),
            "forward_grad_ms": 1e3 * statistics.median(times[(n, True)]),
            "forward_vs_surface_only": statistics.median(
                b / a for a, b in zip(times[(args.sizes[0], False)], times[(n, False)])),
        })
    print(json.dumps(result, indent=1) if args.json else result)


if __name__ == "__main__":
    main()
