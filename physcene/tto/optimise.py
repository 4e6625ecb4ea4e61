"""The batched Adam loop over ξ (paper: 100 steps of lr 0.01) and its device result.

Every scene keeps its best iterate (lowest penetration energy; among collision-free iterates the
lowest remaining objective); a scene stops at its first collision-free iterate that meets the
hinges (``early_stop``), and the host checks "every scene stopped" only every ``check_every``
steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from physcene.tto.config import TTOConfig
from physcene.tto.losses import (
    footprint_overlap_depth,
    footprints,
    near_violation,
    penetration,
    support_bounds,
    support_violation,
    zone_violation,
)
from physcene.tto.problem import CM, IN, TTOProblem, forward_kinematics

__all__ = ["TTOSolution", "optimise"]


@dataclass
class TTOSolution:
    """Device results of :func:`optimise` for S scenes."""

    xi: torch.Tensor          # (S, N, 4) best ξ
    poses: torch.Tensor       # (S, N, 4) cm, poses of the best ξ
    energy: torch.Tensor      # (S,) cm, optimised energy of the best ξ
    energy_input: torch.Tensor  # (S,) cm, the same energy of the unmodified input
    steps: torch.Tensor       # (S,) long, steps taken before the scene stopped


def optimise(problem: TTOProblem, engine, config: TTOConfig) -> TTOSolution:
    """Batched Adam over ξ; host syncs only every ``check_every`` steps (all-stopped test)."""
    xi0 = problem.xi0
    # (S, N, 4): x, y, yaw of every free object; the lift only where it has room
    trainable = problem.trainable.unsqueeze(-1) & torch.cat(
        (torch.ones_like(xi0[..., :3], dtype=torch.bool), (problem.lift_max > 0).unsqueeze(-1)), dim=-1)
    # Adam's first steps are about lr per coordinate whatever the gradient's size (1 cm): a sliding
    # content's (u, v) are optimised in units scaled by in_lr_scale, so that one step cannot carry
    # it through a container wall a few mm thick (it would then be pushed outwards, into the wall)
    unit = torch.ones_like(xi0)
    unit[..., :2] = torch.where(((problem.kind == IN) & problem.trainable).unsqueeze(-1),
                                config.in_lr_scale, 1.0)
    theta = (xi0 / unit).requires_grad_(True)  # (S, N, 4) Adam's parameter: ξ = θ · unit
    opt = torch.optim.Adam([theta], lr=config.lr, fused=xi0.device.type == "cuda")  # one kernel per step
    n = problem.n_scene
    dev = xi0.device
    inf = torch.full((n,), math.inf, device=dev)
    best_xi, best_e, best_rest = xi0.clone(), inf.clone(), inf.clone()
    active = torch.ones(n, dtype=torch.bool, device=dev)
    steps_taken = torch.full((n,), config.steps, dtype=torch.long, device=dev)
    on = problem.bounded
    for step in range(config.steps + 1):
        xi = theta * unit
        xi_eff = torch.where(trainable, xi, xi0)  # frozen in children, held objects, padding stay put
        poses = forward_kinematics(problem, xi_eff)
        energy = penetration(engine, problem, poses)
        corners = footprints(poses, problem.sizes)  # (S, N, 4, 2)
        hinge_cm = (CM * support_violation(problem, xi_eff) + near_violation(problem, poses),
                    zone_violation(problem, poses, corners))
        drift = ((xi_eff - xi0) ** 2 * trainable).sum((1, 2))
        rest = (config.lambda_rel * hinge_cm[0] + config.lambda_zone * hinge_cm[1]) / CM \
            + config.lambda_reg * drift
        with torch.no_grad():
            e, r = energy.detach(), rest.detach()
            free, best_free = e <= config.stop_energy_cm, best_e <= config.stop_energy_cm
            better = active & torch.where(free & best_free, r < best_rest, e < best_e)
            best_xi = torch.where(better[:, None, None], xi_eff.detach(), best_xi)
            best_e, best_rest = torch.where(better, e, best_e), torch.where(better, r, best_rest)
            if config.early_stop:
                done = active & free & (hinge_cm[0] + hinge_cm[1] <= config.stop_violation_cm)
                steps_taken = torch.where(done, torch.full_like(steps_taken, step), steps_taken)
                active = active & ~done
        if step == config.steps:
            break
        proxy = footprint_overlap_depth(problem, poses, corners) if config.footprint_proxy else 0.0
        loss = ((config.lambda_sdf * (energy + proxy) / CM + rest) * active).sum()
        opt.zero_grad(set_to_none=False)
        loss.backward()
        # cosine decay lr -> lr_final: full-size steps travel, small ones settle at the contacts
        # (a host float: no sync)
        opt.param_groups[0]["lr"] = config.lr_final + 0.5 * (config.lr - config.lr_final) * (
            1.0 + math.cos(math.pi * step / max(config.steps, 1)))
        opt.step()
        with torch.no_grad():
            xi = theta * unit
            bound = support_bounds(problem, xi)
            projected = torch.maximum(torch.minimum(xi[..., :2], bound), -bound)
            xi[..., :2] = torch.where(on.unsqueeze(-1), projected, xi[..., :2])
            xi[..., 3] = torch.minimum(xi[..., 3].clamp_min(0.0), problem.lift_max)
            theta.copy_(torch.where(active[:, None, None], xi, best_xi) / unit)
        if config.early_stop and (step + 1) % config.check_every == 0 and not bool(active.any()):
            break
    with torch.no_grad():
        poses = forward_kinematics(problem, best_xi)
        energy_input = penetration(engine, problem, problem.raw_poses)
    return TTOSolution(best_xi, poses, best_e, energy_input, steps_taken)
