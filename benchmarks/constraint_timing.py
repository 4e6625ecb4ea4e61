"""Is ``time/constraint_s`` host work, or the wait for the step's forward pass? (CUDA only)

    python benchmarks/constraint_timing.py runs/small/sft runs/small/anchors.jsonl --n 64 --steps 768 \
        [--cache static_compile] [--profile]

Samples the first N prompts by rejection under the CTRC constraint (as PADA's groups are) three
times: with ``CTRCConstraint.seconds`` as logged, with the CUDA stream synchronized before its clock
starts (so a wait for the queued forward pass falls outside it), and as logged again. Equal figures:
the logged time is the constraint's own host work. Measured on an H100 (docs/training.md).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import torch

import physcene.train.constrained as constrained
from physcene.train.generate import generate_token_ids, load_for_generation
from physcene.train.records import load_records

made: list = []


class _Logged(constrained.CTRCConstraint):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        made.append(self)


class _Synchronized(_Logged):
    def __call__(self, input_ids, scores):
        torch.cuda.current_stream(scores.device).synchronize()
        return super().__call__(input_ids, scores)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("records", help="JSONL (.gz ok) with a prompt column")
    parser.add_argument("--n", type=int, default=64)
    parser.add_argument("--steps", type=int, default=768)
    parser.add_argument("--cache", default="dynamic",
                        help="dynamic | static | static_compile (PADA: static_compile)")
    parser.add_argument("--profile", action="store_true",
                        help="also profile the constraint's calls of the last run (cProfile, top 20)")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("constraint_timing: needs a CUDA device (the question is about GPU waits)")
    prompts = [r["prompt"] for r in load_records(args.records)[:args.n]]
    model, tokenizer, _ = load_for_generation(args.model, device="cuda")
    runs = (("warm-up", _Logged, 32), ("logged", _Logged, args.steps),
            ("synchronized", _Synchronized, args.steps), ("logged again", _Logged, args.steps))
    profiler = cProfile.Profile()
    for name, cls, steps in runs:
        if args.profile and name == "logged again":
            cls = _profiled(cls, profiler)
        constrained.CTRCConstraint = cls  # generate_token_ids builds its processor from the module
        made.clear()
        torch.cuda.synchronize()
        start = time.perf_counter()
        ids = generate_token_ids(model, tokenizer, prompts, max_new_tokens=steps, batch_size=len(prompts),
                                 do_sample=True, seed=0, cache=args.cache, constrained=True)
        torch.cuda.synchronize()
        total = time.perf_counter() - start
        n_steps = max(len(row) for row in ids)
        seconds = sum(m.stats.seconds for m in made)
        print(f"{name}: {n_steps} steps, generate {total:.2f} s, constraint {seconds:.2f} s "
              f"({1000 * seconds / n_steps:.2f} ms/step of {1000 * total / n_steps:.2f})", flush=True)
    if args.profile:
        pstats.Stats(profiler).sort_stats("tottime").print_stats(20)


def _profiled(cls, profiler: cProfile.Profile):
    """``cls`` with each call profiled (only the constraint's own work, not the model's)."""

    class Profiled(cls):
        def __call__(self, input_ids, scores):
            profiler.enable()
            try:
                return super().__call__(input_ids, scores)
            finally:
                profiler.disable()

    return Profiled


if __name__ == "__main__":
    main()
