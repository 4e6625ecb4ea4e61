"""Batched SDF penetration (paper eq. 3): broadphase, narrowphase, hand-written pose gradients.

Everything here works on a *batch*: S scenes padded to N object slots (slot = s * N + i, valid
for i < count[s]), and the assets packed into flat arrays (one 1-D float array of SDF grids with
per-asset start + resolution, one array of surface points with per-asset start + count).

Pairs are enumerated per scene as CSR: scene s owns pair indices [pair_start[s], pair_start[s+1])
= its count*(count-1)/2 pairs (i < j) in row-major order. Stages (one launch each, no host sync,
so the whole sequence can be captured as a graph: ``launch_penetration(graph=True)``):

0. ``table_contact``: per object, the surface points below the table top z = 0.
1. ``broadphase``: per pair, decode (i, j), test the slightly inflated yawed boxes (z interval +
   2-D separating axes of the two footprints) and write ``pair_hit``.
2. the narrowphase, one of two (``narrowphase=`` of :func:`launch_penetration`, same maths, same
   results up to float summation order):

   - ``worklist`` (default; kernels/narrowphase.py): the broadphase appends the (pair, direction)
     items of the pairs that pass to a dense list, and ``lanes`` threads per *item* stride over
     the owner's points in the buckets that meet the other object's box;
   - ``buckets`` (``narrowphase_buckets`` below): ``lanes`` threads for *every* (pair,
     direction), most exiting at once when the pair failed the broadphase.

   Either way the lanes query the other object's field and each writes its partial sums. No
   atomics on values: the partials are reduced in a fixed order, so results are bit-for-bit
   repeatable.
3. ``reduce_pairs``: per pair energy Σ ReLU(−φ), depth max(−φ), and the pose gradient of both
   objects (4-vectors), from the partials of step 2.
4. ``reduce_scenes`` / ``reduce_objects``: per scene energy and depths, per object gradient, each a
   fixed-order loop over the scene's pairs.

The maths (scale rule for non-uniform sizes, gradient formulas) is in docs/physics.md; the
float64 torch oracle is physcene/physics/reference.py and must stay the same maths.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import threading
from collections import OrderedDict

import torch
import warp as wp

# Every gradient here is written by hand; Warp's adjoint would turn shared pose reads into
# contended atomics (DESIGN: ~24x slower on an H100).
wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no greeting on stdout (CLI prints JSON)
wp.set_module_options({"enable_backward": False})
wp.init()

__all__ = ["DEFAULT_LANES", "launch_penetration", "launch_support"]

# Threads sharing one (pair, direction), per device type (see the module docstring).
DEFAULT_LANES = {"cpu": 1, "cuda": 32}
# Gradients of the normalised field smaller than this are "vanished": fall back to h_min.
_GRAD_EPS = wp.constant(1.0e-6)
# Surface points are sorted into BUCKETS^3 cells of the normalised cube (physics.pack_assets), so
# the narrowphase reads only the cells that meet the other object's box.
BUCKETS = wp.constant(4)


@wp.func
def bucket_of(x: float):
    """The point-bucket index (0..BUCKETS-1) of a normalised coordinate, clamped."""
    return wp.clamp(int(wp.floor((x + 1.0) * 0.5 * float(BUCKETS))), 0, BUCKETS - 1)


@wp.func
def rotate_z(c: float, s: float, v: wp.vec3):
    return wp.vec3(c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])


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


@wp.func
def footprint_radius(c: float, s: float, hw: float, hd: float, ux: float, uy: float):
    """Half-width of a yawed rectangle projected on the unit axis (ux, uy)."""
    return hw * wp.abs(c * ux + s * uy) + hd * wp.abs(-s * ux + c * uy)


@wp.func
def footprint_gap(pa: wp.vec4, ha: wp.vec3, pb: wp.vec4, hb: wp.vec3):
    """Largest separation of the two yawed footprints over the 4 candidate axes (cm, <0: overlap)."""
    ca = wp.cos(pa[3])
    sa = wp.sin(pa[3])
    cb = wp.cos(pb[3])
    sb = wp.sin(pb[3])
    dx = pb[0] - pa[0]
    dy = pb[1] - pa[1]
    gap = float(-1.0e30)
    for k in range(4):
        ux = ca
        uy = sa
        if k == 1:
            ux = -sa
            uy = ca
        elif k == 2:
            ux = cb
            uy = sb
        elif k == 3:
            ux = -sb
            uy = cb
        sep = wp.abs(dx * ux + dy * uy) - footprint_radius(ca, sa, ha[0], ha[1], ux, uy) \
            - footprint_radius(cb, sb, hb[0], hb[1], ux, uy)
        gap = wp.max(gap, sep)
    return gap


@wp.func
def find_scene(pair_start: wp.array(dtype=wp.int32), n_scene: int, k: int):
    """The scene s with pair_start[s] <= k < pair_start[s+1] (binary search over the CSR)."""
    lo = int(0)
    hi = n_scene - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if pair_start[mid] <= k:
            lo = mid
        else:
            hi = mid - 1
    return lo


@wp.func
def decode_pair(pair_start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), n_slot: int, k: int):
    """Slots (a, b) of CSR pair k: scene by binary search, then the row-major (i < j) of its pairs."""
    s = find_scene(pair_start, count.shape[0], k)
    n = int(count[s])
    r = k - int(pair_start[s])
    # row-major (i < j): row i starts at i*n - i*(i+1)/2; float guess, then exact integer fix-up
    i = int(float(n) - 0.5 - wp.sqrt((float(n) - 0.5) * (float(n) - 0.5) - 2.0 * float(r)))
    i = wp.clamp(i, 0, n - 2)
    while i > 0 and i * n - i * (i + 1) // 2 > r:
        i -= 1
    while (i + 1) * n - (i + 1) * (i + 2) // 2 <= r:
        i += 1
    j = r - (i * n - i * (i + 1) // 2) + i + 1
    return s * n_slot + i, s * n_slot + j


@wp.func
def boxes_meet(pa: wp.vec4, ha: wp.vec3, pb: wp.vec4, hb: wp.vec3, margin: float):
    """1 if the two yawed boxes (half sizes ha, hb), inflated by margin, overlap, else 0."""
    hit = int(0)
    if wp.abs(pa[2] - pb[2]) <= ha[2] + hb[2] + margin:
        if footprint_gap(pa, ha, pb, hb) <= margin:
            hit = 1
    return hit


@wp.kernel
def broadphase(
    pair_start: wp.array(dtype=wp.int32),  # (S+1,)
    count: wp.array(dtype=wp.int32),  # (S,)
    n_slot: int,
    poses: wp.array(dtype=wp.vec4),  # (S*N,) x, y, z, yaw (cm, rad)
    sizes: wp.array(dtype=wp.vec3),  # (S*N,) w, d, h (cm)
    margin: float,
    pair_a_out: wp.array(dtype=wp.int32),  # (T,) slot of the lower-index object
    pair_b_out: wp.array(dtype=wp.int32),  # (T,)
    pair_hit_out: wp.array(dtype=wp.int32),  # (T,) 1 if the inflated boxes overlap
):
    k = wp.tid()
    a, b = decode_pair(pair_start, count, n_slot, k)
    pair_a_out[k] = a
    pair_b_out[k] = b
    pair_hit_out[k] = boxes_meet(poses[a], sizes[a] * 0.5, poses[b], sizes[b] * 0.5, margin)


@wp.kernel
def narrowphase_buckets(
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
    pair_hit: wp.array(dtype=wp.int32),
    poses: wp.array(dtype=wp.vec4),
    sizes: wp.array(dtype=wp.vec3),
    obj_asset: wp.array(dtype=wp.int32),  # (S*N,)
    sdf: wp.array(dtype=float),  # all grids, flat
    rays: wp.array(dtype=float),  # (3 * len(sdf),) axis ray distances, 3 per node, interleaved
    sdf_start: wp.array(dtype=wp.int32),  # (A,)
    sdf_res: wp.array(dtype=wp.int32),  # (A,)
    points: wp.array(dtype=wp.vec3),  # all surface points, normalised frames, bucket-sorted
    pt_bucket: wp.array(dtype=wp.int32),  # (A * (BUCKETS^3 + 1),) first point of each bucket
    with_grad: int,
    lanes: int,
    part_energy_out: wp.array(dtype=float),  # (T*2*lanes,) Σ ReLU(−φ) cm
    part_depth_out: wp.array(dtype=float),  # (T*2*lanes,) max ReLU(−φ) cm
    part_gu_out: wp.array(dtype=wp.vec3),  # (T*2*lanes,) Σ ∂φ/∂u, field frame (cm/cm)
    part_yaw_out: wp.array(dtype=wp.vec2),  # (T*2*lanes,) Σ ∂φ/∂yaw of (owner, field)
):
    tid = wp.tid()
    pair = tid // (2 * lanes)
    if pair_hit[pair] == 0:
        return
    rem = tid - pair * 2 * lanes
    direction = rem // lanes
    lane = rem - direction * lanes
    owner = pair_a[pair]
    field = pair_b[pair]
    if direction == 1:
        owner = pair_b[pair]
        field = pair_a[pair]
    po = poses[owner]
    pf = poses[field]
    ho = sizes[owner] * 0.5
    hf = sizes[field] * 0.5
    ao = obj_asset[owner]
    af = obj_asset[field]
    grid0 = sdf_start[af]
    res = sdf_res[af]
    # owner-local cm -> field-local cm: u = R(θo − θf) v + R(θf)ᵀ (t_o − t_f)
    cr = wp.cos(po[3] - pf[3])
    sr = wp.sin(po[3] - pf[3])
    cf = wp.cos(pf[3])
    sf = wp.sin(pf[3])
    dt = wp.vec3(po[0] - pf[0], po[1] - pf[1], po[2] - pf[2])
    t_rel = rotate_z(cf, -sf, dt)
    energy = float(0.0)
    depth = float(0.0)
    sum_gu = wp.vec3(0.0, 0.0, 0.0)
    yaw_owner = float(0.0)
    yaw_field = float(0.0)
    # the field's box seen from the owner's normalised frame: only the owner's point buckets that
    # meet it are read (every point of the other buckets is outside the field's box)
    co = wp.cos(po[3])
    so = wp.sin(po[3])
    d = rotate_z(co, -so, -dt)  # field centre, owner-local cm
    ca = wp.abs(cr)
    sa = wp.abs(sr)
    reach = wp.vec3(ca * hf[0] + sa * hf[1], sa * hf[0] + ca * hf[1], hf[2])
    lo = wp.cw_div(d - reach, ho)
    hi = wp.cw_div(d + reach, ho)
    kx0 = bucket_of(lo[0] - 1.0e-4)
    kx1 = bucket_of(hi[0] + 1.0e-4)
    ky0 = bucket_of(lo[1] - 1.0e-4)
    ky1 = bucket_of(hi[1] + 1.0e-4)
    kz0 = bucket_of(lo[2] - 1.0e-4)
    kz1 = bucket_of(hi[2] + 1.0e-4)
    b0 = ao * (BUCKETS * BUCKETS * BUCKETS + 1)
    for kx in range(kx0, kx1 + 1):
        for ky in range(ky0, ky1 + 1):
            for kz in range(kz0, kz1 + 1):
                b = b0 + (kx * BUCKETS + ky) * BUCKETS + kz
                for p in range(pt_bucket[b] + lane, pt_bucket[b + 1], lanes):
                    pl = points[p]
                    v = rotate_z(cr, sr, wp.cw_mul(pl, ho))  # owner point, field frame, from owner
                    u = v + t_rel  # field-local cm
                    q = wp.cw_div(u, hf)
                    # a point outside the field's box cannot be inside its shape: no grid read
                    if wp.max(wp.abs(q[0]), wp.max(wp.abs(q[1]), wp.abs(q[2]))) > 1.0:
                        continue
                    phi, gq = world_phi(sdf, rays, grid0, res, q, hf)
                    if phi < 0.0:
                        energy += -phi
                        depth = wp.max(depth, -phi)
                        if with_grad != 0:
                            gu = wp.cw_div(gq, hf)  # ∂φ/∂u, field-local cm
                            sum_gu += gu
                            yaw_owner += gu[1] * v[0] - gu[0] * v[1]
                            yaw_field += gu[0] * u[1] - gu[1] * u[0]
    part_energy_out[tid] = energy
    part_depth_out[tid] = depth
    if with_grad != 0:
        part_gu_out[tid] = sum_gu
        part_yaw_out[tid] = wp.vec2(yaw_owner, yaw_field)


@wp.kernel
def reduce_pairs(
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
    pair_hit: wp.array(dtype=wp.int32),
    poses: wp.array(dtype=wp.vec4),
    part_energy: wp.array(dtype=float),
    part_depth: wp.array(dtype=float),
    part_gu: wp.array(dtype=wp.vec3),
    part_yaw: wp.array(dtype=wp.vec2),
    pair_item: wp.array(dtype=wp.int32),  # (T,) worklist: first of the pair's two items; else unused
    compact: int,  # 1: partials of item k at k*lanes (worklist), 0: of pair p at p*2*lanes (buckets)
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


_CTYPES: dict = {}


def _ct(t: torch.Tensor, dtype=None):
    """A zero-copy Warp view of a contiguous torch tensor, in launch's fast ctype form.

    The view is only (pointer, shape, strides), so views are memoised on exactly that key: a later
    tensor at the same address with the same layout gets the identical view (and the launcher
    below then skips re-packing it). The view does not hold the tensor: holding it would keep
    every call's scratch memory alive until the memo is cleared, so the allocator could never
    hand the same address back (the memo would never hit, and CUDA memory would pile up).
    """
    key = (t.data_ptr(), t.shape, t.stride(), t.dtype, dtype, t.device)
    view = _CTYPES.get(key)
    if view is None:
        if len(_CTYPES) > 4096:
            _CTYPES.clear()
        view = _CTYPES[key] = wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)
        view._ref = None
    return view


class _Launcher:
    """Launches on one device and, on CUDA, on torch's current stream (no scoped sync).

    Each kernel's launch is recorded once (``wp.launch(record_cmd=True)``) and replayed: only
    the arguments that changed since its last launch are re-packed. ``wp.launch`` packs every
    argument on every call, which is most of its ~10-20 µs host cost; at < 1 ms per engine call
    with 5-6 launches, host time is a large part of the wall time.
    """

    _streams: dict = {}
    _recorded: dict = {}

    def __init__(self, device: torch.device):
        self.device = wp.device_from_torch(device)
        self.stream = None
        if device.type == "cuda":
            key = (str(device), torch.cuda.current_stream(device).cuda_stream)
            self.stream = self._streams.get(key)
            if self.stream is None:
                self.stream = self._streams[key] = wp.stream_from_torch(device)

    def __call__(self, kernel, dim: int, inputs: list, block_dim: int | None = None) -> None:
        if dim <= 0:
            return
        # per thread: a recorded Launch is set, then launched
        key = (kernel, self.device.alias, threading.get_ident(), block_dim)
        hit = self._recorded.get(key)
        if hit is None:
            cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True,
                            block_dim=block_dim)
            self._recorded[key] = (cmd, [dim], list(inputs))
        else:
            cmd, last_dim, last = hit
            if last_dim[0] != dim:
                cmd.set_dim(dim)
                last_dim[0] = dim
            for k, value in enumerate(inputs):
                old = last[k]
                # memoised views: the same object when the array is the same; scalars by value
                if value is not old and (type(value) is not type(old) or value != old):
                    cmd.set_param_at_index_from_ctype(k, value)
                    last[k] = value
        cmd.launch(self.stream)


NARROWPHASES = ("buckets", "worklist")
# CUDA work-list launch: at most this many waves of resident threads; each thread loops over items.
_WORKLIST_WAVES = 4


def _resident_threads(device: torch.device) -> int:
    """Threads a CUDA device keeps resident at once (SMs x threads per SM), memoised."""
    key = str(device)
    n = _RESIDENT.get(key)
    if n is None:
        props = torch.cuda.get_device_properties(device)
        n = _RESIDENT[key] = props.multi_processor_count * props.max_threads_per_multi_processor
    return n


_RESIDENT: dict = {}


def launch_penetration(
    *,
    pair_start: torch.Tensor,
    count: torch.Tensor,
    n_pairs: int,
    poses: torch.Tensor,
    sizes: torch.Tensor,
    obj_asset: torch.Tensor,
    assets: dict[str, torch.Tensor],
    margin: float,
    tolerance: float,
    with_grad: bool,
    lanes: int | None = None,
    narrowphase: str = "worklist",
    graph: bool = False,
    block_dim: int | None = None,
) -> dict[str, torch.Tensor]:
    """Run broadphase → narrowphase → reductions on torch tensors (zero-copy, torch's stream).

    Inputs: pair_start (S+1,) int32; count (S,) int32; poses (S, N, 4) float32 contiguous;
    sizes (S, N, 3) float32; obj_asset (S, N) int32; ``assets`` the packed arrays (``sdf``,
    ``rays``, ``sdf_start``, ``sdf_res``, ``points`` (K, 3), ``pt_start``, ``pt_count``,
    ``pt_zmin``, ``pt_bucket``).
    Returns torch tensors: ``energy``, ``max_depth``, ``depth_sum`` (S,); ``pair_a``, ``pair_b``
    (T,) slots; ``pair_hit`` (T,); ``pair_energy``, ``pair_depth`` (T,); ``table_depth``,
    ``table_energy``, ``table_below`` (S, N); ``grad`` (S, N, 4) when ``with_grad``.
    ``lanes``: threads per (pair, direction), default ``DEFAULT_LANES`` of the device type.
    ``narrowphase``: ``"worklist"`` (kernels/narrowphase.py: threads only for pairs that pass the
    broadphase) or ``"buckets"`` (every pair's threads launched); same results up to float
    summation order. No host synchronisation: every launch size is known from the arguments (the
    work list's length stays on the device).
    ``graph``: capture the launches of a batch layout (the same arrays, sizes and settings) the
    second time it is run (a CUDA graph; a Warp CPU graph on the CPU) and replay them from the
    third: the poses are copied into the graph's own buffer and the outputs cloned out of it,
    so callers get fresh tensors as without.
    ``block_dim``: CUDA threads per block of the narrowphase launch (None: Warp's 256); ignored on
    the CPU.
    """
    device = poses.device
    lanes = DEFAULT_LANES[device.type] if lanes is None else int(lanes)
    if lanes < 1:
        raise ValueError(f"lanes must be >= 1, got {lanes}")
    if narrowphase not in NARROWPHASES:
        raise ValueError(f"narrowphase {narrowphase!r}: expected one of {', '.join(NARROWPHASES)}")
    if device.type != "cuda":
        block_dim = None
    elif block_dim is not None and not 1 <= int(block_dim) <= 1024:
        raise ValueError(f"block_dim must be in 1..1024, got {block_dim}")
    launcher = _Launcher(device)
    args = dict(pair_start=pair_start, count=count, n_pairs=n_pairs, sizes=sizes, obj_asset=obj_asset,
                assets=assets, margin=float(margin), tolerance=float(tolerance), with_grad=bool(with_grad),
                lanes=lanes, worklist=narrowphase == "worklist",
                block_dim=None if block_dim is None else int(block_dim))
    if not graph or n_pairs == 0:
        return _penetration(launcher, _ct, poses=poses, buffers=_allocate(poses, **args), **args)
    key = _Plan.key(launcher, poses, args)
    plan = _PLANS.get(key)
    if plan is not None:
        _PLANS.move_to_end(key)
        return plan.replay(poses, launcher)
    # run directly (this also loads the kernels); capture only a layout seen before, so a stream of
    # new batches (the reward's) never pays for captures it would not replay
    out = _penetration(launcher, _ct, poses=poses, buffers=_allocate(poses, **args), **args)
    if _SEEN.pop(key, None) is None:
        _SEEN[key] = True
        if len(_SEEN) > 64:
            _SEEN.pop(next(iter(_SEEN)))
    else:
        if len(_PLANS) >= _MAX_PLANS:
            _PLANS.pop(next(iter(_PLANS)))  # the least recently used
        _PLANS[key] = _Plan(launcher, poses, args)
    return out


def _partials(n_pairs: int, lanes: int) -> int:
    """Partial-sum slots of the narrowphase: 2 directions x lanes per pair (work list: upper bound)."""
    return 2 * n_pairs * lanes


def _allocate(poses: torch.Tensor, *, n_pairs: int, with_grad: bool, lanes: int, worklist: bool,
              **_) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(floats, ints, part): one allocation per kind for every output and scratch array of a call."""
    device = poses.device
    n_scene, n_obj = poses.shape[0], poses.shape[0] * poses.shape[1]
    # one allocation for the float outputs, one for the int ones: views are cheap, allocations not
    floats = torch.empty(3 * n_scene + 2 * n_pairs + 3 * n_obj + (4 * n_obj if with_grad else 0),
                         dtype=torch.float32, device=device)
    # pair_a, pair_b, pair_hit, then (work list) pair_item, items (2T), the item counter
    ints = torch.empty(3 * n_pairs + (3 * n_pairs + 1 if worklist else 1), dtype=torch.int32, device=device)
    n_part = _partials(n_pairs, lanes)
    # the gradient partials are never touched without with_grad: 8 spare floats stand in for them
    part = torch.empty((7 * n_part + 8 * n_pairs if with_grad else 2 * n_part + 8) if n_pairs else 0,
                       dtype=torch.float32, device=device)
    return floats, ints, part


def _outputs(floats: torch.Tensor, ints: torch.Tensor, n_scene: int, n_slot: int, n_pairs: int,
             with_grad: bool) -> dict[str, torch.Tensor]:
    """The named output views of one call's float and int buffers."""
    n_obj = n_scene * n_slot
    sizes_f = [n_scene, n_scene, n_scene, n_pairs, n_pairs, n_obj, n_obj, n_obj]
    views = torch.split(floats, sizes_f + ([4 * n_obj] if with_grad else []))
    out = dict(zip(("energy", "max_depth", "depth_sum", "pair_energy", "pair_depth"), views[:5]))
    for key, view in zip(("table_depth", "table_energy", "table_below"), views[5:8]):
        out[key] = view.view(n_scene, n_slot)
    if with_grad:
        out["grad"] = views[8].view(n_scene, n_slot, 4)
    out["pair_a"], out["pair_b"], out["pair_hit"] = torch.split(ints[:3 * n_pairs], [n_pairs] * 3)
    return out


def _penetration(launch, view, *, pair_start, count, n_pairs, poses, sizes, obj_asset, assets, margin,
                 tolerance, with_grad, lanes, worklist, block_dim, buffers) -> dict[str, torch.Tensor]:
    """Issue every launch of one call through ``launch(kernel, dim, inputs)`` with array arguments
    made by ``view(tensor, dtype=None)``, writing into ``buffers`` (see :func:`_allocate`)."""
    device = poses.device
    floats, ints, part = buffers
    n_scene, n_slot = poses.shape[0], poses.shape[1]
    n_obj = n_scene * n_slot
    out = _outputs(floats, ints, n_scene, n_slot, n_pairs, with_grad)
    n_item = ints[-1:]
    w_poses = view(poses.reshape(n_obj, 4), wp.vec4)
    w_sizes = view(sizes.reshape(n_obj, 3), wp.vec3)
    w_asset = view(obj_asset.reshape(n_obj))
    w_pair_start, w_count = view(pair_start), view(count)
    w_points = view(assets["points"], wp.vec3)
    w_n_item = view(n_item)
    launch(table_contact, n_obj, [w_count, n_slot, w_poses, w_sizes, w_asset, w_points,
                                  view(assets["pt_start"]), view(assets["pt_count"]), view(assets["pt_zmin"]),
                                  w_n_item,
                                  view(out["table_depth"].view(-1)), view(out["table_energy"].view(-1)),
                                  view(out["table_below"].view(-1))])
    if n_pairs == 0:
        floats[:3 * n_scene].zero_()
        if with_grad:
            out["grad"].zero_()
        return out
    w_pair_a, w_pair_b, w_hit = view(out["pair_a"]), view(out["pair_b"]), view(out["pair_hit"])
    w_pair_item = w_hit
    n_part = _partials(n_pairs, lanes)
    if worklist:
        from physcene.kernels.narrowphase import broadphase_items, narrowphase_items

        pair_item, items = ints[3 * n_pairs:4 * n_pairs], ints[4 * n_pairs:6 * n_pairs]
        w_pair_item, w_items = view(pair_item), view(items)
        launch(broadphase_items, n_pairs, [w_pair_start, w_count, n_slot, w_poses, w_sizes, margin,
                                           w_pair_a, w_pair_b, w_hit, w_pair_item, w_n_item, w_items])
        # the count stays on the device: each group of lanes threads loops over items (grid-stride)
        if device.type == "cuda":  # a few waves of resident threads
            n_thread = min(2 * n_pairs, max(1, _WORKLIST_WAVES * _resident_threads(device) // lanes)) * lanes
        else:  # the CPU runs threads one after another: one group of lanes does every item
            n_thread = lanes
    else:
        launch(broadphase, n_pairs, [w_pair_start, w_count, n_slot, w_poses, w_sizes, margin,
                                     w_pair_a, w_pair_b, w_hit])
        n_thread = n_part
    if with_grad:
        pe, pd, pg, py, pair_grad = torch.split(part, [n_part, n_part, 3 * n_part, 2 * n_part, 8 * n_pairs])
        pg, py, pair_grad = pg.view(n_part, 3), py.view(n_part, 2), pair_grad.view(n_pairs, 2, 4)
    else:  # the gradient buffers are never touched: one-element stand-ins
        pe, pd, spare = torch.split(part, [n_part, n_part, 8])
        pg, py, pair_grad = spare[:3].view(1, 3), spare[3:5].view(1, 2), spare.view(1, 2, 4)
    w_part = [view(pe), view(pd), view(pg, wp.vec3), view(py, wp.vec2)]
    w_pair_grad = view(pair_grad, wp.vec4)
    w_fields = [w_poses, w_sizes, w_asset, view(assets["sdf"]), view(assets["rays"]),
                view(assets["sdf_start"]), view(assets["sdf_res"]), w_points, view(assets["pt_bucket"]),
                int(with_grad)]
    if worklist:
        launch(narrowphase_items, n_thread, [w_items, w_n_item, n_thread, lanes, w_pair_a, w_pair_b,
                                             *w_fields, *w_part], block_dim)
    else:
        launch(narrowphase_buckets, n_thread, [w_pair_a, w_pair_b, w_hit, *w_fields, lanes, *w_part],
               block_dim)
    w_pair_energy, w_pair_depth = view(out["pair_energy"]), view(out["pair_depth"])
    launch(reduce_pairs, n_pairs, [w_pair_a, w_pair_b, w_hit, w_poses, *w_part, w_pair_item, int(worklist),
                                   int(with_grad), lanes, w_pair_energy, w_pair_depth, w_pair_grad])
    launch(reduce_scenes, n_scene, [w_pair_start, w_pair_energy, w_pair_depth, tolerance,
                                    view(out["energy"]), view(out["max_depth"]), view(out["depth_sum"])])
    if with_grad:
        launch(reduce_objects, n_obj, [w_pair_start, w_count, n_slot, w_pair_grad,
                                       view(out["grad"].view(n_obj, 4), wp.vec4)])
    return out


def _warp_array(t: torch.Tensor, dtype=None):
    """A zero-copy ``wp.array`` view (graph capture records arrays, not raw ctype views)."""
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


# Captured launch sequences, least recently used first; each holds its scratch memory.
_PLANS: OrderedDict = OrderedDict()
_MAX_PLANS = 4
# Layouts run once without a capture (the second run captures), oldest first.
_SEEN: OrderedDict = OrderedDict()
_CAPTURE_STREAMS: dict = {}


def _capture_stream(device) -> wp.Stream:
    """A non-default CUDA stream of ``device`` to capture graphs on, one per device."""
    stream = _CAPTURE_STREAMS.get(device.alias)
    if stream is None:
        stream = _CAPTURE_STREAMS[device.alias] = wp.Stream(device)
    return stream


class _Plan:
    """One batch layout's launches captured as a graph, with the buffers it reads and writes."""

    def __init__(self, launcher: _Launcher, poses: torch.Tensor, args: dict):
        self.args = args
        self.poses = poses.clone()  # the graph's own input: callers' poses are copied in
        self.buffers = _allocate(self.poses, **args)
        self.shape = (poses.shape[0], poses.shape[1])

        # CUDA cannot capture on the legacy default stream (torch's usual current stream): capture on
        # a private stream; the graph is then launched on the caller's stream
        stream = _capture_stream(launcher.device) if launcher.device.is_cuda else None

        def launch(kernel, dim, inputs, block_dim=None):
            if dim > 0:
                wp.launch(kernel, dim=dim, inputs=inputs, device=launcher.device, stream=stream,
                          block_dim=block_dim)

        with wp.ScopedCapture(device=launcher.device, stream=stream) as capture:
            _penetration(launch, _warp_array, poses=self.poses, buffers=self.buffers, **args)
        self.graph = capture.graph

    @staticmethod
    def key(launcher: _Launcher, poses: torch.Tensor, args: dict) -> tuple:
        """Everything the captured launches depend on: array addresses and shapes, scalars."""
        arrays = [args[k] for k in ("pair_start", "count", "sizes", "obj_asset")]
        arrays += args["assets"].values()
        # per thread: a replay writes the plan's buffers, so two threads must not share one
        return (launcher.device.alias, id(launcher.stream), threading.get_ident(), tuple(poses.shape),
                poses.dtype, tuple((t.data_ptr(), t.numel()) for t in arrays),
                *(args[k] for k in ("n_pairs", "margin", "tolerance", "with_grad", "lanes", "worklist",
                                    "block_dim")))

    def replay(self, poses: torch.Tensor, launcher: _Launcher) -> dict[str, torch.Tensor]:
        self.poses.copy_(poses)
        wp.capture_launch(self.graph, stream=launcher.stream)
        floats, ints, _ = self.buffers
        n_pairs = self.args["n_pairs"]
        return _outputs(_fresh(floats), _fresh(ints[:3 * n_pairs]), *self.shape, n_pairs,
                        self.args["with_grad"])


def _fresh(t: torch.Tensor) -> torch.Tensor:
    """A copy of t. On the CPU through numpy: torch's parallel copy leaves its OpenMP threads
    spinning after it, which on a small machine slows the single-threaded Warp kernels after it."""
    return torch.from_numpy(t.numpy().copy()) if t.device.type == "cpu" else t.clone()


def launch_support(*, count: torch.Tensor, poses: torch.Tensor, sizes: torch.Tensor,
                   overlap_eps: float) -> torch.Tensor:
    """Per object, its bottom's height above the highest support under it, (S, N) cm."""
    n_scene, n_slot = poses.shape[0], poses.shape[1]
    gap = torch.empty(n_scene, n_slot, dtype=torch.float32, device=poses.device)
    _Launcher(poses.device)(support_gap, n_scene * n_slot,
                            [_ct(count), n_slot, _ct(poses.reshape(-1, 4), wp.vec4),
                             _ct(sizes.reshape(-1, 3), wp.vec3), float(overlap_eps), _ct(gap.view(-1))])
    return gap
