"""An RL run's training curves from its log, in windows of steps: what the rollouts were and what a step
cost while the policy moved.

Each run folder (or a checkpoint folder) of ``physcene train pada`` keeps the trainer's log history as
``train_log.json`` (a checkpoint: ``trainer_state.json``'s ``log_history``). This averages chosen logged
keys over windows of ``--window`` optimiser steps, per run, side by side:

    python -m physcene.train.analysis.rl_logs pada=artifacts/rl-phys-credit-s1-pada \\
        grpo=artifacts/rl-phys-credit-s1-grpo --window 10 --out docs/results/credit_rl_logs.json

A run stopped without its final save (killed, or its host taken away) keeps the steps after its newest
checkpoint only in the console log ``physcene train pada`` printed (one ``{'loss': ..., 'epoch': ...}``
line per step; the logs rl_ablation.sh writes, ``<run>/<variant>.log``). ``NAME=FOLDER,LOG`` reads both:
each console line past the folder's last step is placed by its epoch, at the folder's own steps per
epoch (``step / epoch`` of its entries).

The default keys are the policy's drift (``kl``), the share of sampled tokens the CTRC constraint
overruled and the draws it refused (a policy leaving the grammar), the seconds of a step and of its host
check, and the rollouts' collision-free share and out-of-zone objects (what the reward saw).
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import shlex
import sys
from pathlib import Path

__all__ = ["DEFAULT_KEYS", "console_history", "log_history", "run_history", "windows"]

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


_CONSOLE_LINE = re.compile(r"\{'loss': .*?\}")  # the trainer's printed log of one step (tqdm's \r around it)


def console_history(log: str | Path, steps_per_epoch: float) -> list[dict]:
    """The per-step entries of a console log of ``physcene train pada`` (the dicts the trainer prints,
    their values as strings), each given ``step = round(epoch * steps_per_epoch)``, in step order."""
    if not steps_per_epoch > 0:
        raise ValueError(f"steps_per_epoch must be > 0, got {steps_per_epoch!r}")
    entries = []
    for text in _CONSOLE_LINE.findall(Path(log).read_text(errors="replace")):
        try:
            printed = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            continue  # a line cut short (the run was killed while printing)
        entry = {}
        for key, value in printed.items():
            try:
                entry[key] = float(value)
            except (TypeError, ValueError):
                entry[key] = value
        if "reward" in entry and isinstance(entry.get("epoch"), float):
            entry["step"] = round(entry["epoch"] * steps_per_epoch)
            entries.append(entry)
    return sorted(entries, key=lambda e: e["step"])


def run_history(spec: str) -> list[dict]:
    """``FOLDER`` or ``FOLDER,LOG``: the folder's entries, then the console log's past its last step."""
    folder, _, log = spec.partition(",")
    history = log_history(folder)
    if not log:
        return history
    ratios = [e["step"] / e["epoch"] for e in history if e.get("epoch")]
    if not ratios:
        raise ValueError(f"{folder}: no logged step with an epoch, so {log}'s lines cannot be placed")
    last = int(history[-1]["step"])
    return history + [e for e in console_history(log, sum(ratios) / len(ratios)) if e["step"] > last]


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
    parser.add_argument("runs", nargs="+", metavar="NAME=FOLDER[,LOG]",
                        help="a run (or checkpoint) folder, named; LOG: its console log (the steps after it)")
    parser.add_argument("--window", type=int, default=10, help="optimiser steps per window (default 10)")
    parser.add_argument("--keys", nargs="+", default=list(DEFAULT_KEYS), help="logged keys to average")
    parser.add_argument("--out", help="write the windows as JSON here")
    args = parser.parse_args(argv)
    bad = [r for r in args.runs if "=" not in r]
    if bad:
        parser.error(f"runs are NAME=FOLDER[,LOG], got {bad}")
    result = {"window": args.window, "keys": args.keys, "runs": {},
              "command": "python -m physcene.train.analysis.rl_logs " + shlex.join(argv or sys.argv[1:])}
    for spec in args.runs:
        name, folder = spec.split("=", 1)
        try:
            history = run_history(folder)
        except (FileNotFoundError, ValueError) as exc:
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
