"""The narrowphase: ``lanes`` threads per (pair, direction) item that passed the broadphase.

The broadphase (``broadphase_items``, kernels/broadphase.py) appends the two items of every pair
whose inflated boxes meet to a dense work list. Launching threads for every pair instead (the
``buckets`` variant, kept as an A/B script in benchmarks/narrowphase_buckets.py) left 92 % of them
exiting at once on the bench batch (512 scenes x 16 objects), and on CUDA the live warps sat in
blocks whose other warps were dead, so few live warps were resident to hide memory latency.

``narrowphase_items``: ``lanes`` threads per item. The item's points in the buckets that meet
the other object's box form at most 16 contiguous runs (the (kx, ky) columns, kz range
contiguous in the bucket-sorted points); the lanes stride over their concatenation, so every
lane has a point on every iteration but the last. Partial sums go to ``item * lanes + lane``.
The item count stays on the device (no host synchronisation): on CUDA the launch covers
min(2T, a few resident waves) x lanes threads that loop over the items (grid-stride); on the
CPU, whose threads run one after another, one group of lanes threads loops over all items.
``reduce_pairs`` (kernels/reduce.py) then sums each pair's 2 x lanes partials in a fixed order,
so results are bit-for-bit repeatable although the list's order is arbitrary on CUDA.
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

from physcene.kernels.boxes import rotate_z
from physcene.kernels.sdf_field import world_phi

wp.set_module_options({"enable_backward": False})

__all__ = ["BUCKETS", "bucket_of", "column_run", "narrowphase_items"]

# Surface points are sorted into BUCKETS^3 cells of the normalised cube (physics.pack_assets), so
# the narrowphase reads only the cells that meet the other object's box.
BUCKETS = wp.constant(4)


@wp.func
def bucket_of(x: float):
    """The point-bucket index (0..BUCKETS-1) of a normalised coordinate, clamped."""
    return wp.clamp(int(wp.floor((x + 1.0) * 0.5 * float(BUCKETS))), 0, BUCKETS - 1)


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
