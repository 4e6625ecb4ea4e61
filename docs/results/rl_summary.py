"""Figures of an RL run (grpo / pada_star / pada) from its saved ``train_log.json`` and ``physcene_run.json``:
the ``rl`` block of ``docs/results/ablation*.json``.

    python docs/results/rl_summary.py runs/small/grpo runs/small/pada_star runs/small/pada

Per run: optimizer steps (and those applied: not dropped as non-finite), generation rounds, wall
seconds (sum of ``step_time``), seconds per step, median seconds of a round's generation, the
rollouts' collision-free share in the first and last two rounds, KL (median, max), the share of
tokens the constraint chose, the last adaptive-KL β, the steps the non-finite guard dropped, the
anchor CE (first step, mean of the last 8), and where the run logged them the rollouts' E_pen (mm) and
summed size outside the category bands (cm, ``reward.size_per_cm`` / the ``size`` term), means of the
first and last two rounds, and the denoising NLL, means of the first and last 8 steps.
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path


def summary(run: Path) -> dict:
    log = json.loads((run / "train_log.json").read_text())
    info = json.loads((run / "physcene_run.json").read_text())
    steps = [e for e in log if "step_time" in e]
    rounds = [e for e in log if "time/generate_s" in e]
    free = [e["collision_free_rate"] for e in rounds if "collision_free_rate" in e]
    kl = [e["kl"] for e in log if "kl" in e]
    seconds = sum(e["step_time"] for e in steps)
    out = {
        "steps": int(info.get("steps", len(steps))),
        "rounds": len(rounds),
        "seconds": round(seconds, 1),
        "s_per_step": round(seconds / max(len(steps), 1), 2),
        "generate_median_s": (round(statistics.median(e["time/generate_s"] for e in rounds), 1)
                              if rounds else None),
        "collision_free_first_2_rounds": round(statistics.fmean(free[:2]), 3) if free else None,
        "collision_free_last_2_rounds": round(statistics.fmean(free[-2:]), 3) if free else None,
        "kl_median": round(statistics.median(kl), 4) if kl else None,
        "kl_max": round(max(kl), 4) if kl else None,
        "overruled_frac_median": round(statistics.median(
            e["constraint/overruled_frac"] for e in rounds if "constraint/overruled_frac" in e), 4)
        if any("constraint/overruled_frac" in e for e in rounds) else None,
        "beta_last": next((round(e["beta"], 4) for e in reversed(log) if "beta" in e), None),
        "nonfinite_steps_dropped": info.get("nonfinite_steps_dropped", []),
    }
    out["steps_applied"] = out["steps"] - len(out["nonfinite_steps_dropped"])
    ce = [e["anchor_ce"] for e in log if "anchor_ce" in e]
    if ce:
        out["anchor_ce_first"] = round(ce[0], 3)
        out["anchor_ce_last_8_mean"] = round(statistics.fmean(ce[-8:]), 3)
    for key, name, n, unit in (("penetration_mm", "penetration_mm", 2, "rounds"),  # logged once a round
                               ("size_outside_cm", "size_outside_cm", 2, "rounds"),
                               ("invalid_rate", "invalid_rate", 2, "rounds"),  # reward.valid_terms
                               ("floating_objects", "floating_objects", 2, "rounds"),
                               ("shrunk_objects", "shrunk_objects", 2, "rounds"),
                               ("denoise/nll", "denoise_nll", 8, "steps")):         # once a step
        values = [e[key] for e in log if key in e]
        if values:
            out[f"{name}_first_{n}_{unit}"] = round(statistics.fmean(values[:n]), 3)
            out[f"{name}_last_{n}_{unit}"] = round(statistics.fmean(values[-n:]), 3)
    # a round's generation: the constraint's time in it, of that the wait for the GPU's forward and
    # the vocabulary scans (medians over the rounds after the first, which compiles)
    for key, name in (("time/constraint_s", "constraint_median_s"),
                      ("time/constraint_wait_s", "constraint_wait_median_s"),
                      ("time/constraint_scan_s", "constraint_scan_median_s")):
        values = [e[key] for e in rounds[1:] or rounds if key in e]
        if values:
            out[name] = round(statistics.median(values), 1)
    return out


if __name__ == "__main__":
    print(json.dumps({Path(p).name: summary(Path(p)) for p in sys.argv[1:]}, indent=1))
