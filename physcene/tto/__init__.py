"""Hierarchy-constrained test-time optimisation (paper Sec. "Hierarchy-Constrained TTO").

min_ξ λ_sdf·L_sdf + λ_rel·L_rel(G) + λ_reg·‖ξ − ξ_init‖² + λ_zone·L_zone, batched over scenes of
different sizes (padded slots, masks) in one Adam optimisation. docs/tto.md has the formulas.

One stage per module: :mod:`~physcene.tto.config` (:class:`TTOConfig`),
:mod:`~physcene.tto.problem` (scenes -> padded tensors, the parametrisation ξ and its forward
kinematics), :mod:`~physcene.tto.losses` (the objective's terms), :mod:`~physcene.tto.optimise`
(the Adam loop), :mod:`~physcene.tto.report` (the typed :class:`TTOReport`, :func:`summarize`)
and :mod:`~physcene.tto.pipeline` (:func:`repair`: batches and the second pass).

Every scene returns its best iterate (lowest penetration energy; among collision-free iterates the
lowest remaining objective), and never more energy than its input: if nothing beat the input,
the input is returned unchanged.
"""

from physcene.relations import relation_preservation
from physcene.tto.config import IN_MODES, TTOConfig
from physcene.tto.optimise import TTOSolution, optimise
from physcene.tto.pipeline import repair
from physcene.tto.problem import TTOProblem, build_problem, forward_kinematics
from physcene.tto.report import RelationReport, ResidualCollision, TTOReport, TTOResult, summarize

__all__ = ["IN_MODES", "RelationReport", "ResidualCollision", "TTOConfig", "TTOProblem", "TTOReport",
           "TTOResult", "TTOSolution", "build_problem", "forward_kinematics", "optimise",
           "relation_preservation", "repair", "summarize"]
