"""The engine's batch: scenes packed into padded device tensors, its verdicts, and the packed assets.

:class:`SceneBatch` is what every kernel launch reads (poses, sizes, asset slots, CSR pair offsets);
:class:`Score` is the per-scene verdict :meth:`physcene.physics.PhysicsEngine.score` returns;
:func:`pack_assets` concatenates assets' SDF grids, axis-ray distances and bucketed surface points
into the flat arrays the kernels index. Units: cm and radians.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from physcene.assets.interior import interior_points
from physcene.kernels.penetration import BUCKETS
from physcene.scene import zone_overshoot

__all__ = ["SceneBatch", "Score", "axis_ray_distances", "bucket_points", "pack_assets"]


@dataclass
class SceneBatch:
    """Scenes packed for the engine: S scenes padded to N object slots, on one device."""

    poses: torch.Tensor
    """(S, N, 4) float32: x, y, z (cm), yaw (rad); padded slots are 0."""
    sizes: torch.Tensor
    """(S, N, 3) float32 w, d, h (cm); padded slots are 1."""
    mask: torch.Tensor
    """(S, N) bool, True on real objects."""
    ids: list[list[str]]
    """Instance ids per scene, in slot order."""
    asset_index: torch.Tensor
    """(S, N) int32 index into the engine's packed assets."""
    count: torch.Tensor
    """(S,) int32 objects per scene."""
    pair_start: torch.Tensor
    """(S+1,) int32 CSR offsets of each scene's count*(count-1)/2 pairs (i < j, row-major)."""
    n_pairs: int
    """Total pairs T (host int: sizes the launches without a device sync)."""
    zones: torch.Tensor | None = None
    """(S, 4) float32 xmin, xmax, ymin, ymax (cm) of each scene's placement zone (host or device);
    None when the batch was built without them."""
    _resolved: list = field(default_factory=list, repr=False)
    _bounds: np.ndarray | None = field(default=None, repr=False)

    @property
    def asset_ids(self) -> list[list[str]]:
        """The asset used for each object, per scene."""
        return self._per_scene(1)

    @property
    def fallbacks(self) -> list[list[str | None]]:
        """How the library fell back for each object (None when the retrieval was exact)."""
        return self._per_scene(2)

    def _per_scene(self, k: int) -> list[list]:
        b = self._bounds if self._bounds is not None else [0]
        return [[r[k] for r in self._resolved[b[s]:b[s + 1]]] for s in range(len(b) - 1)]

    @property
    def n_scene(self) -> int:
        return self.poses.shape[0]

    def deep_pairs(self, pair_depth, tolerance: float = 0.0) -> list[list[tuple[int, int, float]]]:
        """Per scene, the pairs ``(i, j, depth)`` whose ``pair_depth`` (T,) exceeds ``tolerance`` (cm)."""
        depth = pair_depth.cpu().numpy() if isinstance(pair_depth, torch.Tensor) else np.asarray(pair_depth)
        hot = np.nonzero(depth > tolerance)[0]
        pairs: list[list[tuple[int, int, float]]] = [[] for _ in range(self.n_scene)]
        if hot.size:
            for (s, i, j), d in zip(self.pair_slots()[hot].tolist(), depth[hot].tolist()):
                pairs[s].append((i, j, d))
        return pairs

    def zone_overshoot(self, poses: torch.Tensor | None = None) -> np.ndarray:
        """(S, N) cm on the host: how far each object's yawed footprint reaches past its scene's
        zone (:func:`physcene.scene.zone_overshoot`; 0 inside and on padded slots). Needs ``zones``."""
        if self.zones is None:
            raise ValueError("zone_overshoot: this SceneBatch was built without zones")
        poses = (self.poses if poses is None else poses).detach().cpu().numpy().astype(np.float64)
        sizes = self.sizes.cpu().numpy().astype(np.float64)
        zones = self.zones.cpu().numpy()[:, None, :]
        past = zone_overshoot(poses[..., :2], sizes[..., :2], poses[..., 3], zones)
        return past * self.mask.cpu().numpy()

    def pair_slots(self) -> np.ndarray:
        """(T, 3) int64 (scene, i, j) of every pair in CSR order (host)."""
        count = self.count.cpu().numpy().astype(np.int64)
        rows = []
        for n in np.unique(count):  # one vectorised block per distinct object count
            scenes = np.nonzero(count == n)[0]
            iu, ju = np.triu_indices(int(n), 1)
            rows.append(np.stack([np.repeat(scenes, iu.size), np.tile(iu, scenes.size),
                                  np.tile(ju, scenes.size)], -1))
        table = np.concatenate(rows) if rows else np.zeros((0, 3), np.int64)
        order = np.lexsort((table[:, 2], table[:, 1], table[:, 0]))
        return table[order]


@dataclass
class Score:
    """Per-scene physics verdicts (cm)."""

    energy: torch.Tensor
    """(S,) Σ over pairs of Σ ReLU(−φ) in both directions (cm summed over points)."""
    max_depth: torch.Tensor
    """(S,) deepest pair penetration pen(i, j)."""
    pairs: list[list[tuple[int, int, float]]]
    """Per scene, (i, j, depth_cm) for every pair with depth > 0 (object indices, i < j)."""
    floating: list[list[int]]
    """Per scene, indices of floating objects."""
    table_penetration: torch.Tensor
    """(S,) deepest surface point below the table top z = 0."""
    depth_sum: torch.Tensor
    """(S,) Σ pen(i, j) over pairs deeper than the tolerance score was called with."""
    table_depth: torch.Tensor
    """(S, N) per object, deepest point below z = 0."""
    ids: list[list[str]]


# Axis-ray value of outside nodes not next to a crossing: large enough never to be the minimum.
_FAR = 8.0


def axis_ray_distances(sdf: np.ndarray) -> np.ndarray:
    """Distances to the surface along ±x, ±y, ±z at every grid node, (3, R, R, R) normalised.

    Inside nodes (φ < 0): the distance along axis k to the nearest zero crossing of the grid
    line (linear interpolation between nodes; the cube's faces count as crossings). Outside
    nodes next to a crossing (within one voxel) get minus that distance, so trilinear
    interpolation across a face perpendicular to k is exact; other outside nodes get ``_FAR``.
    """
    res = sdf.shape[0]
    voxel = 2.0 / (res - 1)
    nodes = np.arange(res, dtype=np.float64)
    out = np.empty((3, res, res, res), np.float32)
    for axis in range(3):
        phi = np.moveaxis(np.asarray(sdf, np.float64), axis, -1)
        inside = phi < 0
        a, b = phi[..., :-1], phi[..., 1:]
        cross = inside[..., :-1] != inside[..., 1:]
        with np.errstate(divide="ignore", invalid="ignore"):
            pos = nodes[:-1] + np.where(cross, a / (a - b), 0.0)
        left = np.full(phi.shape, -np.inf)
        left[..., 1:] = np.where(cross, pos, -np.inf)
        left[..., 0] = np.where(inside[..., 0], 0.0, -np.inf)
        right = np.full(phi.shape, np.inf)
        right[..., :-1] = np.where(cross, pos, np.inf)
        right[..., -1] = np.where(inside[..., -1], res - 1.0, np.inf)
        left = np.maximum.accumulate(left, axis=-1)
        right = np.minimum.accumulate(right[..., ::-1], axis=-1)[..., ::-1]
        dist = np.minimum(nodes - left, right - nodes)  # node units
        value = np.where(inside, dist * voxel, np.where(dist <= 1.0, -dist * voxel, _FAR))
        out[axis] = np.moveaxis(value, -1, axis)
    return out


def bucket_points(points: np.ndarray, buckets: int = BUCKETS) -> tuple[np.ndarray, np.ndarray]:
    """Points sorted by their cell of a buckets^3 grid over [-1, 1]^3, and each cell's first index.

    Returns (sorted points (P, 3), offsets (buckets^3 + 1,)); cell (kx, ky, kz) is
    (kx * buckets + ky) * buckets + kz, as ``bucket_of`` in kernels/penetration.py computes it.
    """
    k = np.clip(np.floor((points.astype(np.float64) + 1.0) * 0.5 * buckets), 0, buckets - 1).astype(np.int64)
    cell = (k[:, 0] * buckets + k[:, 1]) * buckets + k[:, 2]
    order = np.argsort(cell, kind="stable")
    offsets = np.searchsorted(cell[order], np.arange(buckets**3 + 1))
    return points[order], offsets


def _derived_arrays(asset, interior_per_axis: int) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """An asset's arrays that packing derives from its SDF and points: the axis-ray distances per
    node (interleaved, flat) and its bucketed samples (:func:`bucket_points`): the surface points
    and the interior samples (:func:`physcene.assets.interior.interior_points`)."""
    samples = np.concatenate([asset.points, interior_points(asset.sdf, interior_per_axis)])
    return np.moveaxis(axis_ray_distances(asset.sdf), 0, -1).reshape(-1), bucket_points(samples)


def pack_assets(assets: Sequence, device: torch.device, derived: dict | None = None,
                before: dict[str, torch.Tensor] | None = None, *,
                interior_per_axis: int = 0) -> dict[str, torch.Tensor]:
    """Concatenate assets' SDF grids and samples into the engine's flat arrays on ``device``.

    The samples of an asset are its surface points and, with ``interior_per_axis`` > 0, its
    interior samples (:class:`~physcene.physics.PhysicsConfig`'s ``interior_per_axis``).

    ``derived``: a cache of each asset's derived arrays by ``asset_id`` (filled here).
    ``before``: the packed arrays of the assets that come first; ``assets`` are appended to them
    (their offsets continue from its ends), so new assets cost host work for themselves only.
    """
    derived = {} if derived is None else derived
    for a in assets:
        if a.asset_id not in derived:
            derived[a.asset_id] = _derived_arrays(a, interior_per_axis)
    sdf_base = 0 if before is None else int(before["sdf"].numel())
    pt_base = 0 if before is None else int(before["points"].shape[0])
    res = np.array([a.resolution for a in assets], dtype=np.int32)
    bucketed = [derived[a.asset_id][1] for a in assets]
    n_pt = np.array([len(b[0]) for b in bucketed], dtype=np.int32)
    pt_start = pt_base + np.concatenate([[0], np.cumsum(n_pt)[:-1]]).astype(np.int64)
    sdf_start = sdf_base + np.concatenate([[0], np.cumsum(res.astype(np.int64) ** 3)[:-1]])
    if sdf_base + int((res.astype(np.int64) ** 3).sum()) >= 2**31:
        raise ValueError(f"{len(assets)} assets exceed 2^31 SDF samples; use lower resolutions")
    arrays = {
        "sdf": np.concatenate([a.sdf.reshape(-1) for a in assets]).astype(np.float32),
        # per node its 3 axis-ray distances, interleaved, at 3 * sdf_start (penetration.world_phi)
        "rays": np.concatenate([derived[a.asset_id][0] for a in assets]),
        "sdf_start": sdf_start.astype(np.int32),
        "sdf_res": res,
        "points": np.concatenate([b[0] for b in bucketed]).astype(np.float32).reshape(-1, 3),
        "pt_start": pt_start.astype(np.int32),
        "pt_count": n_pt,
        # lowest normalised z of each asset's points: table_contact skips objects resting on z = 0
        "pt_zmin": np.array([a.points[:, 2].min() if len(a.points) else 0.0 for a in assets], np.float32),
        "pt_bucket": np.concatenate([b[1] + start for b, start in zip(bucketed, pt_start)]).astype(np.int32),
    }
    packed = {k: torch.from_numpy(np.ascontiguousarray(v)).to(device) for k, v in arrays.items()}
    if before is None:
        return packed
    return {k: torch.cat([before[k], v]) for k, v in packed.items()}
