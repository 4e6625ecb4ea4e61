"""The pieces a synthetic scene is built from (:mod:`physcene.data.synth`): object nodes with
sizes sampled from the category priors and a yaw, and the footprint geometry their placement
tests use (cm, rad)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from physcene.assets import CATEGORY_PRIORS

__all__ = ["FACING", "Node", "boxes_touch", "choose_yaw", "counts_as_in", "footprint_halfextents", "rotated",
           "rotated_rel", "sample_size", "uniform_offset", "weighted_choice"]


# Categories that face the viewer: yaw stays near 0 (or turns to face the table centre).
FACING = frozenset(
    {
        "monitor",
        "television",
        "mirror",
        "picture_frame",
        "clock",
        "laptop",
        "keyboard",
        "cash_register",
        "speaker",
        "receipt_printer",
        "lamp",
        "toaster",
        "coffee_maker",
        "game_console",
        "router",
        "tissue_box",
        "monitor_stand",
    }
)


@dataclass(eq=False)
class Node:
    """One object of a scene under construction (cm, rad)."""

    category: str
    size: np.ndarray  # (3,) w, d, h cm
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) cm
    yaw: float = 0.0  # rad
    parent: int | None = None  # index into the scene's node list, None = table
    relation: str = "near"
    group: str | None = None  # name of the hierarchy it belongs to


def sample_size(category: str, rng: np.random.Generator, clip_sigma: float) -> np.ndarray:
    """A size (w, d, h) cm from the category's prior, within ``clip_sigma`` standard deviations."""
    prior = CATEGORY_PRIORS[category]
    z = np.clip(rng.standard_normal(3), -clip_sigma, clip_sigma)
    size = np.asarray(prior.mean_cm) + z * np.asarray(prior.std_cm)
    return np.maximum(size, 0.3)


def footprint_halfextents(size: np.ndarray, yaw: float) -> tuple[float, float]:
    """Half extents (cm) of the axis-aligned box around a yawed w×d rectangle."""
    c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
    return 0.5 * (c * size[0] + s * size[1]), 0.5 * (s * size[0] + c * size[1])


def choose_yaw(category: str, rng: np.random.Generator) -> float:
    """A yaw (rad): near 0 for objects that face the viewer, else mostly 0 or ±90°, sometimes any."""
    if category in FACING:
        return float(np.deg2rad(rng.normal(0.0, 4.0)))
    u = rng.random()
    if u < 0.55:
        return 0.0
    if u < 0.75:
        return float(rng.choice([0.5 * math.pi, -0.5 * math.pi]))
    if u < 0.9:
        return float(np.deg2rad(rng.normal(0.0, 15.0)))
    return float(rng.uniform(-math.pi, math.pi))


def weighted_choice(rng: np.random.Generator, items: list, weights: list[float]):
    """One of ``items`` drawn with probability proportional to ``weights``."""
    w = np.asarray(weights, dtype=np.float64)
    return items[int(rng.choice(len(items), p=w / w.sum()))]


def rotated_rel(n: Node, yaw: float) -> np.ndarray:
    """(w, d) of the axis-aligned box around the node's footprint at ``yaw``, cm."""
    hx, hy = footprint_halfextents(n.size, yaw)
    return np.array([2.0 * hx, 2.0 * hy])


def boxes_touch(a: np.ndarray, b: np.ndarray, gap: float) -> bool:
    """Whether boxes [x0, x1, y0, y1] come closer than ``gap`` (cm)."""
    return bool(a[0] < b[1] + gap and b[0] < a[1] + gap and a[2] < b[3] + gap and b[2] < a[3] + gap)


def counts_as_in(container: Node, content: Node, z: float) -> bool:
    """The graph's ``in`` test (:mod:`physcene.graph`) with a margin: volume ratio ≥ 1.5 and at least 60 % of
    the content's height inside the container's z-range (footprints are inside by construction)."""
    if np.prod(container.size) < 1.5 * np.prod(content.size):
        return False
    inside = min(container.center[2] + 0.5 * container.size[2], z + 0.5 * content.size[2]) - max(
        container.center[2] - 0.5 * container.size[2], z - 0.5 * content.size[2]
    )
    return inside >= 0.6 * content.size[2]


def rotated(n: Node) -> np.ndarray:
    """(w, d) of the axis-aligned box around the node's footprint at its (relative) yaw, cm."""
    hx, hy = footprint_halfextents(n.size, n.yaw)
    return np.array([2.0 * hx, 2.0 * hy])


def uniform_offset(rng: np.random.Generator, half_range: float) -> float:
    """Uniform offset in [-half_range, half_range] (0 when there is no slack)."""
    return float(rng.uniform(-half_range, half_range)) if half_range > 0 else 0.0
