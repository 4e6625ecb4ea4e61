"""CTRC constraint versions timed interleaved on one replay: before/after in one run on a noisy machine.

    python benchmarks/ab_constrained.py 2000bc3 c95eeb9 --rows 64 --decimals 2 --rounds 5

Each git revision's single-module ``train/constrained.py`` is loaded as a module of its own, next to
the working tree's; every round replays the same synthetic completions through one ``CTRCConstraint`` of each
version (rejection sampling, as PADA's groups: the true token holds ~99.9 % of the mass, the rest
N(-18, 2)), so load that changes during the run hits all versions alike. Prints ms per decoding step
in the processor (min and median over the rounds) and whether every version returned the same masks.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import statistics
import subprocess
import tempfile
from pathlib import Path

import torch
from transformers import LogitsProcessorList

from physcene.ctrc import completion_text
from physcene.data import synthesize
from physcene.graph import build_hierarchy
from physcene.layout import load_layout
from physcene.train import constrained
from physcene.train.tokenizer import build_tokenizer

ROOT = Path(__file__).resolve().parents[1]


def module_at(rev: str, folder: Path):
    """``train/constrained.py`` as it was at git revision ``rev``, imported under its own name (a
    revision where it is the package ``train/constrained/`` is timed from a checkout of its own)."""
    found = subprocess.run(["git", "show", f"{rev}:train/constrained.py"], cwd=ROOT, capture_output=True,
                           text=True)
    if found.returncode != 0:
        raise SystemExit(f"{rev} has no single-module train/constrained.py: time it from its own checkout")
    source = found.stdout
    path = folder / f"constrained_{rev}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("revs", nargs="*", help="git revisions to compare with the working tree")
    parser.add_argument("--rows", type=int, default=64)
    parser.add_argument("--decimals", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    records = list(synthesize("train", args.rows, seed=5))
    for r in records:
        r["completion"] = completion_text(build_hierarchy(load_layout(r["layout"])), decimals=args.decimals)
    tokenizer = build_tokenizer([r["prompt"] for r in records[:32]] + [r["completion"] for r in records[:32]],
                                vocab_size=4096)
    ids = [tokenizer(r["completion"], add_special_tokens=False)["input_ids"] for r in records]
    steps = max(len(i) for i in ids) + 1
    tokens = torch.tensor([i + [tokenizer.eos_token_id] * (steps - len(i)) for i in ids])
    prompt = torch.full((args.rows, 8), tokenizer.pad_token_id)

    def scores(k: int) -> torch.Tensor:
        # drawn again for every replay from the step's own seed: the same scores for every version,
        # without holding steps x rows x vocabulary floats (10 GB at 256 rows)
        s = torch.randn(args.rows, len(tokenizer), generator=torch.Generator().manual_seed(k)) * 2.0 - 18.0
        s[torch.arange(args.rows), tokens[:, k]] = 0.0
        return s

    def replay(module):
        # cold, as for the new prompts of every PADA step
        getattr(module, "grammar", module)._compiled.cache_clear()
        torch.manual_seed(0)
        processor = module.CTRCConstraint(tokenizer, [r["prompt"] for r in records], greedy=False,
                                          warpers=LogitsProcessorList())
        # a digest of each step's mask (finished rows come back whole: their indices would fill memory)
        kept = [hashlib.sha1(torch.isfinite(processor(torch.cat([prompt, tokens[:, :k]], 1), scores(k)))
                             .numpy().tobytes()).hexdigest() for k in range(steps)]
        stats = getattr(processor, "stats", processor)  # revisions before ConstraintStats: on the processor
        return 1e3 * stats.seconds / steps, kept, stats.masked_steps

    with tempfile.TemporaryDirectory() as folder:
        versions = {rev: module_at(rev, Path(folder)) for rev in args.revs}
        versions["working tree"] = constrained
        times = {name: [] for name in versions}
        first = {}
        for _ in range(args.rounds):
            for name, module in versions.items():
                ms, kept, masked = replay(module)
                times[name].append(ms)
                first.setdefault(name, (kept, masked))
    reference_kept, reference_masked = first["working tree"]
    print(f"{args.rows} rows x {steps} steps, {args.decimals} decimals, {args.rounds} rounds")
    for name, ms in times.items():
        kept, masked = first[name]
        same = masked == reference_masked and kept == reference_kept
        print(f"  {name}: min {min(ms):.3f} ms/step, median {statistics.median(ms):.3f}; "
              f"same masks as the working tree: {same} (rows x steps overruled {masked})")


if __name__ == "__main__":
    main()
