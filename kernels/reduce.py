"""The reductions: per pair, per scene and per object sums of the narrowphase's partials.

No atomics on values: every sum is a fixed-order loop, so results are bit-for-bit repeatable.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.boxes import rotate_z

wp.set_module_options({"enable_backward": False})

__all__ = ["reduce_objects", "reduce_pairs", "reduce_scenes"]


@wp.kernel
def reduce_pairs(
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
    pair_hit: wp.array(dtype=wp.int32),
    poses: wp.array(dtype=wp.vec4),
    sizes: wp.array(dtype=wp.vec3),
    depth_cap_ratio: float,  # depth <= this x half the thinner object's smallest size; 0: no cap
    part_energy: wp.array(dtype=float),
    part_depth: wp.array(dtype=float),
    part_gu: wp.array(dtype=wp.vec3),
    part_yaw: wp.array(dtype=wp.vec2),
    pair_item: wp.array(dtype=wp.int32),  # (T,) worklist: first of the pair's two items; else unused
    compact: int,  # 1: partials of item k at k*lanes (the work list), 0: of pair p at p*2*lanes
    # (benchmarks/narrowphase_buckets.py, the variant that launches threads for every pair)
    with_grad: int,
    lanes: int,
    pair_energy_out: wp.array(dtype=float),  # (T,) cm
    pair_depth_out: wp.array(dtype=float),  # (T,) cm
    pair_grad_out: wp.array(dtype=wp.vec4, ndim=2),  # (T, 2) ∂E/∂(x,y,z,yaw) of a and b
):
    pair = wp.tid()
    energy = float(0.0)
    depth = float(0.0)
    ga = wp.vec4(0.0, 0.0, 0.0, 0.0)
    gb = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if pair_hit[pair] != 0:
        base = pair * 2 * lanes
        if compact != 0:
            base = pair_item[pair] * lanes  # the pair's two items are consecutive: direction 0, 1
        for k in range(2 * lanes):
            energy += part_energy[base + k]
            depth = wp.max(depth, part_depth[base + k])
        if depth_cap_ratio > 0.0:
            # where the interior samples' spacing decides the reading (docs/physics.md): a level that
            # every deeper overlap reaches, so the reading never falls as the overlap grows
            sa = sizes[pair_a[pair]]
            sb = sizes[pair_b[pair]]
            thin = wp.min(wp.min(wp.min(sa[0], sa[1]), sa[2]), wp.min(wp.min(sb[0], sb[1]), sb[2]))
            depth = wp.min(depth, depth_cap_ratio * 0.5 * thin)
        if with_grad != 0:
            ya = poses[pair_a[pair]][3]
            yb = poses[pair_b[pair]][3]
            for direction in range(2):
                gu = wp.vec3(0.0, 0.0, 0.0)
                yaw = wp.vec2(0.0, 0.0)
                for lane in range(lanes):
                    gu += part_gu[base + direction * lanes + lane]
                    yaw += part_yaw[base + direction * lanes + lane]
                # E = Σ −φ: ∂E/∂t_owner = −R_f Σgu, ∂E/∂t_field = +R_f Σgu
                yf = yb
                if direction == 1:
                    yf = ya
                gw = rotate_z(wp.cos(yf), wp.sin(yf), gu)
                g_owner = wp.vec4(-gw[0], -gw[1], -gw[2], -yaw[0])
                g_field = wp.vec4(gw[0], gw[1], gw[2], -yaw[1])
                if direction == 0:
                    ga += g_owner
                    gb += g_field
                else:
                    gb += g_owner
                    ga += g_field
    pair_energy_out[pair] = energy
    pair_depth_out[pair] = depth
    if with_grad != 0:
        pair_grad_out[pair, 0] = ga
        pair_grad_out[pair, 1] = gb



@wp.kernel
def reduce_scenes(
    pair_start: wp.array(dtype=wp.int32),
    pair_energy: wp.array(dtype=float),
    pair_depth: wp.array(dtype=float),
    tolerance: float,
    energy_out: wp.array(dtype=float),  # (S,) cm
    max_depth_out: wp.array(dtype=float),  # (S,) cm
    depth_sum_out: wp.array(dtype=float),  # (S,) Σ pen(i, j) over pairs deeper than tolerance, cm
):
    s = wp.tid()
    energy = float(0.0)
    depth = float(0.0)
    total = float(0.0)
    for k in range(int(pair_start[s]), int(pair_start[s + 1])):
        energy += pair_energy[k]
        d = pair_depth[k]
        depth = wp.max(depth, d)
        if d > tolerance:
            total += d
    energy_out[s] = energy
    max_depth_out[s] = depth
    depth_sum_out[s] = total



@wp.kernel
def reduce_objects(
    pair_start: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    n_slot: int,
    pair_grad: wp.array(dtype=wp.vec4, ndim=2),
    grad_out: wp.array(dtype=wp.vec4),  # (S*N,) ∂E_scene/∂(x,y,z,yaw)
):
    slot = wp.tid()
    s = slot // n_slot
    i = slot - s * n_slot
    n = int(count[s])
    g = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if i < n:
        base = int(pair_start[s])
        for j in range(n):
            if j < i:  # pair (j, i): i is side b
                g += pair_grad[base + j * n - j * (j + 1) // 2 + (i - j - 1), 1]
            elif j > i:  # pair (i, j): i is side a
                g += pair_grad[base + i * n - i * (i + 1) // 2 + (j - i - 1), 0]
    grad_out[slot] = g
