"""The differentiable SDF physics engine (PADA, paper eq. 3): penetration, support, pose gradients.

``PhysicsEngine(library, device)`` packs scenes into a padded batch of torch tensors on the
device and scores them with the Warp kernels of :mod:`physcene.kernels.penetration`:

>>> engine = PhysicsEngine(device="cpu")
>>> score = engine.score([scene])           # per-pair depths, energies, floating objects
>>> batch = engine.pack([scene])
>>> energy = engine.penetration_energy(batch, batch.poses.requires_grad_())   # (S,) cm
>>> energy.sum().backward()                 # hand-written pose gradients

Units: cm and radians; energies are sums over surface points of penetration depths (cm).
The maths and its choices are in docs/physics.md; the float64 oracle is
:mod:`physcene.physics_reference`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import chain

import numpy as np
import torch

from physcene.config import ConfigError, load_dataclass
from physcene.kernels.penetration import BUCKETS, NARROWPHASES, launch_penetration, launch_support
from physcene.scene import Scene, zone_overshoot

__all__ = ["PhysicsConfig", "PhysicsEngine", "SceneBatch", "Score", "axis_ray_distances", "bucket_points",
           "pack_assets"]


@dataclass(frozen=True, kw_only=True)
class PhysicsConfig:
    """Engine settings (``configs/physics.yaml``)."""

    margin_cm: float = 0.1
    """Broadphase inflation of every box: pairs closer than this are checked point by point."""
    floating_tolerance_cm: float = 1.0
    """An object whose bottom is more than this above every support under it is floating."""
    footprint_overlap_cm: float = 0.01
    """Two footprints must overlap by more than this to count as one standing on the other."""
    lanes_cpu: int = 1
    """Narrowphase threads per (pair, direction) on the CPU (run one after another: 1 is fastest)."""
    lanes_cuda: int = 64
    """Narrowphase threads per (pair, direction) on CUDA (more lanes fill the GPU)."""
    narrowphase: str = "worklist"
    """``worklist``: threads only for the (pair, direction) items that pass the broadphase
    (kernels/narrowphase.py); ``buckets``: threads for every pair, most exiting at once. Same
    results up to float summation order (docs/physics.md)."""

    narrowphase_block_dim: int = 128
    """CUDA threads per block of the narrowphase launch (worklist: with fewer, a block whose items
    are done frees its SM slot sooner; a multiple of the lanes keeps an item in one block)."""
    graph: bool = True
    """Capture the kernel launches once per batch layout (CUDA graph; Warp CPU graph on the CPU)
    and replay them when the same batch is scored again (TTO steps, benchmarks): host launch
    cost off the critical path, at one capture per new layout. Same results."""

    def __post_init__(self):
        if not 1 <= self.narrowphase_block_dim <= 1024:
            raise ConfigError(f"configs/physics.yaml: narrowphase_block_dim={self.narrowphase_block_dim}: "
                              "expected 1..1024")
        if self.narrowphase not in NARROWPHASES:
            raise ConfigError(f"configs/physics.yaml: narrowphase={self.narrowphase!r}: expected one of "
                              f"{', '.join(NARROWPHASES)}")

    @classmethod
    def load(cls, overrides: Sequence[str] = ()) -> PhysicsConfig:
        return load_dataclass(cls, "physics", overrides)


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


def _derived_arrays(asset) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """An asset's arrays that packing derives from its SDF and points: the axis-ray distances per
    node (interleaved, flat) and its bucketed points (:func:`bucket_points`)."""
    return np.moveaxis(axis_ray_distances(asset.sdf), 0, -1).reshape(-1), bucket_points(asset.points)


def pack_assets(assets: Sequence, device: torch.device, derived: dict | None = None,
                before: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
    """Concatenate assets' SDF grids and points into the engine's flat arrays on ``device``.

    ``derived``: a cache of each asset's derived arrays by ``asset_id`` (filled here).
    ``before``: the packed arrays of the assets that come first; ``assets`` are appended to them
    (their offsets continue from its ends), so new assets cost host work for themselves only.
    """
    derived = {} if derived is None else derived
    for a in assets:
        if a.asset_id not in derived:
            derived[a.asset_id] = _derived_arrays(a)
    sdf_base = 0 if before is None else int(before["sdf"].numel())
    pt_base = 0 if before is None else int(before["points"].shape[0])
    res = np.array([a.resolution for a in assets], dtype=np.int32)
    n_pt = np.array([len(a.points) for a in assets], dtype=np.int32)
    bucketed = [derived[a.asset_id][1] for a in assets]
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


class PhysicsEngine:
    """Batched penetration, support and pose gradients for scenes of posed assets."""

    def __init__(self, library=None, device: str | torch.device = "cpu", config: PhysicsConfig | None = None):
        if library is None:
            from physcene.assets import default_library

            library = default_library()
        self.library = library
        self.device = torch.device(device)
        if self.device.type not in ("cpu", "cuda"):
            raise ValueError(f"engine device {str(device)!r}: expected cpu, cuda or cuda:N")
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"engine device {str(device)!r}: CUDA is not available on this machine")
        if self.device.type == "cuda" and self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        self.config = config or PhysicsConfig()
        self._assets: list = []  # engine-local asset table, grows as new assets are seen
        self._asset_slot: dict[str, int] = {}
        self._resolved: dict[tuple[str, str | None], tuple[int, str, str | None]] = {}
        self._packed: tuple[int, dict[str, torch.Tensor]] | None = None
        self._derived: dict[str, tuple] = {}  # pack_assets' per-asset arrays, kept across repacks
        self._text_packer = None  # physcene.text_pack.TextPacker, built on the first pack_texts

    # Assets ------------------------------------------------------------------------------------
    def _resolve(self, category: str, asset_id: str | None) -> tuple[int, str, str | None]:
        key = (category, asset_id)
        hit = self._resolved.get(key)
        if hit is None:
            retrieval = self.library.resolve(category, asset_id)
            asset = retrieval.asset
            slot = self._asset_slot.get(asset.asset_id)
            if slot is None:
                slot = self._asset_slot[asset.asset_id] = len(self._assets)
                self._assets.append(asset)
            hit = self._resolved[key] = (slot, asset.asset_id, retrieval.fallback)
        return hit

    def packed_assets(self) -> dict[str, torch.Tensor]:
        """The flat asset arrays on the engine's device (new assets are appended as they appear)."""
        if self._packed is None:
            self._packed = (len(self._assets), pack_assets(self._assets, self.device, self._derived))
        elif self._packed[0] != len(self._assets):  # append the new assets to what is uploaded
            n, packed = self._packed
            self._packed = (len(self._assets),
                            pack_assets(self._assets[n:], self.device, self._derived, before=packed))
        return self._packed[1]

    # Packing -----------------------------------------------------------------------------------
    def pack(self, scenes: Sequence[Scene] | Scene) -> SceneBatch:
        """Scenes → a padded :class:`SceneBatch` on the engine's device."""
        if isinstance(scenes, Scene):
            scenes = [scenes]
        scenes = list(scenes)
        for k, scene in enumerate(scenes):
            if not isinstance(scene, Scene):
                raise TypeError(f"pack: item {k} is a {type(scene).__name__}, expected Scene")
        counts = np.array([len(s.objects) for s in scenes], dtype=np.int64)
        n_scene, n_slot = len(scenes), max(1, int(counts.max()) if len(scenes) else 1)
        flat = [o for s in scenes for o in s.objects]
        resolve, cache = self._resolve, self._resolved
        resolved = [cache.get((o.category, o.asset_id)) or resolve(o.category, o.asset_id) for o in flat]
        slot_of = (np.repeat(np.arange(n_scene) * n_slot, counts)
                   + np.arange(len(flat)) - np.repeat(np.cumsum(counts) - counts, counts))
        # one host buffer per dtype, one transfer each: [x, y, z, yaw, w, d, h] and [asset]
        rows = np.zeros((n_scene * n_slot, 7), np.float32)
        rows[:, 4:] = 1.0
        asset = np.zeros(n_scene * n_slot, np.int32)
        if flat:
            rows[slot_of] = np.fromiter(chain.from_iterable((*o.center, o.yaw, *o.size) for o in flat),
                                        np.float32, count=7 * len(flat)).reshape(-1, 7)
            asset[slot_of] = np.fromiter((r[0] for r in resolved), np.int32, count=len(flat))
        pairs = counts * (counts - 1) // 2
        pair_start = np.concatenate([[0], np.cumsum(pairs)])
        if pair_start[-1] >= 2**31 // 64:
            raise ValueError(f"batch has {pair_start[-1]} object pairs; split it into smaller batches")
        ints = torch.from_numpy(np.concatenate([asset, counts, pair_start]).astype(np.int32)).to(self.device)
        rows_t = torch.from_numpy(rows).to(self.device).view(n_scene, n_slot, 7)
        count_t = ints[n_scene * n_slot:n_scene * n_slot + n_scene]
        return SceneBatch(
            poses=rows_t[..., :4].contiguous(),
            sizes=rows_t[..., 4:].contiguous(),
            mask=torch.arange(n_slot, device=self.device)[None, :] < count_t[:, None],
            ids=[s.ids() for s in scenes],
            asset_index=ints[:n_scene * n_slot].view(n_scene, n_slot),
            count=count_t,
            pair_start=ints[n_scene * n_slot + n_scene:],
            n_pairs=int(pair_start[-1]),
            zones=torch.tensor([[s.zone.xmin, s.zone.xmax, s.zone.ymin, s.zone.ymax] for s in scenes],
                               dtype=torch.float32).reshape(n_scene, 4),
            _resolved=resolved,
            _bounds=np.concatenate([[0], np.cumsum(counts)]),
        )

    def pack_texts(self, texts: Sequence[str], fallback=None):
        """Completion texts → a :class:`~physcene.text_pack.TextPack` (batch, row per text, errors).

        Canonical CTRC (what ``ctrc.completion_text`` writes, keys in any order) is read by the
        compiled scanner of kernels/ctrc_scan.py straight into the batch; every other text goes
        to ``fallback`` (default :func:`physcene.ctrc.parse`), whose Scenes are packed into the same
        batch and whose ParseErrors are the texts that do not parse. Rows follow the input order.
        """
        if self._text_packer is None:
            from physcene.text_pack import TextPacker

            self._text_packer = TextPacker(self)
        return self._text_packer.pack(texts, fallback)

    # Evaluation --------------------------------------------------------------------------------
    def _poses(self, batch: SceneBatch, poses: torch.Tensor | None) -> torch.Tensor:
        if poses is None:
            return batch.poses
        if poses.shape != batch.poses.shape:
            raise ValueError(f"poses must have shape {tuple(batch.poses.shape)}, got {tuple(poses.shape)}")
        return poses.detach().to(device=self.device, dtype=torch.float32).contiguous()

    def evaluate(self, batch: SceneBatch, poses: torch.Tensor | None = None, *, with_grad: bool = False,
                 tolerance: float = 0.0) -> dict[str, torch.Tensor]:
        """One pass of the kernels: the raw per-pair / per-scene tensors (see ``launch_penetration``)."""
        return launch_penetration(
            pair_start=batch.pair_start, count=batch.count, n_pairs=batch.n_pairs,
            poses=self._poses(batch, poses), sizes=batch.sizes, obj_asset=batch.asset_index,
            assets=self.packed_assets(), margin=self.config.margin_cm, tolerance=tolerance,
            with_grad=with_grad, narrowphase=self.config.narrowphase, graph=self.config.graph,
            block_dim=self.config.narrowphase_block_dim,
            lanes=self.config.lanes_cuda if self.device.type == "cuda" else self.config.lanes_cpu)

    def support_gap(self, batch: SceneBatch, poses: torch.Tensor | None = None) -> torch.Tensor:
        """(S, N) cm: each object's bottom above the highest support under it (0 when contained)."""
        return launch_support(count=batch.count, poses=self._poses(batch, poses), sizes=batch.sizes,
                              overlap_eps=self.config.footprint_overlap_cm)

    def score(self, scenes_or_batch, poses: torch.Tensor | None = None, *, tolerance: float = 0.0) -> Score:
        """Per-pair depths, per-scene energy, floating objects and table penetration."""
        batch = scenes_or_batch if isinstance(scenes_or_batch, SceneBatch) else self.pack(scenes_or_batch)
        out = self.evaluate(batch, poses, tolerance=tolerance)
        gap = self.support_gap(batch, poses)
        floating_mask = ((gap > self.config.floating_tolerance_cm) & batch.mask).cpu().numpy()
        return Score(
            energy=out["energy"], max_depth=out["max_depth"], pairs=batch.deep_pairs(out["pair_depth"]),
            floating=[np.nonzero(row)[0].tolist() for row in floating_mask],
            table_penetration=out["table_depth"].max(dim=1).values, depth_sum=out["depth_sum"],
            table_depth=out["table_depth"], ids=batch.ids)

    def energy_and_grad(self, batch: SceneBatch, poses: torch.Tensor | None = None):
        """(energy (S,) cm, ∂energy/∂poses (S, N, 4)) in one pass, no autograd graph."""
        out = self.evaluate(batch, poses, with_grad=True)
        return out["energy"], out["grad"]

    def penetration_energy(self, batch: SceneBatch, poses: torch.Tensor | None = None) -> torch.Tensor:
        """(S,) pair penetration energy, differentiable in ``poses`` (S, N, 4) via autograd."""
        poses = batch.poses if poses is None else poses
        return PenetrationEnergy.apply(poses, self, batch)


class PenetrationEnergy(torch.autograd.Function):
    """E(poses) (S,) with the hand-written pose gradient of kernels/penetration.py.

    dE/dposes does not depend on the incoming gradient (E is per scene), so the forward runs the
    gradient kernels in the same pass when ``poses`` requires grad and saves the (S, N, 4)
    result; backward only scales it. Repeated backward returns the same tensor.
    """

    @staticmethod
    def forward(ctx, poses: torch.Tensor, engine: PhysicsEngine, batch: SceneBatch):
        need = ctx.needs_input_grad[0]
        out = engine.evaluate(batch, poses, with_grad=need)
        if need:
            ctx.save_for_backward(out["grad"])
        return out["energy"].to(device=poses.device, dtype=poses.dtype)

    @staticmethod
    def backward(ctx, grad_energy: torch.Tensor):
        (grad,) = ctx.saved_tensors
        g = grad.to(device=grad_energy.device, dtype=grad_energy.dtype) * grad_energy[:, None, None]
        return g, None, None
