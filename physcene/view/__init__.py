"""``physcene view``: an interactive browser viewer of scenes (viser, the ``[view]`` extra).

:mod:`~physcene.view.sources` reads what a path holds (layout, JSONL, eval results, before/after),
:mod:`~physcene.view.findings` marks penetrating pairs, floating objects and scene-graph edges,
:mod:`~physcene.view.viewer` draws them with viser. Importing :class:`SceneViewer` needs viser.
"""

from __future__ import annotations

from physcene.view.findings import RELATIONS, SceneFindings, find
from physcene.view.sources import ViewInputError, ViewItem, load_items

__all__ = ["RELATIONS", "SceneFindings", "SceneViewer", "ViewInputError", "ViewItem", "find", "load_items"]


def __getattr__(name: str):
    # The viewer needs viser (an extra); sources and findings do not.
    if name == "SceneViewer":
        from physcene.view.viewer import SceneViewer

        return SceneViewer
    raise AttributeError(f"module 'physcene.view' has no attribute {name!r}")
