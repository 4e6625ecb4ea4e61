"""Study scripts over evaluated layouts, each runnable as ``python -m physcene.eval.analysis.<name>``
and tested under tests/eval/ (docs/results.md cites what they measured)."""

from __future__ import annotations

import argparse


def add_split_arguments(parser: argparse.ArgumentParser, *, n: int = 866, device: bool = True) -> None:
    """The options every study takes: which records of which split (``--split``, ``--n``, ``--seed``),
    the physics engine's ``--device`` (where the study scores layouts) and ``--out`` (a JSON file)."""
    parser.add_argument("--split", default="test")
    parser.add_argument("--n", type=int, default=n)
    parser.add_argument("--seed", type=int, default=0)
    if device:
        parser.add_argument("--device", default="cpu")
    parser.add_argument("--out")
