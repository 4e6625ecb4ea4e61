"""Subcommands of ``physcene``: one module each (see :mod:`physcene.cli`)."""
