"""The ``physcene`` command: one entry point, one module per subcommand.

Each module in :mod:`physcene.commands` defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; they are found here without a central list, so adding a subcommand is
adding a file. ``NAME``, ``HELP`` and the optional ``SETTINGS`` (the config file its ``key=value``
settings override, and the page that documents them) are string literals read from the source
without importing it, and only the invoked subcommand's module is imported: the modules pull in
torch, Warp and trimesh, and importing all of them cost every command several seconds of start-up. Expected
errors (bad input files, bad configs) print one line and exit 2; they never print a traceback.
"""

from __future__ import annotations

import argparse
import ast
import gc
import importlib
import importlib.util
import pkgutil
import sys
from pathlib import Path

from physcene import __version__, commands

__all__ = ["main"]

# Error types that mean "the user's input was wrong": one line, no traceback.
_INPUT_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, IsADirectoryError,
                                                   PermissionError, KeyError)


def _literal_constants(path: Path, names: tuple[str, ...]) -> dict[str, str]:
    """Module-level ``NAME = "..."`` string constants of a source file, without importing it."""
    found = {}
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant):
            for target in node.targets:
                if isinstance(target, ast.Name) and target.id in names:
                    found[target.id] = str(node.value.value)
    return found


def subcommands() -> dict[str, tuple[str, str, str]]:
    """``{name: (module, help, settings)}`` for every module of :mod:`physcene.commands`."""
    table = {}
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = f"physcene.commands.{info.name}"
        origin = Path(importlib.util.find_spec(module).origin)
        consts = _literal_constants(origin, ("NAME", "HELP", "SETTINGS"))
        if "NAME" not in consts:
            raise RuntimeError(f"{module} defines no literal NAME")
        table[consts["NAME"]] = (module, consts.get("HELP", ""), consts.get("SETTINGS", ""))
    return table


def _epilog(settings: str) -> str | None:
    """The ``--help`` note on ``key=value`` settings, from the command's ``SETTINGS``."""
    if not settings:
        return None
    return f"settings: key=value arguments override {settings}"


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``selected`` (or, when None, every) subcommand gets its arguments."""
    parser = argparse.ArgumentParser(prog="physcene", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"physcene {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text, settings) in subcommands().items():
        p = sub.add_parser(name, help=help_text, description=help_text, epilog=_epilog(settings))
        if selected is None or name == selected:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            for action in p._actions:  # nested actions (data synth) repeat the note
                if isinstance(action, argparse._SubParsersAction):
                    for nested in action.choices.values():
                        nested.epilog = nested.epilog or p.epilog
            p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # also while the subcommand's modules load (torch, Warp: seconds)
        pass
    # Out of the handler the interrupted frames are let go: their progress bars close (and redraw
    # themselves) now, not at exit after the message, which stays the last line.
    gc.collect()
    print("physcene: interrupted", file=sys.stderr)
    return 130


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # the first word that is not an option names the subcommand (top-level takes only -h, --version)
    invoked = next((a for a in argv if not a.startswith("-")), "")
    parser = build_parser(invoked if invoked in subcommands() else "")
    args, extra = parser.parse_known_args(argv)
    unknown = [a for a in extra if "=" not in a or a.startswith("-")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.overrides = [a for a in extra if a not in unknown]
    try:
        return int(args._run(args) or 0)
    except _INPUT_ERRORS as exc:
        print(f"physcene {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
