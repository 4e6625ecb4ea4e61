"""Subcommands of ``physcene``: one module each (see :mod:`physcene.cli`).

The options every command spells the same way live here: ``--quiet`` (no progress bars) and
``--json`` (one JSON document on stdout), and :func:`print_json`, which writes that document.
Only the standard library is imported: this package loads before every command.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

__all__ = ["add_json", "add_quiet", "json_safe", "print_json"]


def add_quiet(parser: argparse.ArgumentParser, *, legacy: tuple[str, ...] = ()) -> None:
    """``--quiet``: no progress bars (they go to stderr). ``legacy``: older spellings still
    accepted, hidden from ``--help`` (``data synth --no-progress``)."""
    parser.add_argument("--quiet", action="store_true", help="no progress bars on stderr")
    for flag in legacy:
        parser.add_argument(flag, dest="quiet", action="store_true", help=argparse.SUPPRESS)


def add_json(parser: argparse.ArgumentParser, what: str = "the results") -> None:
    """``--json``: one JSON document on stdout instead of the text (progress stays on stderr)."""
    parser.add_argument("--json", action="store_true",
                        help=f"print {what} as one JSON document on stdout")


def json_safe(data):
    """``data`` with NaN/inf as null, paths as strings and numpy scalars as Python numbers, so
    that it is strict JSON (``json.loads`` in other languages rejects NaN)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {str(k): json_safe(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_safe(v) for v in data]
    if isinstance(data, Path):
        return str(data)
    if hasattr(data, "item") and callable(data.item) and getattr(data, "shape", None) == ():
        return json_safe(data.item())  # a numpy / torch scalar
    return data


def print_json(data) -> None:
    """Print ``data`` as the command's one JSON document on stdout."""
    print(json.dumps(json_safe(data), indent=1, ensure_ascii=False, allow_nan=False))
