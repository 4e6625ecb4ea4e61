"""The differentiable SDF physics engine (PADA, paper eq. 3): penetration, support, pose gradients.

``PhysicsEngine(library, device)`` packs scenes into a padded batch of torch tensors on the
device and scores them with the Warp kernels of :mod:`physcene.kernels.penetration`:

>>> engine = PhysicsEngine(device="cpu")
>>> score = engine.score([scene])           # per-pair depths, energies, floating objects
>>> batch = engine.pack([scene])
>>> energy = engine.penetration_energy(batch, batch.poses.requires_grad_())   # (S,) cm
>>> energy.sum().backward()                 # hand-written pose gradients

Units: cm and radians; energies are sums over surface and interior samples of penetration depths
(cm).
The maths and its choices are in docs/physics.md; the float64 oracle is
:mod:`physcene.physics.reference`; the batch and the packed assets are
:mod:`physcene.physics.batch`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import chain

import numpy as np
import torch

from physcene.config import ConfigError, load_dataclass
from physcene.kernels.penetration import launch_penetration, launch_support
from physcene.physics.batch import SceneBatch, Score, pack_assets
from physcene.scene import Scene

__all__ = ["PenetrationEnergy", "PhysicsConfig", "PhysicsEngine"]


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
    narrowphase_block_dim: int = 128
    """CUDA threads per block of the narrowphase launch (with fewer, a block whose items are done
    frees its SM slot sooner; a multiple of the lanes keeps an item in one block)."""
    interior_per_axis: int = 7
    """Interior samples per asset: one per cell of this many lattice cells per axis where the
    asset's own SDF is negative (:func:`physcene.assets.interior.interior_points`), read like its
    surface samples, so deep and coincident overlaps never read as clean (docs/physics.md, "Sound
    penetration"). 0: surface samples only (the paper's L_sdf, which reads coincident objects as 0)."""
    depth_cap_ratio: float = 0.8
    """A pair's depth reads at most this × half the thinner object's smallest size: the level every
    deeper overlap reaches with the interior samples, so the reading never falls as an overlap grows
    (shallower overlaps read exactly). 0: no cap."""
    graph: bool = True
    """Capture the kernel launches once per batch layout (CUDA graph; Warp CPU graph on the CPU)
    and replay them when the same batch is scored again (TTO steps, benchmarks): host launch
    cost off the critical path, at one capture per new layout. Same results."""

    def __post_init__(self):
        if self.interior_per_axis < 0:
            raise ConfigError(f"configs/physics.yaml: interior_per_axis={self.interior_per_axis}: "
                              "expected >= 0")
        if not 0.0 <= self.depth_cap_ratio <= 1.0:
            raise ConfigError(f"configs/physics.yaml: depth_cap_ratio={self.depth_cap_ratio}: expected 0..1")
        if not 1 <= self.narrowphase_block_dim <= 1024:
            raise ConfigError(f"configs/physics.yaml: narrowphase_block_dim={self.narrowphase_block_dim}: "
                              "expected 1..1024")

    @classmethod
    def load(cls, overrides: Sequence[str] = ()) -> PhysicsConfig:
        return load_dataclass(cls, "physics", overrides)


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

    # Assets ------------------------------------------------------------------------------------
    def resolve(self, category: str, asset_id: str | None) -> tuple[int, str, str | None]:
        """(slot in the engine's asset table, asset id, library fallback or None) of an object's asset;
        a new asset is added to the table (uploaded with the next :meth:`packed_assets`)."""
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
            self._packed = (len(self._assets), pack_assets(self._assets, self.device, self._derived,
                                                          interior_per_axis=self.config.interior_per_axis))
        elif self._packed[0] != len(self._assets):  # append the new assets to what is uploaded
            n, packed = self._packed
            self._packed = (len(self._assets),
                            pack_assets(self._assets[n:], self.device, self._derived, before=packed,
                                        interior_per_axis=self.config.interior_per_axis))
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
        resolve, cache = self.resolve, self._resolved
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
            with_grad=with_grad, depth_cap_ratio=self.config.depth_cap_ratio, graph=self.config.graph,
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
