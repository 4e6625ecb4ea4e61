"""The ``physcene`` command: one entry point, one module per subcommand.

Each module in :mod:`physcene.commands` defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; they are found here without a central list, so adding a subcommand is
adding a file. ``NAME``, ``HELP`` and the optional ``SETTINGS`` (the config file its ``key=value``
settings override, and the page that documents them) are string literals read from the source
without importing it, and only the invoked subcommand's module is imported: the modules pull in
torch, Warp and trimesh, and importing all of them cost every command several seconds of start-up. Expected
errors (bad input files, bad configs) print one line and exit 2; they never print a traceback.

A word of the form ``key=value`` (a dotted name, ``=``, anything) is a setting wherever it stands,
also among a command's paths (``physcene settle data.jsonl settle.duration_s=4``), unless it is the
value of an option (``--generator endpoint:http://host/v1?a=b``). A command without ``SETTINGS``
takes none: a setting given to it is an error rather than ignored.
"""

from __future__ import annotations

import argparse
import ast
import gc
import importlib
import importlib.util
import os
import pkgutil
import re
import sys
from pathlib import Path

from physcene import __version__, commands

__all__ = ["main"]

# Error types that mean "the user's input was wrong": one line, no traceback.
_INPUT_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, IsADirectoryError,
                                                   PermissionError, KeyError)


# A settings word: a dotted name, "=", a value (a path such as runs/lr=1e-4/x.json is not one).
_SETTING = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]*=")


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


def _epilog(settings: str) -> str:
    """The ``--help`` note on ``key=value`` settings, from the command's ``SETTINGS``."""
    if not settings:
        return "settings: this command takes no key=value settings"
    return f"settings: key=value arguments override {settings}"


_MAIN_EPILOG = ("settings: commands take key=value arguments that override their config file "
                "(configs/*.yaml); each command's --help names the file and the page of docs/ that "
                "documents it. --quiet turns progress bars off, --json prints one JSON document.")


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``selected`` (or, when None, every) subcommand gets its arguments."""
    parser = argparse.ArgumentParser(prog="physcene", description=__doc__.splitlines()[0],
                                     epilog=_MAIN_EPILOG)
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


def _options(parser: argparse.ArgumentParser) -> dict[str, bool]:
    """Option strings of ``parser`` (and its nested subcommands): whether each takes a value."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for nested in action.choices.values():
                found.update(_options(nested))
        else:
            found.update(dict.fromkeys(action.option_strings, action.nargs != 0))
    return found


def _split_settings(argv: list[str], parser: argparse.ArgumentParser) -> tuple[list[str], list[str]]:
    """(``key=value`` settings, the other words): settings are taken out before argparse sees the
    words, so that a command's ``PATH...`` never swallows them."""
    options = _options(parser)

    def is_value(k: int) -> bool:  # argv[k] follows an option that takes it (abbreviated too: --gen)
        prev = argv[k - 1] if k else ""
        if prev in options:
            return options[prev]
        return prev.startswith("--") and any(o.startswith(prev) and v for o, v in options.items())

    settings, words = [], []
    for k, word in enumerate(argv):
        (words if is_value(k) or not _SETTING.match(word) else settings).append(word)
    return settings, words


def main(argv: list[str] | None = None) -> int:
    try:
        status = _main(list(sys.argv[1:] if argv is None else argv))
        sys.stdout.flush()  # here, not at exit, where a closed pipe would print a warning
        return status
    except BrokenPipeError:
        # The reader went away (physcene assets list | head -1): stop quietly. Python flushes stdout
        # again at exit, so point it at devnull first (the recipe of Python's signal docs).
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:  # also while the subcommand's modules load (torch, Warp: seconds)
        pass
    # Out of the handler the interrupted frames are let go: their progress bars close (and redraw
    # themselves) now, not at exit after the message, which stays the last line.
    gc.collect()
    print("physcene: interrupted", file=sys.stderr)
    return 130


def _main(argv: list[str]) -> int:
    # the first word that is neither an option nor a setting names the subcommand (top-level takes
    # only -h, --version)
    invoked = next((a for a in argv if not a.startswith("-") and not _SETTING.match(a)), "")
    table = subcommands()
    parser = build_parser(invoked if invoked in table else "")
    settings, words = _split_settings(argv, parser)
    args, extra = parser.parse_known_args(words)
    unknown = [a for a in extra if "=" not in a or a.startswith("-")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    args.overrides = settings + [a for a in extra if a not in unknown]
    if args.overrides and not table[args.command][2]:
        print(f"physcene {args.command}: error: this command takes no key=value settings, got "
              f"{' '.join(args.overrides)}", file=sys.stderr)
        return 2
    try:
        return int(args._run(args) or 0)
    except (*_INPUT_ERRORS, ModuleNotFoundError) as exc:  # a missing dependency (Warp, MuJoCo): one line
        print(f"physcene {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
