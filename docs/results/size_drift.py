"""Did RL change the objects' sizes? Per-dimension size drift of generated layouts against a baseline's.

    python docs/results/size_drift.py runs/small/ablation/sft runs/small/ablation/pada [--out FILE]

Both folders hold ``layout.json`` files named by record id (``physcene eval``'s layout folders, the
ablation's ``runs/small/ablation/<row>``). Over the categories both write, the mean of
log(size / baseline size) per dimension (x, y, z as written; the category's mean log-size in each
folder), and for the whole set: the share of objects whose size lies outside their category prior's
band (``physcene.assets.SizePrior.band_cm`` at the rule judge's OSR tolerance) and the cm they lie
past it (``SizePrior.outside_band_cm``, what ``reward.size_per_cm`` charges). A reward that charges
penetration only pays for flattening: a thin box cannot be penetrated deeply.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from physcene.assets import CATEGORY_PRIORS, canonical_category
from physcene.layout import read_layout


def sizes_by_category(folder: Path) -> dict[str, np.ndarray]:
    """category -> (n, 3) sizes (cm) of every object written in the folder's layouts."""
    out: dict[str, list] = defaultdict(list)
    for path in sorted(folder.glob("*.json")):
        for o in read_layout(path).objects:
            out[canonical_category(o.category)].append(o.size)
    return {c: np.asarray(s, dtype=np.float64) for c, s in out.items()}


def band_report(by_category: dict[str, np.ndarray], tolerance: float) -> dict:
    """Share of objects with a prior outside its band, and the mean cm past it per such object."""
    past = [CATEGORY_PRIORS[c].outside_band_cm(s, tolerance)
            for c, sizes in by_category.items() if c in CATEGORY_PRIORS for s in sizes]
    past = np.asarray(past)
    return {"objects_with_prior": int(past.size),
            "outside_band_share": round(float((past > 0).mean()), 4) if past.size else 0.0,
            "outside_band_cm_mean": round(float(past.mean()), 3) if past.size else 0.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("baseline", type=Path)
    parser.add_argument("generated", type=Path)
    parser.add_argument("--tolerance", type=float, default=1.0, help="band half-width, prior sigmas (OSR's)")
    parser.add_argument("--top", type=int, default=12, help="categories listed, most frequent first")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    base, gen = sizes_by_category(args.baseline), sizes_by_category(args.generated)
    shared = sorted(set(base) & set(gen), key=lambda c: -len(base[c]))
    drift = np.array([np.log(gen[c]).mean(0) - np.log(base[c]).mean(0) for c in shared])
    report = {
        "baseline": str(args.baseline), "generated": str(args.generated), "categories": len(shared),
        "mean_log_ratio_xyz": np.round(drift.mean(0), 3).tolist() if len(shared) else [],
        "size_ratio_xyz": np.round(np.exp(drift.mean(0)), 3).tolist() if len(shared) else [],
        "band": {"baseline": band_report(base, args.tolerance),
                 "generated": band_report(gen, args.tolerance)},
        "median_size_cm": {c: {"baseline": np.round(np.median(base[c], 0), 1).tolist(),
                               "generated": np.round(np.median(gen[c], 0), 1).tolist(), "n": len(gen[c])}
                           for c in shared[:args.top]},
    }
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
