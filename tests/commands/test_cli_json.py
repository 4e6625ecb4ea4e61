"""The options every command spells the same way: ``--json`` (one JSON document on stdout, nothing
else), ``--quiet`` (no progress bar on stderr), ``--version``, and the ``--help`` note on
``key=value`` settings. The JSON outputs run the real CLI in a subprocess, so that anything else
printed on stdout (a library's warning, a progress bar) would break ``json.loads``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from physcene import __version__, cli

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "office_table.layout.json"
LONG_COMMANDS = {  # argv that reaches --quiet; each shows a progress bar on stderr
    "check": ["check", "x.json"],
    "repair": ["repair", "x.json", "-o", "y.json"],
    "settle": ["settle", "x.json"],
    "eval": ["eval"],
    "demo": ["demo"],
    "generate": ["generate", "a desk"],
    "data synth": ["data", "synth", "--out", "d"],
    "data import-mesatask": ["data", "import-mesatask", "L", "--out", "d"],
}


def _physcene(*argv: str, cwd: Path) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "physcene.cli", *argv], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert done.returncode == 0, done.stderr
    return done


def _document(done: subprocess.CompletedProcess) -> dict:
    return json.loads(done.stdout, parse_constant=lambda c: pytest.fail(f"{c} in the JSON output"))


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """``data synth --n 2 --json --quiet``: the JSON document and the folder."""
    out = tmp_path_factory.mktemp("synth")
    done = _physcene("data", "synth", "--out", str(out), "--n", "2", "--json", "--quiet", cwd=out)
    assert "%|" not in done.stderr  # --quiet: no tqdm bar
    return _document(done), out


def test_data_synth_json(synth):
    doc, out = synth
    assert {"file", "stats_json", "stats_md", "stats"} <= set(doc)
    assert Path(doc["file"]) == out / "test.jsonl" and Path(doc["file"]).is_file()
    assert doc["stats"]["n"] == 2


def test_data_synth_shows_a_bar_unless_quiet_and_keeps_no_progress(tmp_path):
    shown = _physcene("data", "synth", "--out", str(tmp_path / "a"), "--n", "2", "--measure", "no",
                      cwd=tmp_path)
    assert "synth test" in shown.stderr and "synth test" not in shown.stdout
    hidden = _physcene("data", "synth", "--out", str(tmp_path / "b"), "--n", "2", "--measure", "no",
                       "--no-progress", cwd=tmp_path)  # the old spelling still works
    assert "%|" not in hidden.stderr
    help_text = _physcene("data", "synth", "--help", cwd=tmp_path).stdout
    assert "--no-progress" not in help_text and "--quiet" in help_text
    assert "key=value" in help_text  # a nested action repeats the settings note


def test_data_import_mesatask_json(tmp_path):
    scene = tmp_path / "Layout_info" / "office_table" / "s1" / "layout.json"
    scene.parent.mkdir(parents=True)
    scene.write_text(EXAMPLE.read_text())
    doc = _document(_physcene("data", "import-mesatask", str(tmp_path / "Layout_info"), "--out",
                              str(tmp_path / "out"), "--test-size", "0", "--json", "--quiet", cwd=tmp_path))
    assert [s["split"] for s in doc["splits"]] == ["train", "test"]
    assert doc["splits"][0]["n"] == 1 and Path(doc["splits"][0]["file"]).is_file()


def test_repair_json(tmp_path):
    doc = _document(_physcene("repair", str(EXAMPLE), "-o", str(tmp_path / "fixed.json"), "--json",
                              "--quiet", cwd=tmp_path))
    assert {"input", "output", "report", "summary", "scenes"} <= set(doc)
    assert Path(doc["output"]).is_file() and Path(doc["report"]).is_file()
    assert doc["summary"]["scenes"] == 1 and len(doc["scenes"]) == 1
    assert {"energy_before", "energy_after", "relations"} <= set(doc["scenes"][0])


def test_export_json(tmp_path):
    doc = _document(_physcene("export", str(EXAMPLE), "--format", "mjcf", "-o", str(tmp_path / "out"),
                              "--json", cwd=tmp_path))
    assert set(doc) == {"layout", "outputs"}
    (written,) = doc["outputs"]
    assert written["format"] == "mjcf" and Path(written["path"]).is_file()


def test_eval_json(tmp_path):
    done = _physcene("eval", "--n", "2", "--generator", "reference", "--out", str(tmp_path / "e"),
                     "--json", "--quiet", "render=0", cwd=tmp_path)
    doc = _document(done)
    assert {"split", "n", "report", "results", "methods"} <= set(doc)
    assert Path(doc["report"]).is_file() and Path(doc["results"]).is_file()
    assert {"summary", "by_level", "by_type"} <= set(doc["methods"]["Reference"])
    assert "%|" not in done.stderr  # --quiet: no tqdm bar


def test_demo_json(tmp_path):
    doc = _document(_physcene("demo", "--n", "2", "--out", str(tmp_path / "demo"), "--json", "--quiet",
                              "render=0", cwd=tmp_path))
    assert {"split", "n", "seconds", "report", "results", "renders", "methods"} <= set(doc)
    assert doc["n"] == 2 and set(doc["methods"]) == {"Reference", "Reference + TTO"}


def test_settle_shows_a_bar_unless_quiet(tmp_path):
    two = [str(EXAMPLE), str(EXAMPLE)]  # one scene shows no bar
    assert "%|" in _physcene("settle", *two, cwd=tmp_path).stderr
    done = _physcene("settle", *two, "--json", "--quiet", cwd=tmp_path)
    assert len(_document(done)["scenes"]) == 2
    assert "%|" not in done.stderr  # a tqdm bar: "settle: 50%|█████     | 1/2"


@pytest.mark.parametrize("name", sorted(LONG_COMMANDS))
def test_every_long_command_takes_quiet(name):
    argv = LONG_COMMANDS[name]
    args, _ = cli.build_parser(argv[0]).parse_known_args([*argv, "--quiet"])
    assert args.quiet is True


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"physcene {__version__}"


@pytest.mark.parametrize("name", sorted(n for n, (_, _, settings) in cli.subcommands().items() if settings))
def test_help_names_the_key_value_settings(name, capsys):
    with pytest.raises(SystemExit):
        cli.main([name, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "settings: key=value arguments override configs/" in text and "docs/" in text
