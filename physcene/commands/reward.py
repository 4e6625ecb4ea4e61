"""``physcene reward``: the paper's physics reward of completions (physcene.reward).

    physcene reward completions.jsonl            # one reward per line, input order
    physcene reward completions.jsonl --json     # {"rewards": [...]}
    physcene reward c.jsonl tolerance_mm=1 table_term=true --device cuda   # configs/reward.yaml

Each line is ``{"prompt": ..., "completion": ...}`` (the completion a string or a chat list).
Unparsable completions get −100; a line that is not such a record is an input error (exit 2).
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

from physcene.layout import json_records

NAME = "reward"
HELP = "Score completions (JSONL of {prompt, completion}) with the paper's physics reward"
SETTINGS = "configs/reward.yaml (docs/physics.md)"


class RewardInputError(ValueError):
    """The reward input file is missing or has a malformed line (named in the message)."""


def add_arguments(parser) -> None:
    parser.add_argument("file", metavar="FILE.jsonl", help="one {\"prompt\", \"completion\"} record per line")
    parser.add_argument("--device", default=None, help="engine device (default: configs/reward.yaml)")
    parser.add_argument("--json", action="store_true", help='print {"rewards": [...]}')


def read_records(path: Path) -> tuple[list, list]:
    """(prompts, completions) of a JSONL file; malformed lines raise :class:`RewardInputError`."""
    prompts, completions = [], []
    for number, record in json_records(path, error=RewardInputError):
        if not isinstance(record, dict) or "completion" not in record:
            raise RewardInputError(f"{path}:{number}: expected an object with a 'completion' field")
        if not isinstance(record["completion"], (str, list)):
            raise RewardInputError(f"{path}:{number}: 'completion' must be a string or a chat list")
        prompts.append(record.get("prompt"))
        completions.append(record["completion"])
    return prompts, completions


def run(args) -> int:
    from physcene.reward import PhysicsReward, RewardConfig, completion_text_of

    prompts, completions = read_records(Path(args.file))
    config = RewardConfig.load(args.overrides)
    if args.device:
        config = replace(config, device=args.device)
    batch = PhysicsReward(config).score([completion_text_of(c) for c in completions]) if completions else None
    rewards = batch.rewards.tolist() if batch is not None else []
    if args.json:
        print(json.dumps({"rewards": rewards}))
    else:
        for value in rewards:
            print(f"{value:.6g}")
        metrics = ", ".join(f"{k} {v:.4g}" for k, v in (batch.metrics if batch is not None else {}).items())
        print(f"{len(rewards)} completions: {metrics}", file=sys.stderr)
    return 0
