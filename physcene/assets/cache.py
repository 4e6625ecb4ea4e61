"""On-disk cache of baked assets: one ``<key>.npz`` per bake, keyed by a content hash.

The key is the SHA-256 of the normalised mesh bytes (float32 vertices, int32 faces), the grid
resolution, the point count and seed, the sign method, the surface points' weighting and sharp-edge
angle, and :data:`BAKE_VERSION` (bumped whenever the baking code changes its output). Entries are
written to a temporary file in the same folder and ``os.replace``d into place
(:func:`physcene.files.open_atomic`), so a reader never sees half an entry and an interrupted bake
leaves nothing behind; an entry that does not load (truncated,
bad zip, wrong arrays, non-finite values, another key) is deleted and baked again.

Where: ``cache_dir`` when given (config ``assets.cache_dir``), else ``$PHYSCENE_CACHE/assets``,
else ``~/.cache/physcene/assets``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import zipfile
from pathlib import Path

import numpy as np

from physcene.files import open_atomic

__all__ = ["BAKE_VERSION", "BakeCache", "default_cache_dir"]

BAKE_VERSION = "sdf-bake-1"
_log = logging.getLogger(__name__)


def default_cache_dir() -> Path:
    """``$PHYSCENE_CACHE/assets`` if the variable is set, else ``~/.cache/physcene/assets``."""
    root = os.environ.get("PHYSCENE_CACHE")
    return (Path(root).expanduser() if root else Path.home() / ".cache" / "physcene") / "assets"


class BakeCache:
    """A folder of baked SDF grids and surface points."""

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root).expanduser() if root else default_cache_dir()

    @staticmethod
    def key(
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        resolution: int,
        n_points: int,
        seed: int,
        sign_method: str,
        points_scale=None,
        edge_angle_deg: float = 30.0,
    ) -> str:
        """The content hash of one bake. The surface points' weighting (``points_scale``, the
        half-extents that weigh areas and edge lengths; None: the normalised frame) and sharp-edge
        angle are part of it: two meshes with one normalised shape but other proportions sample
        other points, and an entry must not hand one the other's."""
        h = hashlib.sha256()
        h.update(BAKE_VERSION.encode())
        h.update(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
        h.update(np.ascontiguousarray(faces, dtype=np.int32).tobytes())
        h.update(f"|{resolution}|{n_points}|{seed}|{sign_method}".encode())
        scale = "none" if points_scale is None else np.asarray(points_scale, dtype=np.float64).tobytes().hex()
        h.update(f"|{scale}|{float(edge_angle_deg)!r}".encode())
        return h.hexdigest()

    def path(self, key: str) -> Path:
        return self.root / f"{key}.npz"

    def load(self, key: str, resolution: int, n_points: int) -> dict[str, np.ndarray] | None:
        """The arrays of entry ``key`` (``sdf`` (R,R,R), ``points`` (P,3)), or None if absent or corrupt."""
        path = self.path(key)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                entry = {name: data[name] for name in ("key", "sdf", "points")}
            ok = (
                str(entry["key"]) == key
                and entry["sdf"].shape == (resolution,) * 3
                and entry["points"].shape == (n_points, 3)
                and np.all(np.isfinite(entry["sdf"]))
                and np.all(np.isfinite(entry["points"]))
            )
            if not ok:
                raise ValueError("arrays do not match the key")
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            _log.warning("corrupt asset cache entry %s (%s); baking it again", path, exc)
            path.unlink(missing_ok=True)
            return None
        return {"sdf": entry["sdf"], "points": entry["points"]}

    def store(self, key: str, sdf: np.ndarray, points: np.ndarray) -> Path:
        """Write an entry atomically and durably (temp file in the same folder, fsync, ``os.replace``)."""
        with open_atomic(self.path(key), "wb", fsync=True) as f:
            _write_npz(f, key=np.array(key), sdf=sdf, points=points)
        return self.path(key)


def _write_npz(f, **arrays) -> None:
    np.savez(f, **arrays)
