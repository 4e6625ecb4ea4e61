"""Issue 5 acceptance with the real engine and asset library, on two inputs:

- ``noisy``: :func:`physcene.data.noisy.noisy_scenes` (stacks, containers, groups pushed into
  their neighbours), 16 objects per scene;
- ``synthetic``: the synthetic benchmark's ``test`` split (:func:`physcene.data.synthesize`:
  MesaTask-style layouts with interpenetration / sunk / hover noise), 1-20+ objects.

Every pair counts ("no pair deeper than 1 mm"), a container and its contents included;
``collision_free_excluding_frozen`` (``in_children=frozen``) and ``scenes_with_in_body_residual``
are printed beside it. The 200-scene runs are ``slow`` (about a minute each on 2 CPU cores) and
run only when asked:
    PHYSCENE_SLOW=1 python -m pytest tests/tto/test_tto_acceptance.py -q -s -k 200
they print the figures (docs/tto.md, "Measured"); the normal suite runs the same checks on a few
scenes.
"""

from __future__ import annotations

import json

import pytest

from physcene.data.noisy import noisy_scenes
from physcene.physics import PhysicsEngine
from physcene.tto import TTOConfig, repair, summarize


def _synthetic(n: int, seed: int):
    from physcene.data import synthesize
    from physcene.layout import load_layout

    return [load_layout(r["layout"], source=r["id"]) for r in synthesize("test", n=n, seed=seed)]


def _check(scenes, min_collided: float, in_children: str = "slide", min_free: float = 0.95) -> dict:
    """Repair ``scenes`` and assert the issue's measures; ``min_free`` = fraction of scenes with no
    pair (every pair counted) deeper than 1 mm (the issue: 0.95)."""
    results = repair(scenes, TTOConfig(in_children=in_children), PhysicsEngine())
    figures = summarize(results)
    collided = sum(r.report.max_depth_before_cm > 0.1 for r in results)
    figures["input_scenes_deeper_than_1mm"] = collided
    figures["in_children"] = in_children
    print(json.dumps(figures, indent=1))
    assert collided >= min_collided * len(scenes)  # the noise really collides
    assert figures["collision_free"] >= min_free
    assert figures["in_on_kept"] == 1.0 and figures["in_on_edges"] >= len(scenes) / 2
    assert figures["near_kept"] >= 0.95
    assert figures["energy_increased"] == 0
    return figures


def test_acceptance_noisy_20():
    _check(noisy_scenes(20, 16, seed=7), 0.7)


def test_acceptance_synthetic_8():
    _check(_synthetic(8, seed=3), 0.25)


@pytest.mark.slow
@pytest.mark.parametrize("in_children", ["slide", "frozen"])
def test_acceptance_noisy_200(in_children):
    _check(noisy_scenes(200, 16, seed=2026), 0.7, in_children)


@pytest.mark.slow
@pytest.mark.parametrize("in_children", ["slide", "frozen"])
def test_acceptance_synthetic_200(in_children):
    """The issue asks >= 95 % collision-free (every pair); measured 96.0 % with ``slide`` (the
    default; the issue's floor is asserted) and 71.5 % with ``frozen`` (the paper's rigid
    contents: a regression guard at the measured figure, docs/tto.md)."""
    _check(_synthetic(200, seed=0), 0.4, in_children, min_free=0.95 if in_children == "slide" else 0.7)
