"""An RL run's training curves from its log, in windows of steps: what the rollouts were and what a step
cost while the policy moved.

Each run folder (or a checkpoint folder) of ``physcene train pada`` keeps the trainer's log history as
``train_log.json`` (a checkpoint: ``trainer_state.json``'s ``log_history``). This averages chosen logged
keys over windows of ``--window`` optimiser steps, per run, side by side:

    python -m physcene.train.analysis.rl_logs pada=artifacts/rl-phys-credit-s1-pada \\
        grpo=artifacts/rl-phys-credit-s1-grpo --window 10 --out docs/results/credit_rl_logs.json

The default keys are the policy's drift (``kl``), the share of sampled tokens the CTRC constraint
overruled and the draws it refused (a policy leaving the grammar), the seconds of a step and of its host
check, and the rollouts' collision-free share and out-of-zone objects (what the reward saw).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

__all__ = ["DEFAULT_KEYS", "log_history", "windows"]

DEFAULT_KEYS = ("kl", "constraint/overruled_frac", "constraint/refused_draws", "step_time",
                "time/decode_host_check_s", "collision_free_rate", "out_of_zone_objects")


def log_history(run: str | Path) -> list[dict]:
    """The per-step log entries (those with a ``step`` and a ``reward``) of a run folder's
    ``train_log.json`` or a checkpoint folder's ``trainer_state.json``, in step order."""
    folder = Path(run)
    if (folder / "train_log.json").is_file():
        history = json.loads((folder / "train_log.json").read_text())
    elif (folder / "trainer_state.json").is_file():
        history = json.loads((folder / "trainer_state.json").read_text()).get("log_history", [])
    else:
        raise FileNotFoundError(f"{folder}: neither train_log.json nor trainer_state.json (not an RL run "
                                "or checkpoint folder)")
    entries = [e for e in history if "reward" in e and "step" in e]
    return sorted(entries, key=lambda e: int(e["step"]))


def windows(history: list[dict], window: int, keys=DEFAULT_KEYS) -> list[dict]:
    """``[{"steps": [first, last], "n", key: mean or None, ...}]``: the entries of each ``window``
    consecutive optimiser steps (1..window, window+1..2 window, ...), each key averaged over the entries
    that logged it."""
    if int(window) < 1:
        raise ValueError(f"window must be >= 1 step, got {window!r}")
    window = int(window)
    out: dict[int, list[dict]] = {}
    for entry in history:
        out.setdefault((int(entry["step"]) - 1) // window, []).append(entry)
    rows = []
    for k in sorted(out):
        entries = out[k]
        row = {"steps": [k * window + 1, (k + 1) * window], "n": len(entries)}
        for key in keys:
            values = [float(e[key]) for e in entries if key in e]
            row[key] = sum(values) / len(values) if values else None
        rows.append(row)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m physcene.train.analysis.rl_logs", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="NAME=FOLDER", help="a run (or checkpoint) folder, named")
    parser.add_argument("--window", type=int, default=10, help="optimiser steps per window (default 10)")
    parser.add_argument("--keys", nargs="+", default=list(DEFAULT_KEYS), help="logged keys to average")
    parser.add_argument("--out", help="write the windows as JSON here")
    args = parser.parse_args(argv)
    bad = [r for r in args.runs if "=" not in r]
    if bad:
        parser.error(f"runs are NAME=FOLDER, got {bad}")
    result = {"window": args.window, "keys": args.keys, "runs": {},
              "command": "python -m physcene.train.analysis.rl_logs " + shlex.join(argv or sys.argv[1:])}
    for spec in args.runs:
        name, folder = spec.split("=", 1)
        try:
            history = log_history(folder)
        except FileNotFoundError as exc:
            parser.error(str(exc))
        result["runs"][name] = {"path": folder, "steps": int(history[-1]["step"]) if history else 0,
                                "windows": windows(history, args.window, args.keys)}
        for row in result["runs"][name]["windows"]:
            shown = "  ".join(f"{k.split('/')[-1]} {row[k]:.3g}" for k in args.keys if row[k] is not None)
            print(f"{name} {row['steps'][0]}-{row['steps'][1]}: {shown}")
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
