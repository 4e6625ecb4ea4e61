"""The training configs: ``configs/train/base.yaml`` plus a small file per model, composed by
``physcene.config.load_config`` (base, then the model file, then the overrides)."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from physcene.commands.train import training_config
from physcene.config import ConfigError, load_config

# (name, source, dtype, arch.hidden_size, sft lr, pada global batch, pada.constrained, anchors.cache,
#  ablation.n_test, model.path required): the values of the configs before they were composed
EXPECTED = [
    ("tiny", "scratch", "float32", 96, 3.0e-3, 8, False, "dynamic", 4, False),
    ("small", "scratch", "bfloat16", 512, 1.0e-3, 128, True, "fast", 200, False),
    ("cpu", "scratch", "float32", 256, 2.0e-3, 16, True, "dynamic", 96, False),
    ("qwen3_vl_8b", "pretrained", "bfloat16", None, 1.0e-5, 128, False, "dynamic", 200, True),
]


@pytest.mark.parametrize("row", EXPECTED, ids=[r[0] for r in EXPECTED])
def test_each_model_file_over_the_base_gives_the_models_values(row):
    name, source, dtype, hidden, sft_lr, pada_batch, constrained, cache, n_test, needs_path = row
    cfg = load_config(f"train/{name}")
    assert "defaults" not in cfg and cfg.name == name
    assert (cfg.model.source, cfg.model.dtype, cfg.model.arch.get("hidden_size")) == (source, dtype, hidden)
    assert cfg.sft.learning_rate == pytest.approx(sft_lr) and cfg.sft.lr_scheduler_type == "cosine"
    assert (cfg.pada.global_batch_size, cfg.pada.constrained, cfg.anchors.cache) == (pada_batch, constrained,
                                                                                   cache)
    assert cfg.ablation.n_test == n_test and OmegaConf.is_missing(cfg.model, "path") == needs_path
    # the base's keys reach every model: the paper's PADA settings, the extensions off
    assert (cfg.pada.alpha, cfg.pada.beta, cfg.pada.num_generations, cfg.pada.lora.r) == (0.1, 0.04, 4, 16)
    assert cfg.pada.object_credit == 0.0 and cfg.pada.denoise == 0.0 and cfg.pada.nonfinite_probe == 0
    assert cfg.pada.output_dir == f"runs/{name}/pada"  # interpolations resolve after the merge


@pytest.mark.parametrize("name", ["tiny", "small", "cpu", "qwen3_vl_8b"])
def test_old_names_and_the_cli_name_read_the_same_config(name):
    composed = OmegaConf.to_container(load_config(f"train/{name}"), resolve=False)
    assert OmegaConf.to_container(load_config(f"train_{name}"), resolve=False) == composed
    assert OmegaConf.to_container(training_config(name), resolve=False) == composed
    assert training_config(name, ["pada.alpha=0.5"]).pada.alpha == 0.5  # overrides come last


def test_a_defaults_entry_that_names_no_file_is_named(tmp_path):
    (tmp_path / "model.yaml").write_text("defaults: [bsae]\nname: x\n")
    with pytest.raises(ConfigError, match="defaults names 'bsae'"):
        load_config(str(tmp_path / "model.yaml"))
    (tmp_path / "base.yaml").write_text("seed: 1\nname: base\n")
    (tmp_path / "model.yaml").write_text("defaults: [base]\nname: x\n")
    cfg = load_config(str(tmp_path / "model.yaml"))
    assert (cfg.seed, cfg.name) == (1, "x")
