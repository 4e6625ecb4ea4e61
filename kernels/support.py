"""Contact with the table top and support: what lies below z = 0, and each object's support gap.

``table_contact`` (per object: its surface points below the table top z = 0) runs first in the
penetration driver; ``support_gap`` (per object: its bottom's height above the highest support
under it, the floating metric) is :func:`launch_support`.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import torch
import warp as wp

from physcene.kernels.boxes import footprint_gap
from physcene.kernels.launch import Launcher, torch_view

wp.set_module_options({"enable_backward": False})

__all__ = ["launch_support", "support_gap", "table_contact"]


@wp.kernel
def table_contact(
    count: wp.array(dtype=wp.int32),
    n_slot: int,
    poses: wp.array(dtype=wp.vec4),
    sizes: wp.array(dtype=wp.vec3),
    obj_asset: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    pt_start: wp.array(dtype=wp.int32),
    pt_count: wp.array(dtype=wp.int32),
    pt_zmin: wp.array(dtype=float),  # (A,) lowest normalised z of each asset's points
    counter_out: wp.array(dtype=wp.int32),  # (1,) zeroed here for the worklist's append (one launch less)
    depth_out: wp.array(dtype=float),  # (S*N,) deepest surface point below z = 0, cm
    energy_out: wp.array(dtype=float),  # (S*N,) Σ ReLU(−z) over surface points, cm
    below_out: wp.array(dtype=float),  # (S*N,) number of points below z = 0 (= −∂E/∂z)
):
    slot = wp.tid()
    if slot == 0:
        counter_out[0] = 0
    s = slot // n_slot
    depth = float(0.0)
    energy = float(0.0)
    below = float(0.0)
    pose = poses[slot]
    half = sizes[slot] * 0.5
    a = obj_asset[slot]
    # z + p_z h_z is monotone in p_z (rounding too): if the lowest point is not below z = 0, none
    # is, and an object resting on the table skips its points exactly
    if slot - s * n_slot < int(count[s]) and pose[2] + pt_zmin[a] * half[2] < 0.0:
        p0 = pt_start[a]
        for p in range(pt_count[a]):
            # yaw does not change z: z = z_c + p_z * h_z
            z = pose[2] + points[p0 + p][2] * half[2]
            if z < 0.0:
                depth = wp.max(depth, -z)
                energy += -z
                below += 1.0
    depth_out[slot] = depth
    energy_out[slot] = energy
    below_out[slot] = below



@wp.kernel
def support_gap(
    count: wp.array(dtype=wp.int32),
    n_slot: int,
    poses: wp.array(dtype=wp.vec4),
    sizes: wp.array(dtype=wp.vec3),
    overlap_eps: float,
    gap_out: wp.array(dtype=float),  # (S*N,) bottom height above the highest support under it, cm
):
    slot = wp.tid()
    s = slot // n_slot
    i = slot - s * n_slot
    n = int(count[s])
    gap = float(0.0)
    if i < n:
        pi = poses[slot]
        hi = sizes[slot] * 0.5
        bottom = pi[2] - hi[2]
        gap = bottom  # the table top, z = 0, is under everything
        for j in range(n):
            if j != i:
                pj = poses[s * n_slot + j]
                hj = sizes[s * n_slot + j] * 0.5
                if footprint_gap(pi, hi, pj, hj) < -overlap_eps:
                    top = pj[2] + hj[2]
                    if top <= bottom:
                        gap = wp.min(gap, bottom - top)
                    elif pj[2] - hj[2] < bottom:
                        gap = 0.0  # the bottom is inside j's box: contained (pen in a holder)
    gap_out[slot] = gap



def launch_support(*, count: torch.Tensor, poses: torch.Tensor, sizes: torch.Tensor,
                   overlap_eps: float) -> torch.Tensor:
    """Per object, its bottom's height above the highest support under it, (S, N) cm."""
    n_scene, n_slot = poses.shape[0], poses.shape[1]
    gap = torch.empty(n_scene, n_slot, dtype=torch.float32, device=poses.device)
    Launcher(poses.device)(support_gap, n_scene * n_slot,
                           [torch_view(count), n_slot, torch_view(poses.reshape(-1, 4), wp.vec4),
                            torch_view(sizes.reshape(-1, 3), wp.vec3), float(overlap_eps),
                            torch_view(gap.view(-1))])
    return gap
