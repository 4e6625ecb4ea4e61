"""Warp kernels and their host launchers: the only place in physcene that imports ``warp``."""
