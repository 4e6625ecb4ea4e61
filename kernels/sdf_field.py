"""The signed distance field of a posed asset: trilinear samples, cube clamping, world-scaled φ.

Grids are R^3 nodes of the normalised cube [-1, 1]^3 (flat, per-asset start and resolution);
``rays`` holds per node the three axis-ray distances to the surface, interleaved. The maths
(scale rule for non-uniform sizes) is in docs/physics.md.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

# Every gradient here is written by hand; Warp's adjoint would turn shared pose reads into
# contended atomics (~24x slower on an H100).
wp.set_module_options({"enable_backward": False})

__all__ = ["grid_cell", "sdf_sample", "trilinear", "world_phi", "world_scale"]

# Gradients of the normalised field smaller than this are "vanished": fall back to h_min.
_GRAD_EPS = wp.constant(1.0e-6)


@wp.func
def trilinear(grid: wp.array(dtype=float), base: int, elem: int, res: int, t: wp.vec3, inv_h: float):
    """Value and gradient (per normalised unit) of the cell at ``base`` with fractions t.

    ``elem`` is the distance between consecutive nodes in ``grid`` (1 for φ, 3 for the
    interleaved axis rays). Returns vec4(value, ∂/∂q). Interpolates along z, then y, then x,
    like the torch reference.
    """
    sz = elem
    sy = res * elem
    sx = res * res * elem
    c000 = grid[base]
    c001 = grid[base + sz]
    c010 = grid[base + sy]
    c011 = grid[base + sy + sz]
    c100 = grid[base + sx]
    c101 = grid[base + sx + sz]
    c110 = grid[base + sx + sy]
    c111 = grid[base + sx + sy + sz]
    tx = t[0]
    ty = t[1]
    tz = t[2]
    c00 = c000 + (c001 - c000) * tz
    c01 = c010 + (c011 - c010) * tz
    c10 = c100 + (c101 - c100) * tz
    c11 = c110 + (c111 - c110) * tz
    c0 = c00 + (c01 - c00) * ty
    c1 = c10 + (c11 - c10) * ty
    value = c0 + (c1 - c0) * tx
    gx = (c1 - c0) * inv_h
    d0z = c001 - c000 + (c011 - c010 - c001 + c000) * ty
    d1z = c101 - c100 + (c111 - c110 - c101 + c100) * ty
    gy = ((1.0 - tx) * (c01 - c00) + tx * (c11 - c10)) * inv_h
    gz = ((1.0 - tx) * d0z + tx * d1z) * inv_h
    return wp.vec4(value, gx, gy, gz)



@wp.func
def grid_cell(q: wp.vec3, res: int):
    """The cell of q clamped to the cube: (q clamped, node offset of the cell, fractions)."""
    qc = wp.vec3(wp.clamp(q[0], -1.0, 1.0), wp.clamp(q[1], -1.0, 1.0), wp.clamp(q[2], -1.0, 1.0))
    inv_h = float(res - 1) * 0.5
    fx = (qc[0] + 1.0) * inv_h
    fy = (qc[1] + 1.0) * inv_h
    fz = (qc[2] + 1.0) * inv_h
    ix = wp.clamp(int(wp.floor(fx)), 0, res - 2)
    iy = wp.clamp(int(wp.floor(fy)), 0, res - 2)
    iz = wp.clamp(int(wp.floor(fz)), 0, res - 2)
    t = wp.vec3(fx - float(ix), fy - float(iy), fz - float(iz))
    return qc, (ix * res + iy) * res + iz, t



@wp.func
def sdf_sample(sdf: wp.array(dtype=float), start: int, res: int, q: wp.vec3):
    """Trilinear φ (normalised units) and its gradient at q; outside the cube: clamp + distance.

    Returns vec4(φ, ∂φ/∂q).
    """
    qc, node, t = grid_cell(q, res)
    sample = trilinear(sdf, start + node, 1, res, t, float(res - 1) * 0.5)
    out = q - qc
    dist = wp.length(out)
    if dist > 0.0:
        # clamped axes do not move the grid sample; the distance to the cube does
        gx = sample[1]
        gy = sample[2]
        gz = sample[3]
        if out[0] != 0.0:
            gx = 0.0
        if out[1] != 0.0:
            gy = 0.0
        if out[2] != 0.0:
            gz = 0.0
        sample = wp.vec4(sample[0] + dist, gx + out[0] / dist, gy + out[1] / dist, gz + out[2] / dist)
    return sample



@wp.func
def world_scale(g: wp.vec3, half: wp.vec3):
    """cm per normalised unit along the field's normal: 1/|S⁻¹ n̂| ∈ [h_min, h_max]."""
    glen = wp.length(g)
    if glen < _GRAD_EPS:
        return wp.min(half[0], wp.min(half[1], half[2]))
    m = wp.vec3(g[0] / half[0], g[1] / half[1], g[2] / half[2]) / glen
    return 1.0 / wp.length(m)



@wp.func
def world_phi(sdf: wp.array(dtype=float), rays: wp.array(dtype=float), start: int, res: int,
              q: wp.vec3, half: wp.vec3):
    """World φ (cm) of a point inside the field's shape and ∂φ/∂q, else φ ≥ 0 (docs/physics.md).

    φ_world = max(φ_n / |S⁻¹ n̂|, −h_k r_k(q)): the first-order anisotropic estimate, capped by
    the distances r_k to the surface along the three axes (exact for axis-aligned faces). Under
    a uniform scale the first term is exact already and the rays are not read.
    """
    sample = sdf_sample(sdf, start, res, q)
    phi = sample[0]
    g = wp.vec3(sample[1], sample[2], sample[3])
    if phi >= 0.0:
        return phi, g
    scale = world_scale(g, half)  # held constant in the gradient
    phi = phi * scale
    g = g * scale
    if wp.max(half[0], wp.max(half[1], half[2])) <= wp.min(half[0], wp.min(half[1], half[2])) * 1.000001:
        return phi, g
    qc, node, t = grid_cell(q, res)
    for k in range(3):
        if half[k] >= scale:
            continue  # h_k r_k >= h_k |φ_n| >= this depth already (r_k >= |φ_n|): cannot be smaller
        r = trilinear(rays, 3 * (start + node) + k, 3, res, t, float(res - 1) * 0.5)
        if -half[k] * r[0] > phi:
            phi = -half[k] * r[0]
            g = wp.vec3(-half[k] * r[1], -half[k] * r[2], -half[k] * r[3])
    return phi, g
