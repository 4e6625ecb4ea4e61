"""The TTO objective's terms, each (S,) per scene of a :class:`~physcene.tto.problem.TTOProblem`.

min_ξ λ_sdf·L_sdf + λ_rel·L_rel(G) + λ_reg·‖ξ − ξ_init‖² + λ_zone·L_zone (docs/tto.md has the
formulas). L_sdf is the engine's :func:`penetration` energy (plus the footprint-overlap proxy of
pairs that start in contact); L_rel = :func:`support_violation` (an ``on`` child's footprint may
not slide further off its support than it started; a hard projection with :func:`support_bounds`
follows every step) + :func:`near_violation` (each table-level object keeps the direction to its
reference); L_zone = :func:`zone_violation` (footprint corners outside the placement zone +
overlap depth with restricted zones).
"""

from __future__ import annotations

import torch

from physcene.tto.problem import CM, TTOProblem

__all__ = ["footprint_overlap_depth", "footprints", "near_violation", "penetration", "support_bounds",
           "support_violation", "zone_violation"]


def footprints(poses: torch.Tensor, sizes: torch.Tensor) -> torch.Tensor:
    """Yawed footprint corners (S, N, 4, 2) cm."""
    hw, hd = 0.5 * sizes[..., 0], 0.5 * sizes[..., 1]
    lx = torch.stack((-hw, hw, hw, -hw), dim=-1)
    ly = torch.stack((-hd, -hd, hd, hd), dim=-1)
    c, s = torch.cos(poses[..., 3:4]), torch.sin(poses[..., 3:4])
    return torch.stack((poses[..., 0:1] + c * lx - s * ly, poses[..., 1:2] + s * lx + c * ly), dim=-1)


def footprint_overlap_depth(problem: TTOProblem, poses: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """(S,) cm: Σ over contact pairs whose z-ranges overlap of the footprint-AABB penetration depth.

    Why: where one object stands in a thin one (a bottle in a tray's floor, both on the table) the
    SDF pushes only vertically, and z is held; this proxy gives the sideways direction out.
    """
    lo, hi = corners.amin(dim=2), corners.amax(dim=2)  # (S, N, 2)
    half_h = 0.5 * problem.sizes[..., 2]
    zlo, zhi = poses[..., 2] - half_h, poses[..., 2] + half_h

    def pick(t: torch.Tensor, k: int) -> torch.Tensor:
        idx = problem.contact[..., k]
        if t.dim() == 2:
            return torch.gather(t, 1, idx)
        return torch.gather(t, 1, idx.unsqueeze(-1).expand(-1, -1, t.shape[-1]))

    # the shortest of the four sideways moves that separates the boxes (also when one contains
    # the other, where the plain overlap width has no gradient)
    push = torch.minimum(pick(hi, 1) - pick(lo, 0), pick(hi, 0) - pick(lo, 1))  # (S, P, 2)
    z_overlap = torch.minimum(pick(zhi, 0), pick(zhi, 1)) - torch.maximum(pick(zlo, 0), pick(zlo, 1))
    depth = torch.relu(push.amin(dim=-1)) * (z_overlap > 0) * problem.contact_mask
    return depth.sum(-1)


def zone_violation(problem: TTOProblem, poses: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """(S,) cm: Σ corner distance outside the zone + Σ overlap depth with restricted zones."""
    z = problem.zone[:, None, None, :]
    outside = (torch.relu(z[..., 0] - corners[..., 0]) + torch.relu(corners[..., 0] - z[..., 1])
               + torch.relu(z[..., 2] - corners[..., 1]) + torch.relu(corners[..., 1] - z[..., 3]))
    total = (outside.sum(-1) * problem.mask).sum(-1)
    lo, hi = corners.amin(dim=2), corners.amax(dim=2)  # (S, N, 2) footprint AABB
    r = problem.restricted[:, None, :, :]  # (S, 1, R, 4)
    depth = torch.minimum(
        torch.minimum(hi[..., None, 0] - r[..., 0], r[..., 1] - lo[..., None, 0]),
        torch.minimum(hi[..., None, 1] - r[..., 2], r[..., 3] - lo[..., None, 1]))
    inside = torch.relu(depth) * problem.restricted_mask[:, None, :] * problem.mask[..., None]
    return total + inside.sum((1, 2))


def support_bounds(problem: TTOProblem, xi: torch.Tensor) -> torch.Tensor:
    """(S, N, 2) metres: how far an on (or sliding in) child's centre may sit from its parent's centre.

    Per axis of the parent frame, never further out than the input was and always allowed to be
    fully over the support: max(|u0|, |P − h(ψ)|), with h the child's half extent there.
    """
    psi = xi[..., 2]
    c, s = torch.cos(psi).abs(), torch.sin(psi).abs()
    hw, hd = 0.5 * problem.sizes[..., 0], 0.5 * problem.sizes[..., 1]
    half = torch.stack((c * hw + s * hd, s * hw + c * hd), dim=-1)
    return torch.maximum(problem.xi0[..., :2].abs(), (problem.parent_half - half).abs() / CM)


def support_violation(problem: TTOProblem, xi: torch.Tensor) -> torch.Tensor:
    """(S,) metres: on / sliding in children's offsets beyond their parents' bounds."""
    excess = torch.relu(xi[..., :2].abs() - support_bounds(problem, xi)).sum(-1)
    return (excess * problem.bounded).sum(-1)


def near_violation(problem: TTOProblem, poses: torch.Tensor) -> torch.Tensor:
    """(S,) cm: Σ ReLU(margin − (sign·d_axis − |d_other|)) over near relations."""
    a = torch.gather(poses[..., :2], 1, problem.near[..., 0:1].expand(-1, -1, 2))
    b = torch.gather(poses[..., :2], 1, problem.near[..., 1:2].expand(-1, -1, 2))
    d = a - b  # (S, K, 2)
    along = torch.gather(d, 2, problem.near_axis.unsqueeze(-1)).squeeze(-1) * problem.near_sign
    other = torch.gather(d, 2, (1 - problem.near_axis).unsqueeze(-1)).squeeze(-1).abs()
    return (torch.relu(problem.near_margin - (along - other)) * problem.near_mask).sum(-1)


def penetration(engine, problem: TTOProblem, poses: torch.Tensor) -> torch.Tensor:
    """(S,) cm: the engine's differentiable energy over the pairs the optimisation can change."""
    return engine.penetration_energy(problem.batch, poses) - problem.frozen_energy
