"""Bad input through the real CLI: one clear error naming the key, field or file, no traceback, no
output left behind (issue 31, items 1 and 2).

The cases that used to print a traceback, and the closed pipe, run ``python -m physcene.cli`` in a
subprocess; the others call :func:`physcene.cli.main` in-process, where an exception that escapes
the command fails the test just as a traceback would."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from physcene import cli

ROOT = Path(__file__).resolve().parents[2]
ZONE = [0, 100, 0, 60]
CUP = {"instance": "cup_0", "position": [20, 20, 5], "size": [8, 8, 10]}


def _layout(**fields) -> dict:
    return {"item_placement_zone": ZONE, "objects": [CUP], **fields}


def _physcene(*argv: str, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "physcene.cli", *argv], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=timeout)


def _strict_json(text: str):
    return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON output"))


def _one_error(err: str, *words: str) -> None:
    """``err`` holds exactly one error line, naming every word, and no traceback."""
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if "error" in line]
    assert len(lines) == 1, err
    assert all(w in lines[0] for w in words), (lines[0], words)


@pytest.fixture(scope="module")
def bad(tmp_path_factory) -> dict[str, Path]:
    """One tiny layout file per way of being wrong, and a good one."""
    folder = tmp_path_factory.mktemp("bad")
    texts = {
        "good": json.dumps(_layout()),
        "empty": json.dumps({"item_placement_zone": ZONE, "objects": []}),
        "no_objects": json.dumps({"item_placement_zone": ZONE}),
        "huge_size": json.dumps(_layout(objects=[{**CUP, "size": [1e30, 8, 10]}])),
        "far_position": json.dumps(_layout(objects=[{**CUP, "position": [20, 5000, 5]}])),
        "digits": json.dumps(_layout(objects=[{**CUP, "position": [20, 20, 5]}])).replace(
            "[20, 20, 5]", "[2" + "0" * 400 + ", 20, 5]"),
        "deep": "[" * 100_000 + "]" * 100_000,
    }
    paths = {}
    for name, text in texts.items():
        paths[name] = folder / f"{name}.json"
        paths[name].write_text(text)
    return paths


# field named in the error of each bad file (None: the file alone)
BAD = {"no_objects": "field 'objects'", "huge_size": "object 'cup_0', field 'size'",
       "far_position": "object 'cup_0', field 'position'", "digits": "field 'position'", "deep": None}


# --- item 1: settings ---------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["demo", "n=abc"], ["n='abc'", "demo.yaml", "expected an integer"]),  # was a traceback
    (["train", "sft", "--config", "tiny", "sft.max_steps=abc"], ["sft.max_steps='abc'", "train/tiny.yaml"]),
])
def test_a_bad_value_names_the_key_and_file_before_anything_is_written(argv, words, tmp_path):
    done = _physcene(*argv, cwd=tmp_path)
    assert done.returncode == 2
    _one_error(done.stderr, *words)
    assert list(tmp_path.iterdir()) == []  # no physcene-demo/, no half-made tokenizer folder


def test_eval_names_a_bad_n(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["eval", "n=abc"]) == 2  # was "invalid literal for int()"
    _one_error(capsys.readouterr().err, "n='abc'", "eval.yaml", "expected an integer")
    assert list(tmp_path.iterdir()) == []
    assert cli.main(["eval", "temperature=-0.5"]) == 2
    _one_error(capsys.readouterr().err, "temperature=-0.5", "eval.yaml", "expected 0 (greedy)")
    assert list(tmp_path.iterdir()) == []


def test_settings_after_paths_are_settings(bad, capsys):
    # settle's PATH... used to take the settings as paths, simulate, then fail on them
    assert cli.main(["settle", str(bad["empty"]), "settle.duration_z=4", "--quiet"]) == 2
    _one_error(capsys.readouterr().err, "settle.duration_z", "export.yaml")
    assert cli.main(["settle", str(bad["empty"]), "settle.duration_s=0.1", "--json", "--quiet"]) == 0
    doc = _strict_json(capsys.readouterr().out)
    assert [s["path"] for s in doc["scenes"]] == [str(bad["empty"])]
    assert cli.main(["check", str(bad["good"]), "margin_cm=wide"]) == 2
    _one_error(capsys.readouterr().err, "margin_cm='wide'", "physics.yaml")


def test_an_option_value_with_an_equals_sign_stays_the_options():
    url = "endpoint:http://127.0.0.1:8000/v1?key=v"
    for flag in ("--generator", "--gen"):  # argparse takes abbreviations
        argv = ["eval", flag, url, "n=3", "--repair", "seed=1"]
        assert cli._split_settings(argv, cli.build_parser("eval")) == (
            ["n=3", "seed=1"], ["eval", flag, url, "--repair"])


def test_a_command_without_settings_refuses_them(capsys, tmp_path):
    assert cli.main(["view", str(tmp_path / "x.json"), "port=1"]) == 2
    _one_error(capsys.readouterr().err, "takes no key=value settings", "port=1")


@pytest.mark.parametrize("name", sorted(cli.subcommands()))
def test_every_help_says_where_settings_are_and_spells_quiet_alike(name, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([name, "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    settings = cli.subcommands()[name][2]
    assert ("key=value arguments override configs/" in text and "docs/" in text if settings
            else "this command takes no key=value settings" in text)
    assert not any(flag in text for flag in ("--no-progress", "--progress", "--silent", "--no-bar"))


def test_version_and_top_level_help(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert "key=value" in capsys.readouterr().out
    assert cli.build_parser("assets").parse_known_args(["assets", "bake", "--quiet"])[0].quiet


# --- item 2: layout files -----------------------------------------------------------------------

def test_check_names_each_bad_file_once(bad, capsys):
    names = ["good", "empty", *BAD]
    assert cli.main(["check", *(str(bad[n]) for n in names)]) == 2
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert "Traceback" not in text
    for name, field in BAD.items():
        assert text.count(str(bad[name])) == 1, name  # each error once, not on stdout and stderr
        (line,) = [line for line in captured.err.splitlines() if str(bad[name]) in line]
        assert field is None or field in line
    assert f"{bad['empty']}: 0 objects" in captured.out and f"{bad['good']}: 1 objects" in captured.out


def test_settle_json_is_strict_and_names_each_bad_file(bad, capsys):
    assert cli.main(["settle", *(str(bad[n]) for n in BAD), "--json", "--quiet"]) == 2
    captured = capsys.readouterr()
    doc = _strict_json(captured.out)  # no scene settled: the rates are null, not NaN
    assert doc["stability_rate"] is None and doc["object_stability_rate"] is None
    assert [s["path"] for s in doc["scenes"]] == [str(bad[n]) for n in BAD]
    assert all(captured.err.count(str(bad[n])) == 1 for n in BAD)


@pytest.mark.parametrize("name", sorted(BAD))
def test_repair_and_export_refuse_a_bad_file_and_write_nothing(name, bad, tmp_path, capsys):
    fixed, exported = tmp_path / "fixed.json", tmp_path / "x"
    for argv, out in ((["repair", str(bad[name]), "-o", str(fixed)], fixed),
                      (["export", str(bad[name]), "--format", "mjcf", "-o", str(exported)], exported)):
        assert cli.main(argv) == 2
        _one_error(capsys.readouterr().err, str(bad[name]), *([BAD[name]] if BAD[name] else []))
        assert not out.exists()


def test_tracebacks_of_old_are_one_line_in_a_real_process(bad, tmp_path):
    # int too large, RecursionError and an AttributeError (no objects) escaped as tracebacks
    done = _physcene("check", str(bad["digits"]), str(bad["deep"]), str(bad["empty"]), cwd=tmp_path)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert [line for line in done.stderr.splitlines() if "error" in line] == [
        f"physcene check: error: {bad['digits']}, object 'cup_0', field 'position': "
        "number too large (401 digits)",
        f"physcene check: error: {bad['deep']}: invalid JSON: nested too deeply"]
    assert f"{bad['empty']}: 0 objects" in done.stdout


def test_check_reads_a_synth_folder_and_skips_its_stats(tmp_path, capsys):
    out = tmp_path / "synth"
    assert cli.main(["data", "synth", "--out", str(out), "--n", "2", "--measure", "no", "--quiet"]) == 0
    capsys.readouterr()
    assert (out / "test_stats.json").is_file()
    assert cli.main(["check", str(out)]) == 0
    captured = capsys.readouterr()
    assert "error" not in captured.err and "test_stats" not in captured.out
    assert [line.split(": ")[0] for line in captured.out.splitlines()] == [f"{out / 'test.jsonl'}:{k}"
                                                                           for k in (1, 2)]


@pytest.mark.parametrize("make_dir", [True, False])
def test_repair_into_a_folder(make_dir, bad, tmp_path, capsys):
    folder = tmp_path / "newdir"
    if make_dir:
        folder.mkdir()
    assert cli.main(["repair", str(bad["good"]), "-o", f"{folder}/", "steps=2", "--quiet"]) == 0
    capsys.readouterr()
    assert (folder / "good.json").is_file() and (folder / "good.report.json").is_file()


def test_a_closed_pipe_ends_quietly(tmp_path):
    # the reader is gone before the command writes (physcene assets list | head -0)
    proc = subprocess.Popen([sys.executable, "-m", "physcene.cli", "assets", "list"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0
    assert "Traceback" not in err and "BrokenPipe" not in err, err
