"""The ``physcene`` entry point: discovery of subcommands and lazy import."""

import argparse
import subprocess
import sys

import pytest

from physcene import cli


def test_every_subcommand_is_discovered_and_builds_its_arguments():
    table = cli.subcommands()
    assert {"ctrc", "check", "reward", "bench", "repair", "assets", "data", "eval", "demo", "export",
            "settle", "train"} <= set(table)
    parser = cli.build_parser()  # imports every module: each must define add_arguments and run
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for name in table:
        assert callable(action.choices[name].get_default("_run")), name


def test_top_level_help_imports_no_subcommand_module():
    code = ("import sys; from physcene import cli\n"
            "try: cli.main(['--help'])\nexcept SystemExit: pass\n"
            "heavy = [m for m in ('torch', 'warp', 'trimesh') if m in sys.modules]\n"
            "print('HEAVY', heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "HEAVY []" in out


def test_unknown_subcommand_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["no-such-command"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err
