"""TTO settings: :class:`TTOConfig` (``configs/tto.yaml``), every check in ``__post_init__``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from physcene.config import load_dataclass

__all__ = ["IN_MODES", "TTOConfig"]

IN_MODES = ("slide", "frozen")
"""How ``in`` children are parametrised (see :attr:`TTOConfig.in_children`)."""


@dataclass(kw_only=True)
class TTOConfig:
    """TTO settings (``configs/tto.yaml``); lengths in cm unless the name says otherwise."""

    steps: int = 100
    """Adam iterations (paper: 100)."""
    lr: float = 0.01
    """Adam step size in metres / radians (paper: 0.01)."""
    lr_final: float = 0.01
    """Learning rate reached at the last step by cosine decay (= lr: constant, the paper's)."""
    lambda_sdf: float = 10.0
    """Weight of the penetration energy, taken in metres (engine cm / 100)."""
    lambda_rel: float = 5.0
    """Weight of the structure term (support + near hinges, metres)."""
    lambda_reg: float = 1.0
    """Weight of ‖ξ − ξ_init‖² (metres², radians²)."""
    lambda_zone: float = 10.0
    """Weight of the zone term (metres)."""
    contact_gap_cm: float = 1e-5
    """An ``on`` child rests this far above its support's top: float32 rounding of a zero gap
    reads as ~1e-7 cm penetration; the gap is far below the 1e-4 cm placement requirement."""
    reattach_gap_cm: float = 3.0
    """A table-level object hovering over / sunk into a support by less than this is optimised as
    ``on`` it (0 disables; see :func:`physcene.tto.problem.reattach`)."""
    separate_deep: bool = True
    """Before the optimisation, move apart penetrating table-level pairs where one object stands
    deep in the other's footprint (coincident, or sunk past half its width): the penetration energy
    of such a pair has a local minimum at coincidence (every surface sample of one lies on the
    other's surface), so gradient steps would not part them. The later-written object (with its
    stack) moves sideways the shortest way out of the other's footprint box; coincident ones along
    the golden angle of their rank, a deterministic symmetry break (docs/tto.md)."""
    in_children: str = "slide"
    """``slide``: an ``in`` child's (x, y, yaw) in its container's frame are parameters (z offset held,
    footprint kept inside the container's), so a content modelled into its container's wall can be
    fixed; ``frozen``: the paper's rigid container body (docs/tto.md, "in children")."""
    in_lr_scale: float = 0.25
    """``slide`` only: an ``in`` child's (u, v) take Adam steps of this fraction of ``lr`` (0.25 cm),
    smaller than its container's clearance, so a content does not step into a wall; in (0, 1]."""
    in_lift_cm: float = 3.0
    """``slide`` only: a content may also rise by up to this much in its container (never so far that
    less than 55 % of its height stays inside the container's z-range, the graph's ``in`` test
    needs 50 %), so a content sunk into its container's floor can come out (0: z offset fixed)."""
    footprint_proxy: bool = True
    """Add the footprint-overlap proxy of pairs that penetrate at the start (see docs/tto.md)."""
    near_margin_cm: float = 0.5
    """Slack a near direction keeps over the axis tie (never more than the input had)."""
    stop_energy_cm: float = 1e-3
    """Optimised energy at or below this counts as collision-free (early stop, best iterate)."""
    stop_violation_cm: float = 0.01
    """Hinge terms at or below this count as met (early stop)."""
    check_every: int = 10
    """Host check for "every scene stopped" every k steps (>= 1)."""
    early_stop: bool = True
    """Freeze each scene at its first collision-free iterate that meets the hinges."""
    collision_depth_cm: float = 0.1
    """Reporting: pairs deeper than this are residual collisions."""
    zone_tolerance_cm: float = 0.1
    """Reporting: footprints further outside the zone than this are reported."""
    device: str = "cpu"
    """Torch device of the optimisation."""
    report_relations: bool = True
    """Rebuild each result's graph and measure relation preservation (host work)."""
    batch_size: int = 512
    """Scenes per optimisation batch in :func:`physcene.tto.repair` (>= 1)."""

    def __post_init__(self) -> None:
        if self.in_children not in IN_MODES:
            raise ValueError(f"in_children must be one of {list(IN_MODES)}, got {self.in_children!r}")
        if not 0 < self.in_lr_scale <= 1:
            raise ValueError(f"in_lr_scale must be in (0, 1], got {self.in_lr_scale}")
        if self.steps < 0 or self.lr <= 0 or self.check_every < 1 or self.batch_size < 1:
            raise ValueError(f"steps >= 0, lr > 0, check_every >= 1, batch_size >= 1 required, "
                             f"got steps={self.steps} lr={self.lr} check_every={self.check_every} "
                             f"batch_size={self.batch_size}")

    @classmethod
    def load(cls, overrides: Sequence[str] = ()) -> TTOConfig:
        """``configs/tto.yaml`` with ``key=value`` overrides (a bad value: :class:`ConfigError`)."""
        return load_dataclass(cls, "tto", list(overrides))
