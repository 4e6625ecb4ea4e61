"""Convex decomposition of an asset mesh for collision geometry (CoACD, cached on disk).

A scaling is linear, so the scaled parts of a convex decomposition are a convex decomposition of
the scaled mesh: one cache entry per asset serves every size. Entries are keyed by a hash of the
mesh and the CoACD settings.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import trimesh

from physcene.files import open_atomic

__all__ = ["convex_parts"]


def _cache_dir(setting) -> Path:
    if setting:
        return Path(setting)
    base = os.environ.get("PHYSCENE_CACHE") or os.path.join(Path.home(), ".cache", "physcene")
    return Path(base) / "coacd"


def _coacd_kwargs(settings: dict) -> dict:
    keys = ("threshold", "max_convex_hull", "preprocess_mode", "preprocess_resolution", "resolution",
            "mcts_nodes", "mcts_iterations", "mcts_max_depth", "merge", "max_ch_vertex", "seed")
    return {k: settings[k] for k in keys if k in settings}


def convex_parts(mesh: trimesh.Trimesh, settings: dict) -> list[trimesh.Trimesh]:
    """Convex parts covering ``mesh`` (its own frame), cached on disk by content hash.

    A mesh within ``convex_tolerance`` of its convex hull (by volume) is its own single part.
    """
    hull = mesh.convex_hull
    if mesh.is_volume and hull.volume - mesh.volume <= settings.get("convex_tolerance", 0.05) * hull.volume:
        return [hull]
    import coacd

    kwargs = _coacd_kwargs(settings)  # the cache key holds the setting as configured
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    settings_key = {"coacd": getattr(coacd, "__version__", "?"), **kwargs}
    digest.update(json.dumps(settings_key, sort_keys=True).encode())
    path = _cache_dir(settings.get("cache_dir")) / f"{digest.hexdigest()[:32]}.npz"
    if path.is_file():
        try:
            with np.load(path) as data:
                return _unpack_parts(data["vertices"], data["faces"], data["offsets"])
        except (OSError, ValueError, KeyError):
            pass  # a corrupt or foreign entry: decompose again and overwrite it
    if kwargs.get("preprocess_mode", "auto") == "auto":
        # CoACD's own "auto" check aborts the process on some closed meshes (a procedural apple);
        # trimesh decides instead: remesh to a manifold only when the mesh is not a closed volume.
        kwargs["preprocess_mode"] = "off" if mesh.is_volume else "on"
    raw = _run_coacd_isolated(np.asarray(mesh.vertices), np.asarray(mesh.faces), kwargs)
    if raw is None and kwargs["preprocess_mode"] == "off":
        raw = _run_coacd_isolated(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                  {**kwargs, "preprocess_mode": "on"})
    parts = [trimesh.Trimesh(v, f, process=True).convex_hull for v, f in raw or () if len(v) >= 4]
    if not parts:
        warnings.warn(f"CoACD failed on a mesh of {len(mesh.faces)} faces; its convex hull stands in "
                      "(cavities of this asset are closed in the export)", RuntimeWarning, stacklevel=2)
        return [hull]  # not cached: every run says so, and a fixed CoACD gets its chance
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces for p in parts])
    offsets = np.cumsum([[0, 0]] + [[len(p.vertices), len(p.faces)] for p in parts], axis=0)
    with open_atomic(path, "wb") as fh:  # readers never see half a file
        np.savez(fh, vertices=vertices, faces=faces, offsets=offsets)
    return parts


# The child: a fresh interpreter that reads the mesh from an .npz, runs CoACD and writes the parts.
_COACD_CHILD = """
import json, sys
import numpy as np
import coacd
coacd.set_log_level("error")
data = np.load(sys.argv[1])
parts = coacd.run_coacd(coacd.Mesh(data["vertices"], data["faces"]), **json.loads(sys.argv[3]))
out = {}
for k, (v, f) in enumerate(parts):
    out[f"v{k}"], out[f"f{k}"] = np.asarray(v), np.asarray(f)
np.savez(sys.argv[2], **out)
"""


def _run_coacd_isolated(vertices: np.ndarray, faces: np.ndarray, kwargs: dict):
    """CoACD's parts [(vertices, faces)], run in a child process; None when the child failed.

    CoACD aborts (C++ ``std::logic_error``, SIGABRT) on some inputs, which would kill the whole
    export; in a child process that is a value. The child is a fresh ``python -c`` interpreter,
    not a multiprocessing worker: a forked copy of a parent that has run torch holds a live OpenMP
    pool and CoACD's OpenMP deadlocks in it (seen in a test run), and a spawned worker re-imports
    the parent's ``__main__``, which fails for stdin scripts and notebooks. Parts are cached per
    asset, so the start-up is paid once.
    """
    with tempfile.TemporaryDirectory(prefix="physcene-coacd-") as tmp:
        src, dst = Path(tmp) / "mesh.npz", Path(tmp) / "parts.npz"
        np.savez(src, vertices=np.asarray(vertices, dtype=np.float64),
                 faces=np.asarray(faces, dtype=np.int64))
        done = subprocess.run([sys.executable, "-c", _COACD_CHILD, str(src), str(dst), json.dumps(kwargs)],
                              capture_output=True, text=True)
        if done.returncode != 0 or not dst.exists():
            return None
        with np.load(dst) as parts:
            n = len(parts.files) // 2
            return [(parts[f"v{k}"], parts[f"f{k}"]) for k in range(n)]


def _unpack_parts(vertices: np.ndarray, faces: np.ndarray, offsets: np.ndarray) -> list[trimesh.Trimesh]:
    parts = []
    for (v0, f0), (v1, f1) in zip(offsets[:-1], offsets[1:]):
        parts.append(trimesh.Trimesh(vertices[v0:v1], faces[f0:f1], process=False))
    return parts

