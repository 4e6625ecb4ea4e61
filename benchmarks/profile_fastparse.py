"""Where the time of the reward's text fast path goes: host stages, kernels, engine.

    python benchmarks/profile_fastparse.py --device cuda --scenes 512 --objects 16

On the completion texts of ``physcene bench reward``'s scenes, prints the median wall time
(device synchronised after each call) of each stage of ``TextPacker.pack`` and of the
whole reward, and on CUDA the device time of every kernel of one ``TextPacker.pack`` call (from
``torch.profiler``, as benchmarks/profile_engine.py does).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
from profile_engine import kernel_times

from physcene.assets import AssetLibrary
from physcene.commands.bench import bench_scenes
from physcene.ctrc import completion_text
from physcene.kernels.ctrc_reader import launch_scan
from physcene.physics import PhysicsEngine
from physcene.reward import PhysicsReward, RewardConfig, TextPacker
from physcene.reward.text_batch import READER_LIMITS


def wall_ms(fn, device: torch.device, repeat: int) -> float:
    """Median milliseconds of ``fn()`` with the device synchronised before and after."""
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fn()
    times = []
    for _ in range(repeat):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", type=int, default=512)
    parser.add_argument("--objects", type=int, default=16)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    device = torch.device(args.device)
    library = AssetLibrary(resolution=64, n_points=args.points)
    library.add_primitives()
    engine = PhysicsEngine(library, device)
    texts = [completion_text(s) for s in bench_scenes(args.scenes, args.objects)]
    packer = TextPacker(engine)
    pack = packer.pack(texts)  # JIT, categories learned
    data, header = packer._encode(texts)
    n, n_chunks = len(texts), int(header[-1])
    text_t, header_t = packer._stage(data, header)
    buffers = packer._scan_buffers(n, n_chunks)

    def kernels_only():
        launch_scan(text=text_t, offsets=header_t[:n + 1], chunk_start=header_t[n + 1:], n_text=n,
                    n_chunks=n_chunks, words=packer._words, table=packer._table, limits=READER_LIMITS,
                    buffers=buffers)

    reward = PhysicsReward(RewardConfig(device=str(device)), engine=engine)
    batch = pack.batch
    r = args.repeat
    out = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "scenes": args.scenes, "objects": args.objects, "bytes": len(data),
        "accepted": float(pack.fast.mean()),
        "encode_ms": wall_ms(lambda: packer._encode(texts), device, r),
        "stage_upload_ms": wall_ms(lambda: packer._stage(data, header), device, r),
        "scan_kernels_ms": wall_ms(kernels_only, device, r),
        "scan_with_status_sync_ms": wall_ms(lambda: packer.scan(texts), device, r),
        "pack_texts_ms": wall_ms(lambda: packer.pack(texts), device, r),
        "engine_evaluate_ms": wall_ms(lambda: engine.evaluate(batch), device, r),
        "whole_reward_ms": wall_ms(lambda: reward.score(texts), device, r),
    }
    if device.type == "cuda":
        out["kernels_ms"] = kernel_times(lambda: packer.pack(texts), r)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
