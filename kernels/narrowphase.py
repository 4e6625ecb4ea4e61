"""The work-list narrowphase: threads only for (pair, direction) items that pass the broadphase.

The ``buckets`` narrowphase of :mod:`physcene.kernels.penetration` launches ``lanes`` threads for
every pair and direction of the batch; on the bench batch (512 scenes x 16 objects) 92 % of them
exit at once because the pair failed the broadphase, and on CUDA the live warps sit in blocks
whose other warps are dead, so few live warps are resident to hide memory latency. Its live
lanes also restart their loop at each of up to 64 point buckets of ~16 points.

Here, with the same maths and the same per-point code:

1. ``broadphase_items`` (one thread per pair): the broadphase test; a pair that passes appends its
   two items (pair * 2 + direction) to a dense list with one ``atomic_add`` on a device counter
   (zeroed by ``table_contact``, launched just before). The list's order is arbitrary on CUDA, but
   every item's sums are computed in a fixed order and land in the pair's slots
   (``pair_item[pair]`` = the position of its direction-0 item), so results are bit-for-bit
   repeatable anyway.
2. ``narrowphase_items``: ``lanes`` threads per item. The item's points in the buckets that meet
   the other object's box form at most 16 contiguous runs (the (kx, ky) columns, kz range
   contiguous in the bucket-sorted points); the lanes stride over their concatenation, so every
   lane has a point on every iteration but the last. Partial sums go to ``item * lanes + lane``.
   The item count stays on the device (no host synchronisation): on CUDA the launch covers
   min(2T, a few resident waves) x lanes threads that loop over the items (grid-stride); on the
   CPU, whose threads run one after another, one group of lanes threads loops over all items.
3. ``reduce_pairs`` (``compact=1``) then sums each pair's 2 x lanes partials in a fixed order,
   and the scene / object reductions are the buckets path's.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp
from physcene.kernels.boxes import boxes_meet, rotate_z
from physcene.kernels.broadphase import decode_pair
from physcene.kernels.sdf_field import world_phi

wp.set_module_options({"enable_backward": False})

__all__ = ["BUCKETS", "broadphase_items", "bucket_of", "narrowphase_buckets", "narrowphase_items"]

# Surface points are sorted into BUCKETS^3 cells of the normalised cube (physics.pack_assets), so
# the narrowphase reads only the cells that meet the other object's box.
BUCKETS = wp.constant(4)


@wp.func
def bucket_of(x: float):
    """The point-bucket index (0..BUCKETS-1) of a normalised coordinate, clamped."""
    return wp.clamp(int(wp.floor((x + 1.0) * 0.5 * float(BUCKETS))), 0, BUCKETS - 1)


@wp.kernel
def broadphase_items(
    pair_start: wp.array(dtype=wp.int32),  # (S+1,)
    count: wp.array(dtype=wp.int32),  # (S,)
    n_slot: int,
    poses: wp.array(dtype=wp.vec4),  # (S*N,) x, y, z, yaw (cm, rad)
    sizes: wp.array(dtype=wp.vec3),  # (S*N,) w, d, h (cm)
    margin: float,
    pair_a_out: wp.array(dtype=wp.int32),  # (T,) slot of the lower-index object
    pair_b_out: wp.array(dtype=wp.int32),  # (T,)
    pair_hit_out: wp.array(dtype=wp.int32),  # (T,) 1 if the inflated boxes overlap
    pair_item_out: wp.array(dtype=wp.int32),  # (T,) position of the pair's first item (hit pairs)
    n_item: wp.array(dtype=wp.int32),  # (1,) items appended so far; 0 on entry
    items_out: wp.array(dtype=wp.int32),  # (2T,) pair * 2 + direction, the first n_item[0] valid
):
    k = wp.tid()
    a, b = decode_pair(pair_start, count, n_slot, k)
    pair_a_out[k] = a
    pair_b_out[k] = b
    hit = boxes_meet(poses[a], sizes[a] * 0.5, poses[b], sizes[b] * 0.5, margin)
    pair_hit_out[k] = hit
    if hit != 0:
        first = wp.atomic_add(n_item, 0, 2)
        items_out[first] = 2 * k
        items_out[first + 1] = 2 * k + 1
        pair_item_out[k] = first


@wp.func
def column_run(pt_bucket: wp.array(dtype=wp.int32), b0: int, kx: int, ky: int, kz0: int, kz1: int):
    """Points [lo, hi) of buckets (kx, ky, kz0..kz1): contiguous, points being bucket-sorted."""
    b = b0 + (kx * BUCKETS + ky) * BUCKETS
    return int(pt_bucket[b + kz0]), int(pt_bucket[b + kz1 + 1])


@wp.kernel
def narrowphase_items(
    items: wp.array(dtype=wp.int32),  # (>= n_item,) pair * 2 + direction
    n_item: wp.array(dtype=wp.int32),  # (1,)
    n_thread: int,  # launch size, a multiple of lanes
    lanes: int,
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
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
    part_energy_out: wp.array(dtype=float),  # (n_item*lanes,) Σ ReLU(−φ) cm
    part_depth_out: wp.array(dtype=float),  # (n_item*lanes,) max ReLU(−φ) cm
    part_gu_out: wp.array(dtype=wp.vec3),  # (n_item*lanes,) Σ ∂φ/∂u, field frame (cm/cm)
    part_yaw_out: wp.array(dtype=wp.vec2),  # (n_item*lanes,) Σ ∂φ/∂yaw of (owner, field)
):
    tid = wp.tid()
    lane = tid % lanes
    for item in range(tid // lanes, n_item[0], n_thread // lanes):
        code = items[item]
        pair = code // 2
        owner = pair_a[pair]
        field = pair_b[pair]
        if code - 2 * pair == 1:
            owner = pair_b[pair]
            field = pair_a[pair]
        po = poses[owner]
        pf = poses[field]
        ho = sizes[owner] * 0.5
        hf = sizes[field] * 0.5
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
        # the field's box seen from the owner's normalised frame -> the owner's buckets meeting it
        co = wp.cos(po[3])
        so = wp.sin(po[3])
        d = rotate_z(co, -so, -dt)  # field centre, owner-local cm
        ca = wp.abs(cr)
        sa = wp.abs(sr)
        reach = wp.vec3(ca * hf[0] + sa * hf[1], sa * hf[0] + ca * hf[1], hf[2])
        lo = wp.cw_div(d - reach, ho)
        hi = wp.cw_div(d + reach, ho)
        kx0 = bucket_of(lo[0] - 1.0e-4)
        ky0 = bucket_of(lo[1] - 1.0e-4)
        ky1 = bucket_of(hi[1] + 1.0e-4)
        kz0 = bucket_of(lo[2] - 1.0e-4)
        kz1 = bucket_of(hi[2] + 1.0e-4)
        n_ky = ky1 - ky0 + 1
        n_run = (bucket_of(hi[0] + 1.0e-4) - kx0 + 1) * n_ky
        b0 = obj_asset[owner] * (BUCKETS * BUCKETS * BUCKETS + 1)
        energy = float(0.0)
        depth = float(0.0)
        sum_gu = wp.vec3(0.0, 0.0, 0.0)
        yaw_owner = float(0.0)
        yaw_field = float(0.0)
        # the lanes stride over the concatenated column runs: (run, offset) cursor per lane
        run = int(0)
        run_lo, run_hi = column_run(pt_bucket, b0, kx0, ky0, kz0, kz1)
        offset = lane
        while run < n_run:
            if run_lo + offset >= run_hi:
                offset -= run_hi - run_lo
                run += 1
                if run < n_run:
                    kx = kx0 + run // n_ky
                    run_lo, run_hi = column_run(pt_bucket, b0, kx, ky0 + run - (run // n_ky) * n_ky, kz0, kz1)
                continue
            pl = points[run_lo + offset]
            offset += lanes
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
        out = item * lanes + lane
        part_energy_out[out] = energy
        part_depth_out[out] = depth
        if with_grad != 0:
            part_gu_out[out] = sum_gu
            part_yaw_out[out] = wp.vec2(yaw_owner, yaw_field)


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
