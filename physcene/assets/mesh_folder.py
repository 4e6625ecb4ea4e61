"""Read folders of GLB/glTF/OBJ/PLY/STL meshes, including MesaTask's ``Assets_library``.

MesaTask ships ``Assets_library/{uid}.glb`` and an ``Asset_annotation.json`` (in the folder or its
parent) that gives each uid a category and a description. The annotation may be a mapping
``{uid: {"category": ..., "description": ...}}`` or a list of records carrying ``uid`` (or ``id``);
the category is read from ``category`` / ``class`` / ``label`` / ``name`` and normalised to
lower_snake_case singular, the description from ``description`` / ``caption`` / ``text``. Without
an annotation the category is the file name without trailing numbers (``mug_02.obj`` -> ``mug``).

Frames: glTF is +Y up with metres (its specification), so GLB/glTF meshes are turned +90 deg about
x (Y up -> Z up; glTF's front +Z becomes -y, facing the viewer) and their extents are multiplied by
100 for cm. Other formats carry no convention: they are read as Z up in cm unless ``up_axis`` /
``unit_cm`` say otherwise.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from physcene.assets.categories import CATEGORY_ALIASES, CATEGORY_PRIORS

__all__ = [
    "MESH_SUFFIXES",
    "AssetFileError",
    "MeshFile",
    "load_mesh_file",
    "normalise_category",
    "scan_mesh_folder",
]

MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl")
ANNOTATION_NAME = "Asset_annotation.json"
_Y_UP_TO_Z_UP = trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0))


class AssetFileError(ValueError):
    """A mesh or annotation file could not be used; the message names the file."""


@dataclass(frozen=True)
class MeshFile:
    """One mesh file of a folder, not yet loaded."""

    path: Path
    asset_id: str
    category: str
    description: str
    up_axis: str
    unit_cm: float


# nouns with no singular in everyday use: kept as they are
_PLURAL_ONLY = {
    "headphones",
    "earphones",
    "glasses",
    "eyeglasses",
    "sunglasses",
    "scissors",
    "chopsticks",
    "keys",
    "notes",
    "tongs",
    "tweezers",
    "pliers",
    "earbuds",
    "clothes",
    "jeans",
    "shorts",
}


def normalise_category(name: str) -> str:
    """``"Coffee Mugs"`` -> ``"coffee_mug"``: lower_snake_case, last word singular.

    Known categories and plural-only nouns (``headphones``, ``glasses``, ``sticky_notes``) are kept.
    """
    words = re.findall(r"[a-z0-9]+", name.lower())
    if not words:
        return ""
    joined = "_".join(words)
    last = words[-1]
    if joined in CATEGORY_PRIORS or joined in CATEGORY_ALIASES or last in _PLURAL_ONLY:
        return joined
    if last.endswith("ies") and len(last) > 4:
        last = last[:-3] + "y"
    elif last.endswith(("ches", "shes", "sses", "xes")):
        last = last[:-2]
    elif last.endswith("s") and not last.endswith(("ss", "us", "is")) and len(last) > 3:
        last = last[:-1]
    return "_".join([*words[:-1], last])


def load_mesh_file(path: str | Path, *, up_axis: str = "z") -> trimesh.Trimesh:
    """One triangle mesh from ``path`` (scenes are flattened with their transforms), z up.

    Raises:
        AssetFileError: the file is missing, empty, corrupt or holds no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise AssetFileError(f"{path}: no such mesh file")
    if path.stat().st_size == 0:
        raise AssetFileError(f"{path}: empty file")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for bad bytes; all mean "not a mesh"
        raise AssetFileError(f"{path}: cannot read a mesh ({type(exc).__name__}: {exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise AssetFileError(f"{path}: file holds no triangles")
    if not np.all(np.isfinite(loaded.vertices)):
        raise AssetFileError(f"{path}: non-finite vertex coordinates")
    if up_axis == "y":
        loaded.apply_transform(_Y_UP_TO_Z_UP)
    elif up_axis != "z":
        raise AssetFileError(f"{path}: up_axis must be 'y' or 'z', got {up_axis!r}")
    return loaded


def _read_annotation(folder: Path) -> dict[str, dict]:
    for candidate in (folder / ANNOTATION_NAME, folder.parent / ANNOTATION_NAME):
        if candidate.is_file():
            try:
                data = json.loads(candidate.read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise AssetFileError(f"{candidate}: not a readable JSON annotation ({exc})") from exc
            if isinstance(data, list):
                data = {str(r.get("uid", r.get("id"))): r for r in data if isinstance(r, dict)}
            if not isinstance(data, dict):
                raise AssetFileError(f"{candidate}: expected a mapping uid -> record or a list of records")
            return {str(k): v if isinstance(v, dict) else {"category": str(v)} for k, v in data.items()}
    return {}


def _first(record: dict, keys: tuple[str, ...]) -> str:
    for k in keys:
        if isinstance(record.get(k), str) and record[k].strip():
            return record[k].strip()
    return ""


def scan_mesh_folder(
    folder: str | Path, *, up_axis: str | None = None, unit_cm: float | None = None
) -> list[MeshFile]:
    """The mesh files of ``folder`` (not recursive), with categories from the annotation if any.

    ``up_axis`` / ``unit_cm`` override the per-format defaults (glTF: "y" and 100; others: "z" and 1).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AssetFileError(f"{folder}: not a folder of meshes")
    annotation = _read_annotation(folder)
    files = []
    for path in sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES):
        gltf = path.suffix.lower() in (".glb", ".gltf")
        record = annotation.get(path.stem, {})
        category = (
            normalise_category(
                _first(record, ("category", "class", "label", "name"))
                or re.sub(r"[_\-\s]*\d+$", "", path.stem)
            )
            or "unknown"
        )
        files.append(
            MeshFile(
                path=path,
                asset_id=path.stem,
                category=category,
                description=_first(record, ("description", "caption", "text")),
                up_axis=up_axis or ("y" if gltf else "z"),
                unit_cm=unit_cm if unit_cm is not None else (100.0 if gltf else 1.0),
            )
        )
    return files
