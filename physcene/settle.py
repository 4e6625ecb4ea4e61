"""The MuJoCo settle test: is a layout physically at rest?

The scene is exported to MJCF (:func:`physcene.export.mjcf_document`: one free body per object,
convex-decomposed collision geometry, the table a static box) and simulated for ``duration_s``
(2 s) under gravity from rest. An object is **stable** when its box centre moved at most
``max_moved_cm`` (1 cm) and its orientation turned at most ``max_turned_rad`` (0.1 rad) between
the first and the last step (SceneEval's convention); a scene is stable when all its objects are.
Interpenetrating objects are pushed apart by the contact solver and hovering ones fall, so both
fail. A simulation that diverges (MuJoCo's bad-acceleration warning) fails every object.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from physcene.config import load_config
from physcene.export import ExportConfig, ExportError, build_models, mjcf_document
from physcene.scene import Scene

__all__ = ["ObjectSettle", "SettleConfig", "SettleResult", "object_stability_rate", "settle",
           "settle_many", "stability_rate"]


@dataclass(frozen=True, kw_only=True)
class SettleConfig:
    """The settle test's thresholds (the ``settle`` section of ``configs/export.yaml``)."""

    duration_s: float = 2.0
    """Simulated time, s."""
    max_moved_cm: float = 1.0
    """Largest displacement of a stable object's box centre, cm."""
    max_turned_rad: float = 0.1
    """Largest rotation angle of a stable object, rad."""

    @classmethod
    def load(cls, overrides: Sequence[str] = (), name: str = "export") -> SettleConfig:
        cfg = load_config(name, overrides).settle
        return cls(duration_s=float(cfg.duration_s), max_moved_cm=float(cfg.max_moved_cm),
                   max_turned_rad=float(cfg.max_turned_rad))


@dataclass(frozen=True)
class ObjectSettle:
    """One object's motion over the settle run (NaN when the simulation diverged)."""

    instance_id: str
    moved_cm: float
    turned_rad: float
    stable: bool

    def to_dict(self) -> dict:
        def finite(v):
            return round(v, 6) if math.isfinite(v) else None

        return {"id": self.instance_id, "moved_cm": finite(self.moved_cm),
                "turned_rad": finite(self.turned_rad), "stable": self.stable}


@dataclass(frozen=True)
class SettleResult:
    """Per-object results of one scene; ``stable`` iff every object is."""

    objects: tuple[ObjectSettle, ...]
    diverged: bool = False
    path: str | None = None

    @property
    def stable(self) -> bool:
        return not self.diverged and all(o.stable for o in self.objects)

    @property
    def max_moved_cm(self) -> float:
        return max((o.moved_cm for o in self.objects), default=0.0)

    def to_dict(self) -> dict:
        """The ``physcene settle --json`` record: ``{"path", "stable", "objects": [...]}``."""
        out = {"path": self.path, "stable": self.stable, "objects": [o.to_dict() for o in self.objects]}
        if self.diverged:
            out["diverged"] = True
        return out


def _rotation_angle(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation taking unit quaternions q0 to q1, both (n, 4) w, x, y, z."""
    dot = np.abs(np.sum(q0 * q1, axis=-1)) / (np.linalg.norm(q0, axis=-1) * np.linalg.norm(q1, axis=-1))
    return 2.0 * np.arccos(np.clip(dot, -1.0, 1.0))


def settle(scene: Scene, *, library=None, config: SettleConfig | None = None,
           export_config: ExportConfig | None = None, path: str | None = None) -> SettleResult:
    """Simulate ``scene`` for ``config.duration_s`` in MuJoCo and measure every object's motion."""
    import mujoco

    config = config or SettleConfig.load()
    export_config = export_config or ExportConfig.load()
    if len(scene) == 0:
        return SettleResult(objects=(), path=path)
    models = build_models(scene, library=library, config=export_config)
    xml, files = mjcf_document(scene, config=export_config, models=models)
    try:
        mj_model = mujoco.MjModel.from_xml_string(xml, files)
    except ValueError as exc:  # MuJoCo's compiler error, e.g. a degenerate mesh part
        raise ExportError(f"{path or 'scene'}: MuJoCo rejected the exported model: {exc}") from exc
    data = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, data)
    addr = np.array([mj_model.jnt_qposadr[mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, m.name)]
                     for m in models])
    index = addr[:, None] + np.arange(7)[None, :]  # (n_obj, 7): x, y, z, qw, qx, qy, qz
    start = data.qpos[index].copy()
    n_steps = max(1, int(round(config.duration_s / mj_model.opt.timestep)))
    mujoco.mj_step(mj_model, data, nstep=n_steps)
    end = data.qpos[index].copy()
    # MuJoCo resets the state when accelerations blow up: the end pose then equals the start.
    diverged = bool(data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number) or not np.all(np.isfinite(end))
    if diverged:
        moved = np.full(len(models), np.nan)
        turned = np.full(len(models), np.nan)
    else:
        moved = 100.0 * np.linalg.norm(end[:, :3] - start[:, :3], axis=-1)  # m -> cm
        turned = _rotation_angle(start[:, 3:], end[:, 3:])
    objects = tuple(
        ObjectSettle(m.instance_id, float(d), float(a),
                     bool(not diverged and d <= config.max_moved_cm and a <= config.max_turned_rad))
        for m, d, a in zip(models, moved, turned))
    return SettleResult(objects=objects, diverged=diverged, path=path)


def _settle_job(job: tuple) -> SettleResult:
    scene, path, config, export_config = job
    return settle(scene, config=config, export_config=export_config, path=path)


def settle_many(scenes: Iterable[Scene], *, library=None, config: SettleConfig | None = None,
                export_config: ExportConfig | None = None, paths: Sequence[str | None] | None = None,
                workers: int = 1, progress: bool = False) -> list[SettleResult]:
    """:func:`settle` for each scene (one MuJoCo model each; scenes do not interact), in order.

    ``workers`` > 1 runs scenes in that many spawned processes (MuJoCo and the mesh work are CPU
    bound); they share the on-disk decomposition cache and use the default asset library, so a
    custom ``library`` needs ``workers=1``.
    """
    from tqdm import tqdm

    config = config or SettleConfig.load()
    export_config = export_config or ExportConfig.load()
    scenes = list(scenes)
    paths = list(paths) if paths is not None else [None] * len(scenes)
    if len(paths) != len(scenes):
        raise ValueError(f"settle_many: {len(paths)} paths for {len(scenes)} scenes")
    bar = dict(total=len(scenes), desc="settle", unit="scene", disable=not progress or len(scenes) < 2)
    if workers <= 1 or len(scenes) < 2:
        return [settle(s, library=library, config=config, export_config=export_config, path=p)
                for s, p in tqdm(zip(scenes, paths), **bar)]
    if library is not None:
        raise ValueError("settle_many: workers > 1 uses the default asset library; pass library=None")
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    jobs = [(s, p, config, export_config) for s, p in zip(scenes, paths)]
    # Spawned, not forked: the parent may hold torch/OpenMP threads that a fork would copy mid-state.
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(tqdm(pool.map(_settle_job, jobs, chunksize=4), **bar))


def stability_rate(results: Iterable[SettleResult | dict]) -> float:
    """Fraction of scenes whose every object is stable (0..1); NaN for no scenes.

    Accepts :class:`SettleResult` or their ``to_dict()`` records (``physcene settle --json``).
    """
    flags = [r["stable"] if isinstance(r, dict) else r.stable for r in results]
    return float(np.mean(flags)) if flags else float("nan")


def object_stability_rate(results: Iterable[SettleResult | dict]) -> float:
    """Fraction of objects, over all scenes, that are stable (0..1); NaN for no objects."""
    flags = []
    for r in results:
        objects = r["objects"] if isinstance(r, dict) else [o.to_dict() for o in r.objects]
        flags.extend(o["stable"] for o in objects)
    return float(np.mean(flags)) if flags else float("nan")
