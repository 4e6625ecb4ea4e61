"""What writing completions with fewer decimals does to the data: tokens, and the reference's collisions.

    python docs/results/decimals_check.py 100 [TOKENIZER_DIR]

The first N test-split references are written as CTRC completions at 5, 2 and 1 decimals
(``physcene.ctrc.completion_text``), parsed back and scored with the engine (CPU). Prints the median
and mean token counts (the ``small`` tokenizer, ``runs/small/sft`` unless given) and SCR / ACR at the
0 / 0.5 / 1 cm thresholds and the floating rate of each precision.
"""

from __future__ import annotations

import sys

import numpy as np
from physcene.eval.harness import load_benchmark
from physcene.eval.metrics import collision_rates, physics_from_score
from transformers import AutoTokenizer

from physcene.ctrc import ParseError, completion_text, parse
from physcene.graph import build_hierarchy
from physcene.physics import PhysicsEngine


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    tokenizer = AutoTokenizer.from_pretrained(sys.argv[2] if len(sys.argv) > 2 else "runs/small/sft")
    items = load_benchmark("test", n=n, progress=False)
    engine = PhysicsEngine()
    for decimals in (5, 2, 1):
        scenes, lengths = [], []
        for it in items:
            text = completion_text(build_hierarchy(it.reference), decimals=decimals)
            lengths.append(len(tokenizer(text)["input_ids"]))
            scene = parse(text, zone=it.reference.zone, scene_type=it.scene_type, instruction=it.instruction)
            if isinstance(scene, ParseError):
                raise SystemExit(f"{it.id} at {decimals} decimals does not parse: {scene.reason}")
            scenes.append(scene)
        physics = []
        for k in range(0, len(scenes), 16):
            physics += physics_from_score(scenes[k:k + 16], engine.score(scenes[k:k + 16]))
        rates = {t: {m: round(v, 4) for m, v in r.items()} for t, r in collision_rates(physics).items()}
        floating = float(np.mean([len(p.floating) > 0 for p in physics]))
        print(f"{decimals} decimals: tokens median {np.median(lengths):.0f}, mean {np.mean(lengths):.0f}; "
              f"SCR/ACR by threshold {rates}; floating {floating:.2f}", flush=True)


if __name__ == "__main__":
    main()
