"""The public Python API: thin functions over the stages, results that name objects by id.

    import physcene
    scene = physcene.load_layout("examples/office_table.layout.json")
    report = physcene.check(scene)                 # {"pairs": [{"a": id, "b": id, "depth_cm"}], ...}
    fixed, repair_report = physcene.repair(scene)  # TTO; the report names objects by id
    physcene.render(fixed, "fixed.png")
    physcene.export(fixed, "out/", "mjcf")

Torch, Warp and trimesh are imported by the function that needs them: ``import physcene`` and
``physcene.load_layout`` stay fast (the physics engine, TTO, the renderer and the exporters pull
them in on first use).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path

from physcene.layout import load_layout as _layout_from_dict
from physcene.layout import read_layout, write_layout
from physcene.scene import Scene

__all__ = ["check", "export", "load_layout", "render", "repair", "reward", "save_layout"]


def load_layout(source, *, scene_type: str | None = None) -> Scene:
    """A :class:`Scene` from a MesaTask ``layout.json`` path, a layout dict, or CTRC / JSON text.

    Errors are :class:`~physcene.scene.SceneError` (a ``ValueError``) naming the file, object and field.
    """
    if isinstance(source, dict):
        return _layout_from_dict(source, scene_type=scene_type)
    if isinstance(source, str) and ("\n" in source or source.lstrip().startswith("{")):
        from physcene.ctrc import ParseError, parse

        scene = parse(source)
        if isinstance(scene, ParseError):
            raise ValueError(f"not a layout: {scene.reason}")
        return scene
    return read_layout(Path(source), scene_type=scene_type)


def save_layout(scene: Scene, path) -> Path:
    """Write ``scene`` as a MesaTask ``layout.json`` (centimetres, parent/relation kept); returns the path."""
    return write_layout(scene, path)


def _engine(device: str, engine=None):
    if engine is not None:
        return engine
    from physcene.physics import PhysicsEngine

    return PhysicsEngine(device=device)


def _ids_of(scene: Scene, value) -> str:
    return value if isinstance(value, str) else scene.ids()[int(value)]


def check(scenes: Scene | Sequence[Scene], *, device: str = "cpu", engine=None) -> dict | list[dict]:
    """Physics verdicts of one scene (a dict) or several (a list, one engine call).

    Each report: ``objects``, ``pairs`` ([{"a": id, "b": id, "depth_cm"}], every interpenetrating
    pair), ``max_depth_cm``, ``energy``, ``floating`` (ids), ``table_penetration_cm``,
    ``collision_free`` (no pair at all).
    """
    one = isinstance(scenes, Scene)
    batch = [scenes] if one else list(scenes)
    if not batch:
        return []
    score = _engine(device, engine).score(batch)
    energy, depth = score.energy.cpu().tolist(), score.max_depth.cpu().tolist()
    table = score.table_penetration.cpu().tolist()
    reports = []
    for m, scene in enumerate(batch):
        pairs = [{"a": _ids_of(scene, i), "b": _ids_of(scene, j), "depth_cm": float(d)}
                 for i, j, d in score.pairs[m]]
        reports.append({"objects": len(scene.objects), "pairs": pairs, "max_depth_cm": depth[m],
                        "energy": energy[m], "floating": [_ids_of(scene, i) for i in score.floating[m]],
                        "table_penetration_cm": table[m], "collision_free": not pairs})
    return reports[0] if one else reports


def _plain(report) -> dict:
    """A TTO report as a JSON-ready dict (a dict, or a dataclass report)."""
    if dataclasses.is_dataclass(report) and not isinstance(report, type):
        report = dataclasses.asdict(report)
    return json.loads(json.dumps(dict(report), default=float))


def repair(scenes: Scene | Sequence[Scene], *, device: str | None = None, overrides: Sequence[str] = (),
           engine=None):
    """Hierarchy-constrained test-time optimisation (TTO, ``configs/tto.yaml``; ``overrides`` such
    as ``["steps=200"]``). One scene: ``(repaired scene, report)``; several: a list of such pairs.
    The report holds the energy before/after, the largest displacement, the relations kept and what
    could not be satisfied, naming objects by id."""
    from physcene.tto import TTOConfig
    from physcene.tto import repair as tto_repair

    one = isinstance(scenes, Scene)
    batch = [scenes] if one else list(scenes)
    config = TTOConfig.load([*overrides, *([f"device={device}"] if device else [])])
    results = tto_repair(batch, config, engine if engine is not None else _engine(config.device))
    out = [(r.scene, _plain(r.report)) for r in results]
    return out[0] if one else out


def reward(completions: Sequence[str], prompts: Sequence[str] | None = None, *, device: str | None = None,
           overrides: Sequence[str] = ()) -> list[float]:
    """The paper's physics reward of CTRC completions (``configs/reward.yaml``), one per completion;
    −100 (``unparsable``) for a completion that does not parse."""
    from physcene.reward import PhysicsReward, RewardConfig

    config = RewardConfig.load(list(overrides))
    if device:
        config = dataclasses.replace(config, device=device)
    texts = list(completions)
    return list(PhysicsReward(config)(prompts=list(prompts) if prompts is not None else [None] * len(texts),
                                      completions=texts))


def render(scene: Scene, path=None, *, view: str = "perspective", size: tuple[int, int] = (640, 480)):
    """An (H, W, 3) uint8 image of ``scene`` (views: front, perspective, top ...); written as PNG to
    ``path`` when given."""
    from physcene.eval.render import png_bytes, render_image

    image = render_image(scene, view, size=size)
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(png_bytes(image))
    return image


def export(scene: Scene, out_dir, fmt: str = "mjcf") -> Path:
    """Simulator files of ``scene`` in metres: ``mjcf`` (MuJoCo scene.xml + meshes), ``urdf`` (one
    URDF per object + scene.json for SAPIEN/ManiSkill) or ``glb``; returns the main file."""
    from physcene.export import ExportConfig
    from physcene.export import export as export_scene

    return export_scene(scene, out_dir, fmt, config=ExportConfig.load())
