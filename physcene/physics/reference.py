"""Plain-torch reference of the penetration engine: the tests' oracle and the benchmarks' baseline.

The same maths as kernels/penetration.py (docs/physics.md), written with torch tensor ops and
autograd instead of hand-written kernels, so it runs in float64 and its gradients come from
torch's autograd rather than from our derivative formulas. Inputs are the engine's packed
batch (:class:`physcene.physics.SceneBatch` fields) and packed assets; nothing here loops over
pairs or points in Python (only over fixed-size chunks of queries, to bound memory).
"""

from __future__ import annotations

import torch

__all__ = ["reference_penetration", "reference_support_gap", "sdf_sample", "world_phi"]

# Gradients of the normalised field smaller than this are "vanished": fall back to h_min.
_GRAD_EPS = 1.0e-6


def _rotate_z(c: torch.Tensor, s: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate v (..., 3) about +z by the angle with cosine c and sine s (...,)."""
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], dim=-1)


def _cell(q: torch.Tensor, res: torch.Tensor):
    """(q clamped to the cube, node offset of its cell (K,), fractions (K, 3), 1/voxel (K,))."""
    qc = q.clamp(-1.0, 1.0)
    inv_h = (res.to(q.dtype) - 1.0) * 0.5
    f = (qc + 1.0) * inv_h[:, None]
    idx = torch.minimum(torch.floor(f.detach()).long().clamp(min=0), (res - 2)[:, None])
    node = (idx[:, 0] * res + idx[:, 1]) * res + idx[:, 2]
    return qc, node, f - idx.to(q.dtype), inv_h


def _trilinear(grid: torch.Tensor, base: torch.Tensor, elem: int, res: torch.Tensor, t: torch.Tensor,
               inv_h: torch.Tensor):
    """Value (K,) with autograd to t, and its detached analytic gradient per normalised unit (K, 3).

    ``elem``: distance between consecutive nodes in ``grid`` (1 for φ, 3 for interleaved rays).
    """
    sz, sy, sx = elem, res * elem, res * res * elem
    c000, c001, c010, c011, c100, c101, c110, c111 = (
        grid[base + ox * sx + oy * sy + oz * sz].to(t.dtype)
        for ox in (0, 1) for oy in (0, 1) for oz in (0, 1))
    tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
    c00 = c000 + (c001 - c000) * tz
    c01 = c010 + (c011 - c010) * tz
    c10 = c100 + (c101 - c100) * tz
    c11 = c110 + (c111 - c110) * tz
    c0 = c00 + (c01 - c00) * ty
    c1 = c10 + (c11 - c10) * ty
    value = c0 + (c1 - c0) * tx
    with torch.no_grad():
        gx = (c1 - c0) * inv_h
        d0z = c001 - c000 + (c011 - c010 - c001 + c000) * ty
        d1z = c101 - c100 + (c111 - c110 - c101 + c100) * ty
        gy = ((1.0 - tx) * (c01 - c00) + tx * (c11 - c10)) * inv_h
        gz = ((1.0 - tx) * d0z + tx * d1z) * inv_h
    return value, torch.stack([gx, gy, gz], dim=-1)


def sdf_sample(sdf: torch.Tensor, start: torch.Tensor, res: torch.Tensor, q: torch.Tensor):
    """Trilinear φ at q with the engine's outside rule (clamp to the cube + distance to it).

    sdf: flat grids; start, res: (K,) long per query; q: (K, 3) normalised coordinates.
    Returns (φ (K,), ∂φ/∂q (K, 3) detached analytic gradient). φ carries autograd to q.
    """
    qc, node, t, inv_h = _cell(q, res)
    phi, grad = _trilinear(sdf, start + node, 1, res, t, inv_h)
    out = q - qc
    sq = (out * out).sum(-1)
    outside = sq > 0
    safe = torch.where(outside, sq, torch.ones_like(sq))  # keeps sqrt's gradient finite at 0
    dist = torch.where(outside, torch.sqrt(safe), torch.zeros_like(sq))
    with torch.no_grad():
        unit = out / torch.where(outside, dist, torch.ones_like(dist))[:, None]
        grad = torch.where(out != 0, torch.zeros_like(grad), grad) + unit
    return phi + dist, grad


def world_phi(sdf, rays, start, res, q, half):
    """World φ (cm): max(φ_n / |S⁻¹ n̂|, −h_k r_k(q)) where φ_n < 0, else φ_n (docs/physics.md).

    start, res: (K,) long; q (K, 3); half (K, 3) cm. Autograd flows through the trilinear
    values; the first-order scale is a constant, as in the kernels.
    """
    phi_n, g = sdf_sample(sdf, start, res, q)
    scale = _world_scale(g, half).detach()
    _, node, t, inv_h = _cell(q, res)
    terms = [phi_n * scale]
    for k in range(3):
        r, _ = _trilinear(rays, 3 * (start + node) + k, 3, res, t, inv_h)
        # axes at least as long as the scale are not consulted (h_k r_k >= h_k |φ_n| >= the depth)
        terms.append(torch.where(half[:, k] < scale, -half[:, k] * r, torch.full_like(r, -torch.inf)))
    capped = torch.stack(terms, -1).max(-1).values
    # under a uniform scale the first-order term is exact and the rays are not consulted
    uniform = half.max(-1).values <= half.min(-1).values * 1.000001
    capped = torch.where(uniform, terms[0], capped)
    return torch.where(phi_n < 0, capped, phi_n)


def _world_scale(grad: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """cm per normalised unit along the normal: 1/|S⁻¹ n̂|, h_min where the gradient vanishes."""
    glen = grad.norm(dim=-1)
    m = grad / half / glen.clamp(min=_GRAD_EPS)[:, None]
    return torch.where(glen < _GRAD_EPS, half.min(dim=-1).values, 1.0 / m.norm(dim=-1).clamp(min=1e-30))


def _footprint_gap(pa, ha, pb, hb):
    """Largest separation of two yawed footprints over their 4 axes (cm, < 0: overlap)."""
    ca, sa, cb, sb = torch.cos(pa[:, 3]), torch.sin(pa[:, 3]), torch.cos(pb[:, 3]), torch.sin(pb[:, 3])
    dx, dy = pb[:, 0] - pa[:, 0], pb[:, 1] - pa[:, 1]
    gaps = []
    for ux, uy in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):
        ra = ha[:, 0] * (ca * ux + sa * uy).abs() + ha[:, 1] * (-sa * ux + ca * uy).abs()
        rb = hb[:, 0] * (cb * ux + sb * uy).abs() + hb[:, 1] * (-sb * ux + cb * uy).abs()
        gaps.append((dx * ux + dy * uy).abs() - ra - rb)
    return torch.stack(gaps, -1).max(-1).values


def _pairs(count: torch.Tensor, n_slot: int):
    """All (s, i, j), i < j < count[s], in the engine's CSR order: (T,) each."""
    iu = torch.triu_indices(n_slot, n_slot, 1, device=count.device)
    n_scene = count.shape[0]
    s = torch.arange(n_scene, device=count.device)[:, None].expand(-1, iu.shape[1])
    valid = iu[1][None, :] < count[:, None].long()
    return s[valid], iu[0][None, :].expand(n_scene, -1)[valid], iu[1][None, :].expand(n_scene, -1)[valid]


def reference_penetration(*, poses: torch.Tensor, sizes: torch.Tensor, count: torch.Tensor,
                          obj_asset: torch.Tensor, assets: dict[str, torch.Tensor], margin: float,
                          tolerance: float = 0.0, with_grad: bool = False, depth_cap_ratio: float = 0.0,
                          chunk_queries: int = 1 << 21) -> dict[str, torch.Tensor]:
    """The engine's forward (and gradient) in torch, in the dtype of ``poses``.

    ``assets`` are the engine's packed arrays (surface and interior samples); ``depth_cap_ratio``
    as :class:`~physcene.physics.PhysicsConfig`'s.

    poses (S, N, 4), sizes (S, N, 3), count (S,), obj_asset (S, N). Returns ``energy``,
    ``max_depth``, ``depth_sum`` (S,); ``pair_hit``, ``pair_energy``, ``pair_depth`` (T,) in CSR
    order; ``table_depth``, ``table_energy`` (S, N); ``grad`` (S, N, 4) of Σ_s energy when asked.
    """
    dtype, device = poses.dtype, poses.device
    n_scene, n_slot = poses.shape[:2]
    flat_pose = poses.reshape(-1, 4)
    flat_half = sizes.reshape(-1, 3).to(dtype) * 0.5
    flat_asset = obj_asset.reshape(-1).long()
    s, i, j = _pairs(count, n_slot)
    a, b = s * n_slot + i, s * n_slot + j
    with torch.no_grad():
        pa, pb = flat_pose[a], flat_pose[b]
        z_ok = (pa[:, 2] - pb[:, 2]).abs() <= flat_half[a, 2] + flat_half[b, 2] + margin
        hit = z_ok & (_footprint_gap(pa, flat_half[a], pb, flat_half[b]) <= margin)
    cand = torch.nonzero(hit).reshape(-1)
    # both directions of every candidate: (owner, field)
    owner = torch.cat([a[cand], b[cand]])
    field = torch.cat([b[cand], a[cand]])
    pt_count = assets["pt_count"].long()
    p_max = int(pt_count.max().item()) if pt_count.numel() else 0
    lane = torch.arange(p_max, device=device)
    sdf = assets["sdf"]
    n_points = assets["points"].shape[0]
    sdf_start, sdf_res = assets["sdf_start"].long(), assets["sdf_res"].long()
    combo_energy = torch.zeros(owner.shape[0], dtype=dtype, device=device)
    combo_depth = torch.zeros(owner.shape[0], dtype=dtype, device=device)
    grad = torch.zeros_like(flat_pose) if with_grad else None
    step = max(1, chunk_queries // max(p_max, 1))
    for lo in range(0, owner.shape[0], step):  # fixed-size chunks of queries, not pairs
        o, f = owner[lo:lo + step], field[lo:lo + step]
        pose = flat_pose.detach().clone().requires_grad_(True) if with_grad else flat_pose
        po, pf = pose[o], pose[f]
        ho, hf = flat_half[o], flat_half[f]
        ao, af = flat_asset[o], flat_asset[f]
        valid = lane[None, :] < pt_count[ao][:, None]
        pidx = (assets["pt_start"].long()[ao][:, None] + lane[None, :]).clamp(max=n_points - 1)
        pl = assets["points"][pidx].to(dtype) * ho[:, None, :]  # (K, P, 3) owner-local cm
        dyaw = po[:, 3] - pf[:, 3]
        v = _rotate_z(torch.cos(dyaw)[:, None], torch.sin(dyaw)[:, None], pl)
        t_rel = _rotate_z(torch.cos(pf[:, 3]), -torch.sin(pf[:, 3]), po[:, :3] - pf[:, :3])
        u = v + t_rel[:, None, :]
        q = (u / hf[:, None, :]).reshape(-1, 3)
        k = q.shape[0] // max(p_max, 1)
        # outside the field's box nothing penetrates: only points in it read the grids
        sel = torch.nonzero(valid.reshape(-1) & (q.detach().abs() <= 1.0).all(-1)).reshape(-1)
        combo = sel // max(p_max, 1)
        phi = world_phi(sdf, assets["rays"], sdf_start[af][combo], sdf_res[af][combo], q[sel], hf[combo])
        inside = phi < 0
        flat_depth = torch.zeros(q.shape[0], dtype=dtype, device=device)
        flat_depth = flat_depth.index_put((sel,), torch.where(inside, -phi, torch.zeros_like(phi)))
        depth = flat_depth.reshape(k, p_max)
        e = depth.sum(-1)
        combo_energy[lo:lo + step] = e.detach()
        combo_depth[lo:lo + step] = depth.detach().max(-1).values if p_max else 0.0
        if with_grad and e.numel():
            (gpose,) = torch.autograd.grad(e.sum(), pose, allow_unused=True)
            if gpose is not None:
                grad += gpose
    n_cand = cand.shape[0]
    pair_energy = torch.zeros(a.shape[0], dtype=dtype, device=device)
    pair_depth = torch.zeros(a.shape[0], dtype=dtype, device=device)
    pair_energy[cand] = combo_energy[:n_cand] + combo_energy[n_cand:]
    pair_depth[cand] = torch.maximum(combo_depth[:n_cand], combo_depth[n_cand:])
    if depth_cap_ratio > 0:
        thin = torch.minimum(flat_half[a].min(-1).values, flat_half[b].min(-1).values)
        pair_depth = torch.minimum(pair_depth, depth_cap_ratio * thin)
    energy = torch.zeros(n_scene, dtype=dtype, device=device).index_add_(0, s, pair_energy)
    max_depth = torch.zeros(n_scene, dtype=dtype, device=device).scatter_reduce_(0, s, pair_depth, "amax")
    depth_sum = torch.zeros(n_scene, dtype=dtype, device=device).index_add_(
        0, s, torch.where(pair_depth > tolerance, pair_depth, torch.zeros_like(pair_depth)))
    table_depth, table_energy = _table(flat_pose.detach(), flat_half, flat_asset, assets, count, n_slot,
                                       p_max)
    out = {"energy": energy, "max_depth": max_depth, "depth_sum": depth_sum, "pair_hit": hit.int(),
           "pair_energy": pair_energy, "pair_depth": pair_depth,
           "table_depth": table_depth.reshape(n_scene, n_slot),
           "table_energy": table_energy.reshape(n_scene, n_slot)}
    if with_grad:
        out["grad"] = grad.reshape(n_scene, n_slot, 4)
    return out


def _table(pose, half, asset, assets, count, n_slot, p_max):
    lane = torch.arange(p_max, device=pose.device)
    pt_count = assets["pt_count"].long()[asset]
    n_points = assets["points"].shape[0]
    pidx = (assets["pt_start"].long()[asset][:, None] + lane[None, :]).clamp(max=n_points - 1)
    z = pose[:, 2:3] + assets["points"][pidx][..., 2].to(pose.dtype) * half[:, 2:3]
    slot = torch.arange(pose.shape[0], device=pose.device)
    slot_ok = (slot % n_slot) < count.long().repeat_interleave(n_slot)
    valid = (lane[None, :] < pt_count[:, None]) & slot_ok[:, None]
    below = torch.where(valid, (-z).clamp(min=0), torch.zeros_like(z))
    return below.max(-1).values if p_max else below.sum(-1), below.sum(-1)


def reference_support_gap(*, poses: torch.Tensor, sizes: torch.Tensor, count: torch.Tensor,
                          overlap_eps: float) -> torch.Tensor:
    """Per object, its bottom's height above the highest support under it, (S, N) cm."""
    n_scene, n_slot = poses.shape[:2]
    half = sizes.to(poses.dtype) * 0.5
    pi = poses[:, :, None, :].expand(-1, -1, n_slot, -1).reshape(-1, 4)
    pj = poses[:, None, :, :].expand(-1, n_slot, -1, -1).reshape(-1, 4)
    hi = half[:, :, None, :].expand(-1, -1, n_slot, -1).reshape(-1, 3)
    hj = half[:, None, :, :].expand(-1, n_slot, -1, -1).reshape(-1, 3)
    over = (_footprint_gap(pi, hi, pj, hj) < -overlap_eps).reshape(n_scene, n_slot, n_slot)
    ar = torch.arange(n_slot, device=poses.device)
    valid_j = ar[None, None, :] < count[:, None, None].long()
    over = over & valid_j & (ar[:, None] != ar[None, :])[None]
    bottom = poses[..., 2] - half[..., 2]  # (S, N)
    top = poses[..., 2] + half[..., 2]
    below = over & (top[:, None, :] <= bottom[:, :, None])
    inside = over & (top[:, None, :] > bottom[:, :, None]) & (bottom[:, None, :] < bottom[:, :, None])
    far = torch.full(below.shape, float("inf"), dtype=top.dtype, device=top.device)
    gaps = torch.where(below, bottom[:, :, None] - top[:, None, :], far)
    gap = torch.minimum(bottom, gaps.min(-1).values)
    gap = torch.where(inside.any(-1), torch.zeros_like(gap), gap)
    return torch.where(ar[None, :] < count[:, None].long(), gap, torch.zeros_like(gap))
