"""The ``buckets`` narrowphase: ``lanes`` threads for EVERY (pair, direction), an A/B variant.

It lost to the work list of kernels/narrowphase.py (the engine's one narrowphase): on the bench
batch (512 scenes x 16 objects) 92 % of its threads exit at once because the pair failed the
broadphase, and on CUDA the live warps sit in blocks whose other warps are dead. Same maths and
per-point code; results equal the engine's up to float summation order
(benchmarks/test_narrowphase_buckets.py). Kept here to time against the product:

    python benchmarks/ab_narrowphase.py --variants buckets/16 worklist/1

:class:`BucketsEngine` is a :class:`~physcene.physics.PhysicsEngine` whose ``evaluate`` runs this
narrowphase (direct launches, no graph; ``lanes_cpu`` / ``lanes_cuda`` of its config).
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import torch
import warp as wp

from physcene.kernels.boxes import boxes_meet, rotate_z
from physcene.kernels.broadphase import decode_pair
from physcene.kernels.launch import Launcher, torch_view
from physcene.kernels.narrowphase import BUCKETS, bucket_of
from physcene.kernels.penetration import DEFAULT_LANES, _allocate, _outputs, _partials
from physcene.kernels.reduce import reduce_objects, reduce_pairs, reduce_scenes
from physcene.kernels.sdf_field import world_phi
from physcene.kernels.support import table_contact
from physcene.physics import PhysicsEngine, SceneBatch

wp.set_module_options({"enable_backward": False})

__all__ = ["BucketsEngine", "launch_penetration_buckets"]


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


def launch_penetration_buckets(*, pair_start, count, n_pairs, poses, sizes, obj_asset, assets, margin,
                               tolerance, with_grad, depth_cap_ratio=0.0,
                               lanes=None) -> dict[str, torch.Tensor]:
    """:func:`physcene.kernels.penetration.launch_penetration` with the buckets narrowphase
    (direct launches): table contact, broadphase, narrowphase for every pair, the same reductions."""
    device = poses.device
    lanes = DEFAULT_LANES[device.type] if lanes is None else int(lanes)
    launch, view = Launcher(device), torch_view
    floats, ints, part = _allocate(poses, n_pairs=n_pairs, with_grad=with_grad, lanes=lanes)
    n_scene, n_slot = poses.shape[0], poses.shape[1]
    n_obj = n_scene * n_slot
    out = _outputs(floats, ints, n_scene, n_slot, n_pairs, with_grad)
    w_poses, w_sizes = view(poses.reshape(n_obj, 4), wp.vec4), view(sizes.reshape(n_obj, 3), wp.vec3)
    w_asset, w_count, w_pair_start = view(obj_asset.reshape(n_obj)), view(count), view(pair_start)
    w_points = view(assets["points"], wp.vec3)
    launch(table_contact, n_obj, [w_count, n_slot, w_poses, w_sizes, w_asset, w_points,
                                  view(assets["pt_start"]), view(assets["pt_count"]), view(assets["pt_zmin"]),
                                  view(ints[-1:]),
                                  view(out["table_depth"].view(-1)), view(out["table_energy"].view(-1)),
                                  view(out["table_below"].view(-1))])
    if n_pairs == 0:
        floats[:3 * n_scene].zero_()
        if with_grad:
            out["grad"].zero_()
        return out
    w_pair_a, w_pair_b, w_hit = view(out["pair_a"]), view(out["pair_b"]), view(out["pair_hit"])
    launch(broadphase, n_pairs, [w_pair_start, w_count, n_slot, w_poses, w_sizes, float(margin),
                                 w_pair_a, w_pair_b, w_hit])
    n_part = _partials(n_pairs, lanes)
    if with_grad:
        pe, pd, pg, py, pair_grad = torch.split(part, [n_part, n_part, 3 * n_part, 2 * n_part, 8 * n_pairs])
        pg, py, pair_grad = pg.view(n_part, 3), py.view(n_part, 2), pair_grad.view(n_pairs, 2, 4)
    else:
        pe, pd, spare = torch.split(part, [n_part, n_part, 8])
        pg, py, pair_grad = spare[:3].view(1, 3), spare[3:5].view(1, 2), spare.view(1, 2, 4)
    w_part = [view(pe), view(pd), view(pg, wp.vec3), view(py, wp.vec2)]
    w_pair_grad = view(pair_grad, wp.vec4)
    fields = [w_poses, w_sizes, w_asset, view(assets["sdf"]), view(assets["rays"]), view(assets["sdf_start"]),
              view(assets["sdf_res"]), w_points, view(assets["pt_bucket"]), int(with_grad)]
    launch(narrowphase_buckets, n_part, [w_pair_a, w_pair_b, w_hit, *fields, lanes, *w_part])
    w_pair_energy, w_pair_depth = view(out["pair_energy"]), view(out["pair_depth"])
    # compact = 0: the partials of pair p at p * 2 * lanes (pair_item unused: any int array)
    launch(reduce_pairs, n_pairs, [w_pair_a, w_pair_b, w_hit, w_poses, w_sizes, float(depth_cap_ratio),
                                   *w_part, w_hit, 0, int(with_grad), lanes, w_pair_energy, w_pair_depth,
                                   w_pair_grad])
    launch(reduce_scenes, n_scene, [w_pair_start, w_pair_energy, w_pair_depth, float(tolerance),
                                    view(out["energy"]), view(out["max_depth"]), view(out["depth_sum"])])
    if with_grad:
        launch(reduce_objects, n_obj, [w_pair_start, w_count, n_slot, w_pair_grad,
                                       view(out["grad"].view(n_obj, 4), wp.vec4)])
    return out


class BucketsEngine(PhysicsEngine):
    """The engine with the buckets narrowphase (everything but ``evaluate`` is the engine's)."""

    def evaluate(self, batch: SceneBatch, poses: torch.Tensor | None = None, *, with_grad: bool = False,
                 tolerance: float = 0.0) -> dict[str, torch.Tensor]:
        return launch_penetration_buckets(
            pair_start=batch.pair_start, count=batch.count, n_pairs=batch.n_pairs,
            poses=self._poses(batch, poses), sizes=batch.sizes, obj_asset=batch.asset_index,
            assets=self.packed_assets(), margin=self.config.margin_cm, tolerance=tolerance,
            depth_cap_ratio=self.config.depth_cap_ratio,
            with_grad=with_grad,
            lanes=self.config.lanes_cuda if self.device.type == "cuda" else self.config.lanes_cpu)
