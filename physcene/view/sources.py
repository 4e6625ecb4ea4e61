"""What ``physcene view`` shows: the scenes of a path, each with its variants (before/after, A/B).

A path is a layout (``layout.json``), a JSONL dataset (one scene per record: the scene picker), a
folder of layouts, or an eval results folder (``physcene eval`` with ``save_layouts=true`` writes
``layouts/<method>/<id>.json``: one scene per id, one variant per method, e.g. reference vs TTO).
``--before PATH`` pairs a repair output with its input: variants ``before`` and ``after``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from physcene.commands.settle import read_inputs
from physcene.layout import read_layout
from physcene.scene import Scene

__all__ = ["ViewInputError", "ViewItem", "load_items"]


class ViewInputError(ValueError):
    """A path given to ``physcene view`` holds no scene to show (the message names it)."""


@dataclass(frozen=True)
class ViewItem:
    """One entry of the scene picker."""

    label: str
    """What the picker shows: the file, ``FILE.jsonl:LINE`` or the scene id."""
    variants: dict[str, Scene]
    """Variant name -> scene, in switch order (one ``scene`` entry for a plain layout)."""


def _method_folders(root: Path) -> list[Path]:
    """Sub-folders of ``root`` that hold ``<id>.json`` layouts (an eval run's ``layouts/``)."""
    return sorted(d for d in root.iterdir() if d.is_dir() and any(d.glob("*.json")))


def _by_method(root: Path) -> list[ViewItem]:
    methods = {d.name: {p.stem: p for p in sorted(d.glob("*.json"))} for d in _method_folders(root)}
    ids = sorted({i for files in methods.values() for i in files})
    items = []
    for scene_id in ids:
        variants = {m: read_layout(files[scene_id]) for m, files in methods.items() if scene_id in files}
        items.append(ViewItem(scene_id, variants))
    return items


def _plain(path: str) -> list[ViewItem]:
    items = []
    for label, scene, error in read_inputs([path]):
        if error is not None:
            raise ViewInputError(error)
        items.append(ViewItem(label, {"scene": scene}))
    return items


def load_items(path, before=None) -> list[ViewItem]:
    """The picker entries of ``path`` (module docstring); ``before`` adds a before/after switch."""
    root = Path(path)
    if root.is_dir() and (root / "layouts").is_dir():
        items = _by_method(root / "layouts")
    elif root.is_dir() and (root / "results.json").is_file():
        raise ViewInputError(f"{root}: an eval results folder without layouts/; run physcene eval with "
                             "save_layouts=true to view its scenes")
    elif root.is_dir() and _method_folders(root) and not any(root.glob("*.json")):
        items = _by_method(root)
    else:
        items = _plain(str(path))
    if not items:
        raise ViewInputError(f"{path}: no scene to show")
    if before is not None:
        old = _plain(str(before))
        if len(old) != len(items):
            raise ViewInputError(f"--before {before} holds {len(old)} scenes, {path} holds {len(items)}")
        items = [ViewItem(new.label, {"before": o.variants["scene"], "after": new.variants["scene"]})
                 for o, new in zip(old, items)]
    return items


