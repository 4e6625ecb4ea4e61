"""key=value settings: an unknown key is one clear error naming the key and the config file
(issue 31, item 1), through the CLI, with no traceback and no output written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from physcene.config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "office_table.layout.json"


@pytest.mark.parametrize("argv", [
    ["demo", "nn=5"],
    ["eval", "judgee=rule", "--n", "1"],
    ["export", str(EXAMPLE), "--format", "glb", "foo=1"],
    ["train", "sft", "--config", "tiny", "sft.max_stepz=1"],
])
def test_an_unknown_setting_is_one_error_naming_key_and_file(argv, tmp_path):
    out = tmp_path / "out"
    if argv[0] == "export":
        argv = [*argv, "-o", str(out)]
    run = subprocess.run([sys.executable, "-m", "physcene.cli", *argv], capture_output=True, text=True,
                         cwd=tmp_path, timeout=300)
    key = argv[-1].split("=")[0] if argv[0] != "export" else "foo"
    if argv[0] == "eval":
        key = "judgee"
    assert run.returncode != 0
    assert f".yaml: unknown keys ['{key}']" in run.stderr
    assert "Traceback" not in run.stderr
    assert not out.exists() and not (tmp_path / "physcene-demo").exists()


def test_known_and_dataclass_keys_still_load():
    assert load_config("eval", ["n=3", "render_labels=true"]).n == 3
    assert load_config("train_tiny", ["sft.max_steps=1"]).sft.max_steps == 1
    with pytest.raises(ConfigError, match=r"unknown keys \['sft.max_stepz'\]"):
        load_config("train_tiny", ["sft.max_stepz=1"])
    assert load_config("reward", ["max_overlapping_pairs=5"], known=["max_overlapping_pairs"]) is not None


def test_a_value_takes_the_type_of_the_yaml_default():
    assert load_config("demo", ["n=3"]).n == 3
    assert load_config("export", ["settle.duration_s=4"]).settle.duration_s == 4.0  # an int, as float
    assert load_config("eval", ["device=0"]).device == "0"  # a string default stays a string
    # an interpolation is checked unresolved, then resolved against the whole config
    cfg = load_config("train_tiny", ["sft.output_dir=${output_dir}/x", "sft.max_steps=${seed}"])
    assert cfg.sft.output_dir == f"{cfg.output_dir}/x" and cfg.sft.max_steps == cfg.seed
    for override, words in (("n=abc", "n='abc': expected an integer"),
                            ("n=2.5", "n=2.5: expected an integer"),
                            ("repair=1", "repair=1: expected true or false"),
                            ("judge_image_size=5", "judge_image_size=5: expected a list"),
                            ("split=[a]", "split=['a']: expected a single value")):
        with pytest.raises(ConfigError, match=r"configs/demo\.yaml: ") as exc:
            load_config("demo", [override])
        assert words in str(exc.value)
