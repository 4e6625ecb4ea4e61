"""``physcene bench reward``: the Warp engine against the torch reference, and the whole reward.

    physcene bench reward --device cuda                      # 512 scenes x 16 objects x 1024 points
    physcene bench reward --device cpu --scenes 256 --objects 12 --json
    physcene bench reward --device cuda --lanes 16 32 --graph off on    # A/B in one process

The narrowphase variant that lost (``buckets``) is timed against the product's by
benchmarks/ab_narrowphase.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from physcene.assets import AssetLibrary
from physcene.commands.bench.timing import BenchTarget, Timing, device_name, timed
from physcene.ctrc import completion_text
from physcene.scene import Scene, SceneObject, Zone

__all__ = ["TARGET", "bench_reward", "bench_scenes"]

# The engine's one narrowphase, as the figures name it (each variant's label and "narrowphase").
NARROWPHASE = "worklist"


def bench_scenes(n_scene: int, n_obj: int, seed: int = 0):
    """Random tabletop scenes: n_obj yawed boxes/cylinders/spheres resting on a 120 x 60 cm table.

    Sizes 4-18 cm wide, 2-20 cm tall, uniform positions: an untrained generator's density, with
    many (not all) pairs in contact.
    """
    rng = np.random.default_rng(seed)
    zone = Zone(0.0, 120.0, 0.0, 60.0)
    kinds = ("box", "cylinder", "sphere")
    scenes = []
    for s in range(n_scene):
        size = np.concatenate([rng.uniform(4.0, 18.0, (n_obj, 2)), rng.uniform(2.0, 20.0, (n_obj, 1))], 1)
        xy = rng.uniform([5.0, 5.0], [115.0, 55.0], (n_obj, 2))
        yaw = rng.uniform(-np.pi, np.pi, n_obj)
        kind = rng.integers(0, 3, n_obj)
        scenes.append(Scene(zone, [
            SceneObject(f"{k + 1}_{kinds[kind[k]]}_{k}", kinds[kind[k]], (xy[k, 0], xy[k, 1], size[k, 2] / 2),
                        tuple(size[k]), float(yaw[k]))
            for k in range(n_obj)], scene_type="bench", instruction=f"bench scene {s}"))
    return scenes


# reward ------------------------------------------------------------------------------------------
def _reward_arguments(parser) -> None:
    parser.add_argument("--scenes", type=int, default=512)
    parser.add_argument("--objects", type=int, default=16)
    parser.add_argument("--points", type=int, default=1024, help="surface points per asset")
    parser.add_argument("--resolution", type=int, default=64, help="SDF grid nodes per axis")
    parser.add_argument("--no-reference", action="store_true", help="skip the torch reference")
    parser.add_argument("--lanes", type=int, nargs="+", default=None,
                        help="narrowphase threads per (pair, direction) to time (default: the config's)")
    parser.add_argument("--graph", nargs="+", choices=("off", "on"), default=None,
                        help="time without and/or with the captured launch graph (default: the config's)")


def bench_reward(args) -> dict:
    """Warp engine vs torch reference (forward, forward+gradient) and the whole reward."""
    # the engine (Warp) loads when this target runs: `physcene bench generate` and the CLI's parser
    # need no Warp
    from physcene.physics import PhysicsConfig, PhysicsEngine
    from physcene.physics.reference import reference_penetration
    from physcene.reward import PhysicsReward, RewardConfig, TextPacker

    device = torch.device(args.device)
    library = AssetLibrary(resolution=args.resolution, n_points=args.points)
    library.add_primitives()
    config = PhysicsConfig.load(getattr(args, "overrides", []))
    variants = _variants(config, device, args.lanes, args.graph)
    engine = PhysicsEngine(library, device, variants[0][1])
    scenes = bench_scenes(args.scenes, args.objects)
    batch = engine.pack(scenes)
    assets = engine.packed_assets()
    out = engine.evaluate(batch)
    # query counts (host, outside the timings)
    pt = assets["pt_count"].cpu().numpy()[batch.asset_index.cpu().numpy().reshape(-1)]
    hit = out["pair_hit"].cpu().numpy().astype(bool)
    a, b = out["pair_a"].cpu().numpy()[hit], out["pair_b"].cpu().numpy()[hit]
    evaluated = int(pt[a].sum() + pt[b].sum())
    n = batch.count.cpu().numpy()
    nominal = int((n * (n - 1)).sum() * pt.mean())  # every ordered pair, no broadphase
    result = {
        "target": "reward", "device": device_name(device), "scenes": args.scenes, "objects": args.objects,
        "points": float(pt.mean()), "resolution": args.resolution, "pairs": batch.n_pairs,
        "candidate_pairs": int(hit.sum()), "queries_evaluated": evaluated, "queries_all_pairs": nominal,
    }

    def figures(timing: Timing) -> dict:
        seconds = timing.seconds
        return {"seconds": seconds, "cpu_seconds": timing.cpu_seconds,
                "scenes_per_s": args.scenes / seconds,
                "gq_per_s": evaluated / seconds / 1e9, "all_pairs_gq_per_s": nominal / seconds / 1e9}

    repeat = args.repeat
    base = engine.evaluate(batch, with_grad=True)
    result["variants"] = {}
    for name, variant in variants:  # the first is the engine's config, used for the reward below
        engine.config = variant
        row = result["variants"][name] = {
            "narrowphase": NARROWPHASE, "graph": variant.graph,
            "lanes": variant.lanes_cuda if device.type == "cuda" else variant.lanes_cpu,
            "warp_forward": figures(timed(lambda: engine.evaluate(batch), device, repeat)),
            "warp_grad": figures(timed(lambda: engine.evaluate(batch, with_grad=True), device, repeat))}
        # after the timings (a graph variant replays by now), against the first variant: the same
        # maths up to float summation order
        check = engine.evaluate(batch, with_grad=True)
        row["max_rel_diff"] = {key: _rel_diff(check[key], base[key])
                               for key in ("energy", "pair_depth", "grad")}
    engine.config = variants[0][1]
    result["warp_forward"] = result["variants"][variants[0][0]]["warp_forward"]
    result["warp_grad"] = result["variants"][variants[0][0]]["warp_grad"]
    if not args.no_reference:
        kw = dict(poses=batch.poses, sizes=batch.sizes, count=batch.count, obj_asset=batch.asset_index,
                  assets=assets, margin=engine.config.margin_cm,
                  depth_cap_ratio=engine.config.depth_cap_ratio)
        ref_repeat = max(1, repeat // 5)
        result["reference_forward"] = figures(
            timed(lambda: reference_penetration(**kw), device, ref_repeat, 1))
        result["reference_grad"] = figures(
            timed(lambda: reference_penetration(**kw, with_grad=True), device, ref_repeat, 1))
        result["speedup_forward"] = result["reference_forward"]["seconds"] / result["warp_forward"]["seconds"]
        result["speedup_grad"] = result["reference_grad"]["seconds"] / result["warp_grad"]["seconds"]
    reward = PhysicsReward(RewardConfig(device=str(device)), engine=engine)
    python_reward = PhysicsReward(RewardConfig(device=str(device), fast_parse=False), engine=engine)
    texts = [completion_text(s) for s in scenes]
    parsed = list(scenes)
    result["text_bytes"] = sum(len(t.encode()) for t in texts)
    packer = TextPacker(engine)
    result["fast_parse_accepted"] = float(packer.pack(texts).fast.mean())
    # the whole reward from text: compiled scanner (fast_parse) and pure-Python parse, same run
    whole = timed(lambda: reward.score(texts), device, repeat)
    result["pack_texts"] = _seconds(timed(lambda: packer.pack(texts), device, repeat), args.scenes)
    whole_python = timed(lambda: python_reward.score(texts), device, max(1, repeat // 4), 1)
    result["reward_from_text_python"] = _seconds(whole_python, args.scenes)
    from_scenes = timed(lambda: reward.score_parsed(parsed), device, repeat)
    result["reward_from_text"] = _seconds(whole, args.scenes)
    result["fast_parse_speedup"] = whole_python.seconds / whole.seconds
    result["reward_from_scenes"] = _seconds(from_scenes, args.scenes)
    return result


def _seconds(timing: Timing, n_scene: int) -> dict:
    return {"seconds": timing.seconds, "cpu_seconds": timing.cpu_seconds,
            "scenes_per_s": n_scene / timing.seconds}


def _rel_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| / max |b| (0 when b is all zeros and a equals it)."""
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-12)) if b.numel() else 0.0


def _variants(config, device: torch.device, lanes, graphs=None) -> list:
    """[(name, PhysicsConfig)] for every lanes x graph asked (the config's when not)."""
    for n in lanes or ():
        if n < 1:
            raise ValueError(f"--lanes {n}: expected >= 1")
    key = "lanes_cuda" if device.type == "cuda" else "lanes_cpu"
    out = []
    for n in lanes or [getattr(config, key)]:
        for graph in graphs or ["on" if config.graph else "off"]:
            label = f"{NARROWPHASE}/lanes={n}" + ("/graph" if graph == "on" else "")
            out.append((label, replace(config, graph=graph == "on", **{key: n})))
    return out


def _reward_summary(r: dict) -> str:
    lines = [f"device {r['device']}: {r['scenes']} scenes x {r['objects']} objects x "
             f"{r['points']:.0f} points, "
             f"{r['candidate_pairs']}/{r['pairs']} pairs pass the broadphase, "
             f"{r['queries_evaluated'] / 1e6:.1f} M point queries evaluated "
             f"({r['queries_all_pairs'] / 1e6:.1f} M for all ordered pairs)"]
    rows = [(r["variants"][name][key], f"{label} {name}") for name in r["variants"]
            for key, label in (("warp_forward", "fwd"), ("warp_grad", "fwd+grad"))]
    for key, label in (("reference_forward", "torch reference forward"),
                       ("reference_grad", "torch reference forward+grad")):
        if key in r:
            rows.append((r[key], label))
    for f, label in rows:
        if f:
            lines.append(f"{label:30s} {f['seconds'] * 1e3:9.3f} ms ({f['cpu_seconds'] * 1e3:9.3f} ms CPU)  "
                         f"{f['scenes_per_s']:12.1f} scenes/s  {f['gq_per_s']:8.3f} Gq/s evaluated  "
                         f"{f['all_pairs_gq_per_s']:8.3f} Gq/s all-pairs")
    for name, v in r["variants"].items():
        diff = ", ".join(f"{k} {d:.1e}" for k, d in v["max_rel_diff"].items())
        lines.append(f"{name}: max |diff| / max |first variant|: {diff}")
    if "speedup_forward" in r:
        lines.append(f"warp ({next(iter(r['variants']))}) / reference: forward {r['speedup_forward']:.1f}x, "
                     f"forward+grad {r['speedup_grad']:.1f}x")
    for key, label in (("reward_from_text", "whole reward (text -> rewards)"),
                       ("reward_from_text_python", "  same, pure-Python parse"),
                       ("pack_texts", "  of which text -> batch"),
                       ("reward_from_scenes", "reward from parsed scenes")):
        if key not in r:
            continue
        f = r[key]
        lines.append(f"{label:30s} {f['seconds'] * 1e3:9.3f} ms ({f['cpu_seconds'] * 1e3:9.3f} ms CPU)  "
                     f"{f['scenes_per_s']:12.1f} scenes/s")
    if "fast_parse_speedup" in r:
        lines.append(f"fast parse: {r['fast_parse_accepted']:.0%} of {r['text_bytes'] / 1e6:.2f} MB of "
                     f"completions read by the compiled scanner, whole reward {r['fast_parse_speedup']:.1f}x "
                     "the pure-Python parse")
    return "\n".join(lines)


TARGET = BenchTarget("Warp engine vs torch reference, and the whole physics reward", _reward_arguments,
                     bench_reward, _reward_summary)
