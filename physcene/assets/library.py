"""The asset library: every shape an object can take, and retrieval by asset id or category.

Retrieval (:meth:`AssetLibrary.resolve`) tries, in order, and reports which step answered:

1. the ``asset_id`` (``primitive:box``, ``procedural:mug`` or a mesh folder's uid) -- exact;
2. the category (``mug``): folder meshes first (real shapes), then procedural, then primitives --
   exact;
3. the nearest category name: a known alias (``desk_lamp`` -> ``lamp``), the singular
   (``books`` -> ``book``), the head noun (``coffee_mug`` -> ``mug``), shared words, then
   ``difflib`` similarity >= 0.75 -- reported in ``Retrieval.fallback``;
4. the box primitive -- reported.

A fallback is logged once per library and requested name (logger ``physcene.assets``), never
silent. Assets bake lazily on first retrieval and are memoised; bakes hit the on-disk cache.
"""

from __future__ import annotations

import difflib
import functools
import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from physcene.assets.asset import Asset
from physcene.assets.bake import bake_mesh_asset, normalise_mesh
from physcene.assets.cache import BakeCache
from physcene.assets.categories import CATEGORY_ALIASES, CATEGORY_PRIORS
from physcene.assets.mesh_folder import load_mesh_file, normalise_category, scan_mesh_folder
from physcene.assets.primitives import PRIMITIVES, primitive_asset
from physcene.assets.procedural import procedural_mesh

__all__ = ["AssetEntry", "AssetLibrary", "Retrieval", "default_library", "procedural_points_scale"]

_log = logging.getLogger("physcene.assets")
_SOURCE_RANK = {"folder": 0, "procedural": 1, "primitive": 2}


@functools.cache
def _procedural_shapes() -> dict[str, tuple[bytes, tuple[float, float, float]]]:
    """Each procedural category's normalised mesh (float32 vertices + int32 faces, the bytes the
    cache key hashes) and half-extents (cm), in :data:`CATEGORY_PRIORS` order."""
    out = {}
    for category in CATEGORY_PRIORS:
        normalised, extents = normalise_mesh(procedural_mesh(category), name=f"procedural:{category}")
        shape = (np.ascontiguousarray(normalised.vertices, dtype=np.float32).tobytes()
                 + np.ascontiguousarray(normalised.faces, dtype=np.int32).tobytes())
        out[category] = (shape, tuple(float(e) / 2 for e in extents))
    return out


def procedural_points_scale(category: str) -> tuple[float, float, float]:
    """The half-extents (cm) that weigh the surface points of procedural ``category``: those of the
    first category in :data:`CATEGORY_PRIORS` order with the same normalised mesh. The slabs (book,
    phone, towel, toaster, ...) are one box in the normalised frame and share one bake, SDF and
    points; naming its weighting here makes those points the same in every process, whichever slab
    is baked first, and so the seating of a synthesised scene and the engine's measure with them."""
    shapes = _procedural_shapes()
    shape = shapes[category][0]
    return next(scale for other, scale in shapes.values() if other == shape)


@dataclass(frozen=True)
class AssetEntry:
    """One asset the library can build: its identity and how to get its mesh."""

    asset_id: str
    category: str
    source: str
    """``primitive``, ``procedural`` or ``folder:<path>``."""
    description: str = ""
    load_mesh: Callable[[], trimesh.Trimesh] | None = field(default=None, repr=False, compare=False)
    """Returns the mesh (z up, units of ``unit_cm``); None for exact primitives."""
    unit_cm: float = 1.0

    @property
    def kind(self) -> str:
        return self.source.split(":", 1)[0]


@dataclass(frozen=True)
class Retrieval:
    """The answer of :meth:`AssetLibrary.resolve`."""

    asset: Asset
    fallback: str | None
    """None when the asset id or the category matched exactly; else how it fell back."""
    requested: str
    """The category asked for."""


class AssetLibrary:
    """A set of assets with lazy baking and retrieval by id or category.

    Args:
        resolution: SDF grid nodes per axis.
        n_points: surface points per asset.
        seed: surface point seed.
        device: Warp device for bakes (``"cpu"``, ``"cuda:0"``).
        cache: where bakes are cached; None bakes without caching.
    """

    def __init__(
        self,
        *,
        resolution: int = 64,
        n_points: int = 1024,
        seed: int = 0,
        device: str = "cpu",
        cache: BakeCache | None = None,
        edge_angle_deg: float = 30.0,
    ):
        self.resolution, self.n_points, self.seed, self.device = resolution, n_points, seed, device
        self.cache, self.edge_angle_deg = cache, edge_angle_deg
        self._entries: dict[str, AssetEntry] = {}
        self._by_category: dict[str, list[str]] = {}
        self._baked: dict[str, Asset] = {}
        self._warned: set[str] = set()
        self._lock = threading.RLock()

    # ------------------------------------------------------------ contents

    def add(self, entry: AssetEntry) -> None:
        """Register ``entry``; an id already present is an error."""
        if entry.asset_id in self._entries:
            raise ValueError(f"asset id {entry.asset_id!r} is already in the library")
        self._entries[entry.asset_id] = entry
        ids = self._by_category.setdefault(entry.category, [])
        ids.append(entry.asset_id)
        ids.sort(key=lambda i: (_SOURCE_RANK[self._entries[i].kind], i))

    def add_primitives(self) -> None:
        for kind in PRIMITIVES:
            self.add(AssetEntry(f"primitive:{kind}", kind, "primitive", f"exact {kind} primitive"))

    def add_procedural(self, categories: Iterable[str] | None = None) -> None:
        for category in categories if categories is not None else CATEGORY_PRIORS:
            self.add(
                AssetEntry(
                    f"procedural:{category}",
                    category,
                    "procedural",
                    f"procedural {category}",
                    functools.partial(procedural_mesh, category),
                )
            )

    def add_folder(
        self, folder: str | Path, *, up_axis: str | None = None, unit_cm: float | None = None
    ) -> int:
        """Register every mesh of ``folder`` (see :mod:`physcene.assets.mesh_folder`); returns how many."""
        files = scan_mesh_folder(folder, up_axis=up_axis, unit_cm=unit_cm)
        for f in files:
            self.add(
                AssetEntry(
                    f.asset_id,
                    f.category,
                    f"folder:{Path(folder)}",
                    f.description,
                    functools.partial(load_mesh_file, f.path, up_axis=f.up_axis),
                    f.unit_cm,
                )
            )
        return len(files)

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, asset_id: str) -> bool:
        return asset_id in self._entries

    def entries(self) -> list[AssetEntry]:
        return [self._entries[i] for c in sorted(self._by_category) for i in self._by_category[c]]

    def categories(self) -> list[str]:
        return sorted(self._by_category)

    def listing(self) -> list[dict]:
        """``[{category, asset_id, source}]`` sorted by category (what ``physcene assets list`` prints)."""
        return [{"category": e.category, "asset_id": e.asset_id, "source": e.source} for e in self.entries()]

    # ------------------------------------------------------------ baking

    def get(self, asset_id: str) -> Asset:
        """The baked asset ``asset_id`` (baked on first use, then memoised)."""
        with self._lock:
            if asset_id in self._baked:
                return self._baked[asset_id]
            if asset_id not in self._entries:
                raise KeyError(f"unknown asset id {asset_id!r}")
            entry = self._entries[asset_id]
            if entry.kind == "primitive":
                asset = primitive_asset(entry.category, self.resolution, self.n_points)
            else:
                asset = bake_mesh_asset(
                    entry.load_mesh(),
                    asset_id=entry.asset_id,
                    category=entry.category,
                    source=entry.source,
                    description=entry.description,
                    unit_cm=entry.unit_cm,
                    resolution=self.resolution,
                    n_points=self.n_points,
                    seed=self.seed,
                    device=self.device,
                    cache=self.cache,
                    edge_angle_deg=self.edge_angle_deg,
                    points_scale=(procedural_points_scale(entry.category) if entry.kind == "procedural"
                                  else None),
                )
            self._baked[asset_id] = asset
            return asset

    def bake_all(self, progress: Callable[[AssetEntry], None] | None = None) -> list[Asset]:
        """Bake (or load from the cache) every asset."""
        out = []
        for entry in self.entries():
            if progress is not None:
                progress(entry)
            out.append(self.get(entry.asset_id))
        return out

    # ------------------------------------------------------------ retrieval

    def resolve(self, category: str, asset_id: str | None = None) -> Retrieval:
        """The asset for an object of ``category`` (and ``asset_id`` if it has one); see the module doc."""
        notes = []
        if asset_id is not None:
            if asset_id in self._entries:
                return Retrieval(self.get(asset_id), None, category)
            notes.append(f"asset id {asset_id!r} not in the library")
        if category in self._by_category:
            chosen = self._by_category[category][0]
            if not notes:
                return Retrieval(self.get(chosen), None, category)
            return self._fallback(category, asset_id, chosen, notes)
        nearest = self.nearest_category(category)
        if nearest is not None:
            notes.append(f"no category {category!r}; nearest is {nearest!r}")
            return self._fallback(category, asset_id, self._by_category[nearest][0], notes)
        notes.append(f"no category near {category!r}; using a box")
        if "primitive:box" not in self._entries:
            self.add(AssetEntry("primitive:box", "box", "primitive", "exact box primitive"))
        return self._fallback(category, asset_id, "primitive:box", notes)

    def _fallback(self, category: str, asset_id: str | None, chosen: str, notes: list[str]) -> Retrieval:
        message = "; ".join(notes) + f" -> {chosen}"
        warn_key = f"{category}|{asset_id}"
        if warn_key not in self._warned:
            self._warned.add(warn_key)
            _log.warning("asset retrieval fell back: %s", message)
        return Retrieval(self.get(chosen), message, category)

    def nearest_category(self, name: str) -> str | None:
        """The library category closest to ``name``, or None (see the module doc for the order)."""
        known = self._by_category
        key = normalise_category(name)
        for candidate in (CATEGORY_ALIASES.get(key), CATEGORY_ALIASES.get(name), key):
            if candidate in known:
                return candidate
        words = key.split("_")
        for size in range(len(words) - 1, 0, -1):  # longest trailing phrase: the head noun
            tail = "_".join(words[-size:])
            for candidate in (tail, CATEGORY_ALIASES.get(tail)):
                if candidate in known:
                    return candidate
        scored = [(len(set(words) & set(c.split("_"))), c) for c in known]
        best = max(scored, key=lambda s: (s[0], -len(s[1])), default=(0, None))
        if best[0] > 0:
            ties = sorted(c for s, c in scored if s == best[0])
            return difflib.get_close_matches(key, ties, n=1, cutoff=0.0)[0]
        close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.75)
        return close[0] if close else None


@functools.lru_cache(maxsize=1)
def default_library() -> AssetLibrary:
    """Primitives + every procedural category (+ the config's mesh folders), cached per process.

    Settings come from ``configs/assets.yaml``; bakes go to the on-disk cache, so a second process
    loads each asset in milliseconds.
    """
    from physcene.config import load_config

    cfg = load_config("assets")
    library = AssetLibrary(
        resolution=int(cfg.resolution),
        n_points=int(cfg.n_points),
        seed=int(cfg.seed),
        device=str(cfg.device),
        cache=BakeCache(cfg.cache_dir or None),
        edge_angle_deg=float(cfg.edge_angle_deg),
    )
    library.add_primitives()
    library.add_procedural()
    for folder in cfg.folders or []:
        library.add_folder(folder)
    return library
