"""``physcene bench tto``: batched TTO throughput (512 scenes x 16 objects x 100 steps).

    physcene bench tto --device cuda                    # 512 noisy scenes x 16 objects, 100 steps
    physcene bench tto --device cpu --scenes 16 --json
    physcene bench tto --device cuda in_lr_scale=1.0     # any configs/tto.yaml key=value override

Scenes come from :func:`physcene.data.noisy.noisy_scenes` (stacks, containers, overlaps). Timed:
``optimise`` with every scene running all steps (no early stop: the worst case the target is
about), ``optimise`` with per-scene early stop, and the host preparation (hierarchy + packing).
The quality figures of the timed optimisation come from one full :func:`physcene.tto.repair`.
"""

from __future__ import annotations

import time
from dataclasses import replace

import torch

from physcene.commands.bench.timing import BenchTarget, device_name, timed
from physcene.data.noisy import noisy_scenes
from physcene.graph import ensure_hierarchy
from physcene.tto import TTOConfig, build_problem, optimise, repair, summarize

__all__ = ["TARGET"]


def add_arguments(parser) -> None:
    parser.add_argument("--scenes", type=int, default=512)
    parser.add_argument("--objects", type=int, default=16)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)


def run(args) -> dict:
    from physcene.physics import PhysicsEngine  # Warp loads when this target runs

    device = torch.device(args.device)
    engine = PhysicsEngine(device=device)
    scenes = noisy_scenes(args.scenes, args.objects, seed=args.seed)
    # configs/tto.yaml with the command's key=value overrides, sized for one batch
    base = replace(TTOConfig.load(getattr(args, "overrides", [])), steps=args.steps,
                   device=str(device), batch_size=max(1, args.scenes))
    full, early = replace(base, early_stop=False), replace(base, early_stop=True)
    engine.pack(scenes)  # loads (or bakes) the assets once, outside the timings
    start = time.perf_counter()
    hier = [ensure_hierarchy(s) for s in scenes]
    problem = build_problem(hier, engine, full)
    prepare = time.perf_counter() - start
    repeat = max(1, args.repeat)
    seconds_full = timed(lambda: optimise(problem, engine, full), device, repeat, warmup=1).seconds
    seconds_early = timed(lambda: optimise(problem, engine, early), device, repeat, warmup=0).seconds
    start = time.perf_counter()
    results = repair(scenes, early, engine)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    whole = time.perf_counter() - start
    n = max(1, args.scenes)
    return {
        "target": "tto", "device": device_name(device), "scenes": args.scenes, "objects": args.objects,
        "steps": args.steps,
        "optimise_all_steps": {"seconds": seconds_full, "per_scene_s": seconds_full / n,
                               "steps_per_s": args.steps / seconds_full},
        "optimise_early_stop": {"seconds": seconds_early, "per_scene_s": seconds_early / n},
        "prepare_host": {"seconds": prepare, "per_scene_s": prepare / n},
        "repair_whole": {"seconds": whole, "per_scene_s": whole / n},
        "quality": summarize(results),
    }


def summary(r: dict) -> str:
    q = r["quality"]
    lines = [f"device {r['device']}: {r['scenes']} noisy scenes x {r['objects']} objects, "
             f"{r['steps']} Adam steps"]
    for key, label in (("optimise_all_steps", "optimise, all steps"),
                       ("optimise_early_stop", "optimise, early stop"),
                       ("prepare_host", "hierarchy + packing (host)"),
                       ("repair_whole", "repair() incl. reports")):
        f = r[key]
        lines.append(f"{label:30s} {f['seconds']:9.3f} s  {f['per_scene_s'] * 1e3:9.2f} ms/scene")
    lines.append(f"quality: {q['collision_free']:.1%} scenes without a pair > 1 mm, in/on kept "
                 f"{q['in_on_kept']:.1%}, near kept {q['near_kept']:.1%}, median max displacement "
                 f"{q['median_max_displacement_cm']:.2f} cm, mean steps {q['mean_steps']:.1f}")
    return "\n".join(lines)


TARGET = BenchTarget("Batched hierarchy-constrained TTO (512 scenes x 16 objects x 100 steps)",
                     add_arguments, run, summary)
