"""One config system: omegaconf YAML files under ``configs/`` overridden by ``key=value`` pairs.

``load_config("tto", ["steps=50", "lambda_sdf=20"])`` reads ``configs/tto.yaml`` (installed as the
package ``physcene.configs``) and merges the dotlist over it. ``train/tiny`` reads
``configs/train/tiny.yaml`` (``train_tiny`` too: ``<folder>_<name>`` finds ``<folder>/<name>.yaml``);
any other name that ends in ``.yaml`` or contains a path separator is read as a file path.

A file may list other files of its folder in a ``defaults`` key (``defaults: [base]``): they are
merged first, in order, then the file itself, then the overrides (the training configs: one
``configs/train/base.yaml`` and a small file per model).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

__all__ = ["ConfigError", "config_path", "load_config", "load_dataclass", "split_overrides"]


class ConfigError(ValueError):
    """A config name, file or override was wrong."""


def config_path(name: str) -> Path:
    """Where the config ``name`` lives (a file path is returned as given)."""
    base = resources.files("physcene.configs")
    if not name.endswith((".yaml", ".yml")):
        folder, _, rest = name.partition("_")
        for candidate in (name, f"{folder}/{rest}" if rest else None):  # train_tiny -> train/tiny
            for suffix in (".yaml", ".yml") if candidate else ():
                entry = base / f"{candidate}{suffix}"
                if entry.is_file():
                    return Path(str(entry))
    if name.endswith((".yaml", ".yml")) or "/" in name:
        path = Path(name)
        if not path.is_file():
            raise ConfigError(f"config file {name!r} does not exist")
        return path
    known = sorted(p.name.rsplit(".", 1)[0] for p in base.iterdir() if p.name.endswith(".yaml"))
    known += sorted(f"{d.name}/{p.name.rsplit('.', 1)[0]}" for d in base.iterdir() if d.is_dir()
                    for p in d.iterdir() if p.name.endswith(".yaml") and d.name != "accelerate")
    raise ConfigError(f"unknown config {name!r}; known: {', '.join(known)}")


def _has_key(cfg: DictConfig, key: str) -> bool:
    """Whether the dotted ``key`` names an entry of ``cfg`` (a required ``???`` value included)."""
    node = cfg
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node.keys():
            return False
        node = node._get_node(part)
    return True


def load_config(name: str, overrides: Sequence[str] = (), *, known: Sequence[str] = ()) -> DictConfig:
    """The config ``name`` (over the files its ``defaults`` key names), with ``key=value`` overrides
    merged over it. An override whose key the config does not have (nor ``known`` names) is a
    :class:`ConfigError` naming the key and the file it was looked up in."""
    path = config_path(name)
    cfg = _composed(path)
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise ConfigError(f"overrides must be key=value, got {bad}")
    keys = [o.split("=", 1)[0].strip() for o in overrides]
    unknown = [k for k in keys if k not in known and not _has_key(cfg, k)]
    if unknown:
        raise ConfigError(f"{path}: unknown keys {unknown} (settings are key=value over this file)")
    try:
        merged = OmegaConf.from_dotlist(list(overrides))
    except Exception as exc:  # omegaconf raises several types for malformed overrides
        raise ConfigError(f"bad override in {list(overrides)}: {exc}") from exc
    raw = OmegaConf.to_container(merged)  # unresolved: an override may be ${...} of the config
    for override in overrides:
        key = override.split("=", 1)[0].strip()
        default = _default_value(cfg, key)
        value = raw
        for part in key.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        try:
            OmegaConf.update(merged, key, _typed_like(value, default), merge=False)
        except ValueError as exc:
            raise ConfigError(f"{path}: {key}={value!r}: {exc} (the default is {default!r})") from None
    return OmegaConf.merge(cfg, merged)


_UNTYPED = object()  # an entry whose type the YAML does not fix: null, ???, an interpolation


def _default_value(cfg: DictConfig, key: str):
    """The value ``key`` has in the YAML, or ``_UNTYPED`` (not there, null, ``???``, ``${...}``)."""
    if not _has_key(cfg, key):
        return _UNTYPED
    node = cfg
    for part in key.split("."):
        node = node._get_node(part)
    if node._is_missing() or node._is_interpolation() or node._is_none():
        return _UNTYPED
    return OmegaConf.to_container(node) if isinstance(node, (DictConfig, ListConfig)) else node._value()


def _typed_like(value, default):
    """``value`` (an override, as YAML read it) with the type of ``default``, the value the YAML
    file gives that key: ``n=abc`` over ``n: 24`` is a ValueError, not a string that fails later.
    null is accepted everywhere (the configs use it for "off" / "all"); so is an interpolation."""
    if default is _UNTYPED or value is None or isinstance(value, str) and value.startswith("${"):
        return value
    if isinstance(default, list) and isinstance(value, str):
        return [value]  # `key=name` for a list of names: one name (valid_terms=floating)
    if isinstance(default, (dict, list)):
        if not isinstance(value, type(default)):
            raise ValueError(f"expected a {'mapping {k: v}' if isinstance(default, dict) else 'list [...]'}")
        return value
    if isinstance(value, (dict, list)):
        raise ValueError(f"expected a single value, got a {'mapping' if isinstance(value, dict) else 'list'}")
    if isinstance(default, str):  # device=0 is the string "0"; a boolean keeps its YAML spelling
        return str(value).lower() if isinstance(value, bool) else str(value)
    if isinstance(default, (bool, int, float)):
        return _coerce(value, type(default))
    return value


def _composed(path: Path, seen: tuple[Path, ...] = ()) -> DictConfig:
    """The YAML file ``path`` merged over the files of its folder that its ``defaults`` key names."""
    if path in seen:
        raise ConfigError(f"{path}: defaults loop through {[str(p) for p in seen]}")
    cfg = OmegaConf.load(path)
    names = cfg.pop("defaults", None)
    if names is None:
        return cfg
    names = [names] if isinstance(names, str) else list(names)
    parts = []
    for default in names:
        file = path.parent / f"{default}.yaml"
        if not file.is_file():
            raise ConfigError(f"{path}: defaults names {default!r}, but {file} does not exist")
        parts.append(_composed(file, (*seen, path)))
    return OmegaConf.merge(*parts, cfg)


def split_overrides(args: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split CLI leftovers into (``key=value`` overrides, other arguments)."""
    overrides = [a for a in args if "=" in a and not a.startswith("-")]
    rest = [a for a in args if a not in overrides]
    return overrides, rest


def _coerce(value, kind: type | None):
    """``value`` as ``kind`` (the type of the field's default); None keeps it as it is."""
    if kind is None or isinstance(value, kind) and not (kind is int and isinstance(value, bool)):
        return value
    if kind is bool:
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise ValueError("expected true or false")
    if kind is int:
        try:
            as_float = float(value) if not isinstance(value, bool) else math.nan
        except (TypeError, ValueError):
            as_float = math.nan
        if not as_float.is_integer():
            raise ValueError("expected an integer")
        return int(value) if isinstance(value, int) else int(as_float)
    if kind is float:
        try:
            number = float(value) if not isinstance(value, bool) else None
        except (TypeError, ValueError):
            number = None
        if number is None:
            raise ValueError("expected a number")
        if not math.isfinite(number):
            raise ValueError("expected a finite number")
        return number
    if kind is tuple and isinstance(value, str):
        return (value,)  # `key=name` for a tuple of names: one name, not its characters
    return kind(value)


def load_dataclass(cls, name: str, overrides: Sequence[str] = ()):
    """The flat config ``name`` (``configs/<name>.yaml`` + overrides) as an instance of ``cls``.

    ``cls`` is a dataclass whose fields are the config's keys; a value is converted to the type of
    the field's default. An unknown key, or a value of the wrong type, is a :class:`ConfigError`
    naming the file, the key and the value.
    """
    fields = [f.name for f in dataclasses.fields(cls)]
    cfg = OmegaConf.to_container(load_config(name, overrides, known=fields), resolve=True)
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(cfg) - set(known))
    if unknown:
        raise ConfigError(f"configs/{name}.yaml: unknown keys {unknown}; known: {sorted(known)}")
    values = {}
    for key, value in cfg.items():
        default = known[key].default
        kind = None if default is dataclasses.MISSING or default is None else type(default)
        try:
            values[key] = _coerce(value, kind)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"configs/{name}.yaml: {key}={value!r}: {exc}") from None
    try:
        return cls(**values)
    except ValueError as exc:  # the dataclass's own checks (__post_init__)
        raise ConfigError(f"configs/{name}.yaml: {exc}") from None
