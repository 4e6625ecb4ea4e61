"""Importing the kernels neither initialises Warp nor changes its global settings: that happens at
the first launch (kernels/launch.py: init_warp)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted("physcene.kernels." + ".".join(p.relative_to(ROOT / "kernels").with_suffix("").parts)
                 for p in (ROOT / "kernels").rglob("*.py") if p.name != "__init__.py")

PROBE = """
import importlib, json, sys
import warp
import warp._src.context as context
level = warp.config.log_level
for name in sys.argv[1:]:
    importlib.import_module(name)
before = {"runtime": context.runtime is not None, "log_level_kept": warp.config.log_level == level}
import torch
from physcene.kernels.penetration import launch_support
launch_support(count=torch.ones(1, dtype=torch.int32), poses=torch.zeros(1, 1, 4),
               sizes=torch.ones(1, 1, 3), overlap_eps=0.01)
print(json.dumps({"before": before, "after": context.runtime is not None}))
"""


def test_kernel_modules_are_found():
    assert {"physcene.kernels.penetration", "physcene.kernels.launch", "physcene.kernels.ctrc_reader.scan",
            "physcene.kernels.sdf_bake"} <= set(MODULES)


def test_import_does_not_initialise_warp():
    """Every kernels module, and the engine and reward packages on top of them, in one fresh process."""
    modules = [*MODULES, "physcene.physics", "physcene.reward"]
    out = subprocess.run([sys.executable, "-c", PROBE, *modules], capture_output=True, text=True, check=True,
                         cwd=ROOT)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["before"] == {"runtime": False, "log_level_kept": True}
    assert result["after"]  # the first launch does initialise it
