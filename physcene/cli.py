"""The ``physcene`` command: one entry point, one module per subcommand.

Each module in :mod:`physcene.commands` defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; they are found here without a central list, so adding a subcommand is
adding a file. Expected errors (bad input files, bad configs) print one line and exit 2; they
never print a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from physcene import commands

__all__ = ["main"]

# Error types that mean "the user's input was wrong": one line, no traceback.
_INPUT_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, IsADirectoryError,
                                                   PermissionError, KeyError)


def _subcommand_modules():
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield importlib.import_module(f"physcene.commands.{info.name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="physcene", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in _subcommand_modules():
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    unknown = [a for a in extra if "=" not in a or a.startswith("-")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.overrides = [a for a in extra if a not in unknown]
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("physcene: interrupted", file=sys.stderr)
        return 130
    except _INPUT_ERRORS as exc:
        print(f"physcene {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
