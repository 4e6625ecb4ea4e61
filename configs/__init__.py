"""omegaconf YAML defaults, installed as ``physcene.configs``; see :mod:`physcene.config`."""
