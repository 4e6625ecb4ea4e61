"""physcene.config: omegaconf files with key=value overrides, typed into config dataclasses."""

import pytest

from physcene.config import ConfigError, load_config, load_dataclass
from physcene.physics import PhysicsConfig
from physcene.reward import RewardConfig


def test_overrides_merge_over_the_file():
    cfg = load_config("physics", ["margin_cm=0.5"])
    assert cfg.margin_cm == 0.5 and cfg.floating_tolerance_cm == 1.0


def test_values_take_the_type_of_the_field_default():
    cfg = load_dataclass(PhysicsConfig, "physics", ["lanes_cuda=64", "margin_cm=1"])
    assert cfg.lanes_cuda == 64 and isinstance(cfg.lanes_cuda, int)
    assert cfg.margin_cm == 1.0 and isinstance(cfg.margin_cm, float)
    assert load_dataclass(RewardConfig, "reward", ["table_term=true"]).table_term is True


@pytest.mark.parametrize("override, words", [
    (["nope=1"], "unknown keys ['nope']"),
    (["lanes_cuda=1.5"], "lanes_cuda=1.5"),
    (["margin_cm=wide"], "margin_cm='wide'"),
])
def test_bad_keys_and_values_name_the_file_and_key(override, words):
    with pytest.raises(ConfigError) as exc:
        load_dataclass(PhysicsConfig, "physics", override)
    assert "configs/physics.yaml" in str(exc.value) and words in str(exc.value)


def test_booleans_are_not_numbers():
    with pytest.raises(ConfigError, match="expected true or false"):
        load_dataclass(RewardConfig, "reward", ["table_term=3"])


def test_unknown_config_name_lists_the_known_ones():
    with pytest.raises(ConfigError, match="unknown config 'no_such'.*physics"):
        load_config("no_such")
