"""The synthetic benchmark end to end: plan → clean layout → captions → noise → CTRC record.

:func:`synthesize` yields the records of a split in order; :func:`write_split` writes them as
JSONL (in parallel worker processes; every record has its own RNG seeded from (seed, split,
index), so the bytes do not depend on the number of workers) together with the stats table
(type × level counts, noise counts and, measured with the physics engine, the reference
SCR/ACR) as ``<split>_stats.json`` and ``<split>_stats.md``. The three files are renamed into
place together once all are complete (:func:`physcene.files.write_atomic_many`): an interrupted
run leaves the previous files or none, and running it again writes the same bytes.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import signal
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from physcene.config import ConfigError, load_config
from physcene.ctrc import DECIMALS, MAX_DECIMALS
from physcene.data.captions import describe
from physcene.data.mesatask_ctrc import ctrc_record, dumps_record
from physcene.data.noise import NoiseConfig, NoiseRecord, apply_noise
from physcene.data.scene_types import OOD_SCENE_TYPES, SCENE_TYPES, spec_for
from physcene.data.splits import PlanItem, plan_split, record_rng
from physcene.data.synth import ContainerFit, SynthConfig, synthesize_layout
from physcene.files import open_atomic, write_atomic_many
from physcene.layout import load_layout
from physcene.scene import Scene

__all__ = [
    "DataConfig",
    "build_record",
    "build_scenes",
    "split_files",
    "split_stats",
    "stats_markdown",
    "synthesize",
    "write_records",
    "write_split",
]


MEASURE_VALUES = ("auto", "true", "false", "yes", "no", "1", "0")
"""Accepted ``record.measure`` values (auto: test and ood are measured)."""


@dataclass(frozen=True, kw_only=True)
class DataConfig:
    """All knobs of the benchmark (``configs/data.yaml``)."""

    synth: SynthConfig = field(default_factory=SynthConfig)
    """The clean generator's knobs (``synth:`` section)."""
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    """The annotation-noise knobs (``noise:`` section)."""
    prompt_objects: bool = True
    """``record.prompt_objects``: the prompt lists the requested objects."""
    decimals: int = DECIMALS
    """``record.decimals``: digits after the point in completion text, 0 to ``MAX_DECIMALS``."""
    workers: int = 2
    """``record.workers``: processes that synthesise a split (more than 1 only above 32 scenes)."""
    measure: str = "auto"
    """``record.measure``: score the reference layouts with the engine (auto: test and ood)."""

    def __post_init__(self) -> None:
        if self.measure not in MEASURE_VALUES:
            raise ValueError(f"record.measure must be auto/true/false, got {self.measure!r}")
        if isinstance(self.decimals, bool) or not isinstance(self.decimals, int) \
                or not 0 <= self.decimals <= MAX_DECIMALS:
            raise ValueError(f"record.decimals must be an integer from 0 to {MAX_DECIMALS}, "
                             f"got {self.decimals!r}")

    @classmethod
    def load(cls, overrides=()) -> DataConfig:
        """``configs/data.yaml`` with ``key=value`` overrides; unknown keys are a ConfigError."""
        cfg = OmegaConf.to_container(load_config("data", list(overrides)), resolve=True)

        def build(kind, section: str):
            values = cfg.get(section) or {}
            known = {f.name for f in fields(kind)}
            unknown = sorted(set(values) - known)
            if unknown:
                raise ConfigError(f"unknown {section} keys {unknown}; known: {sorted(known)}")
            try:
                return kind(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"bad {section} config: {exc}") from exc

        unknown = sorted(set(cfg) - {"synth", "noise", "record"})
        if unknown:
            raise ConfigError(f"unknown data config sections {unknown}; known: synth, noise, record")
        rec = cfg.get("record") or {}
        try:
            return cls(
                synth=build(SynthConfig, "synth"),
                noise=build(NoiseConfig, "noise"),
                prompt_objects=bool(rec.get("prompt_objects", True)),
                decimals=rec.get("decimals", DECIMALS),
                workers=int(rec.get("workers", 2)),
                measure=str(rec.get("measure", "auto")).lower(),
            )
        except ValueError as exc:  # the dataclass's own checks (__post_init__)
            raise ConfigError(str(exc)) from None


_FIT: ContainerFit | None = None


def _fit() -> ContainerFit:
    global _FIT
    if _FIT is None:
        _FIT = ContainerFit()
    return _FIT


def build_scenes(
    split: str, seed: int, item: PlanItem, config: DataConfig
) -> tuple[Scene, Scene, NoiseRecord, np.random.Generator]:
    """``(clean, noisy, noise, rng)`` of record ``item.index`` of ``split``: the clean layout as
    planned (captions included), the layout after annotation noise, the noise record, and the
    record's RNG where the noise left it (the record's text draws from it next)."""
    rng = record_rng(seed, split, item.index)
    spec = spec_for(item.scene_type)
    clean = synthesize_layout(spec, item.n_objects, item.level, rng, config.synth, _fit())
    clean = clean.with_objects(o.moved(description=describe(o.category, o.size, rng)) for o in clean.objects)
    noisy, noise = apply_noise(clean, item.level, rng, config.noise)
    return clean, noisy, noise, rng


def build_record(split: str, seed: int, item: PlanItem, config: DataConfig) -> dict:
    """Record ``item.index`` of ``split`` (pure function of its arguments)."""
    clean, noisy, noise, rng = build_scenes(split, seed, item, config)
    record = ctrc_record(
        noisy, record_id=f"{split}-{item.index:05d}", rng=rng, prompt_objects=config.prompt_objects,
        decimals=config.decimals,
    )
    record.update(split=split, noise=noise.as_dict(), arrangement_style=clean.meta["arrangement_style"])
    return record


def synthesize(
    split: str, n: int | None = None, seed: int = 0, config: DataConfig | None = None
) -> Iterator[dict]:
    """The records of a synthetic split, in order (single process)."""
    config = config or DataConfig()
    for item in plan_split(split, n, seed):
        yield build_record(split, seed, item, config)


def _work(args) -> str:
    split, seed, item, config = args
    return dumps_record(build_record(split, seed, item, config))


def _ignore_interrupt() -> None:
    """Pool workers leave Ctrl-C to the parent, which stops the pool (no traceback per worker)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def write_records(lines: Iterable[str], path: Path) -> None:
    """One record per line, written under a temporary name and renamed when complete."""
    with open_atomic(path) as fh:
        for line in lines:
            fh.write(line + "\n")


def split_files(out_dir, split: str, lines: Sequence[str], stats: dict) -> dict[Path, str]:
    """``<split>.jsonl``, ``<split>_stats.md`` and ``<split>_stats.json`` (last: it says the split is
    complete), for :func:`physcene.files.write_atomic_many`."""
    out_dir = Path(out_dir)
    return {out_dir / f"{split}.jsonl": "".join(line + "\n" for line in lines),
            out_dir / f"{split}_stats.md": stats_markdown(stats),
            out_dir / f"{split}_stats.json": json.dumps(stats, indent=2, sort_keys=True) + "\n"}


def write_split(
    out_dir,
    split: str,
    n: int | None = None,
    seed: int = 0,
    config: DataConfig | None = None,
    *,
    progress: bool = True,
    measure: bool | None = None,
    measurer: Callable[[list[Scene]], dict] | None = None,
) -> dict:
    """Write ``<out_dir>/<split>.jsonl`` and its stats; returns the stats dict.

    ``measure`` (None = ``config.measure``; "auto" measures test and ood) scores every scene with
    ``measurer`` (:func:`physcene.eval.metrics.measure_reference`: the physics engine in one batched
    call) for the reference SCR/ACR. The measurer is passed in because the benchmark metrics live
    in the evaluation stage, which reads the data stage (not the other way round).
    """
    from tqdm import tqdm

    config = config or DataConfig()
    out_dir = Path(out_dir)
    plan = plan_split(split, n, seed)
    jobs = [(split, seed, item, config) for item in plan]
    t0 = time.perf_counter()
    bar = tqdm(total=len(jobs), desc=f"synth {split}", unit="scene", disable=not progress)
    lines: list[str] = []
    if config.workers > 1 and len(jobs) > 32:
        ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else mp.get_context()
        with ctx.Pool(config.workers, initializer=_ignore_interrupt) as pool:
            for line in pool.imap(_work, jobs, chunksize=16):
                lines.append(line)
                bar.update()
    else:
        for job in jobs:
            lines.append(_work(job))
            bar.update()
    bar.close()
    seconds = time.perf_counter() - t0
    path = out_dir / f"{split}.jsonl"
    records = [json.loads(line) for line in lines]
    if measure is None:
        measure = (
            split in ("test", "ood") if config.measure == "auto" else config.measure in ("true", "1", "yes")
        )
    if measure and measurer is None:
        raise ValueError(f"write_split: measuring the {split} split's reference needs measurer= "
                         "(e.g. physcene.eval.metrics.measure_reference)")
    stats = split_stats(records, measurer=measurer if measure else None)
    stats.update(split=split, seed=seed, file=path.name)
    # The split and its stats appear together (none is left over from an older run), after the
    # measuring: an interrupted run leaves the previous files or none.
    write_atomic_many(split_files(out_dir, split, lines, stats))
    stats["generation_seconds"] = round(seconds, 2)  # reported, never written (files stay byte-identical)
    return stats


def _scene_of(record: dict) -> Scene:
    return load_layout(record["layout"], source=record["id"])


def split_stats(records: list[dict], *, measurer: Callable[[list[Scene]], dict] | None = None) -> dict:
    """Type × level counts, noise totals and (with a ``measurer``, e.g.
    :func:`physcene.eval.metrics.measure_reference`) the engine's reference SCR/ACR."""
    found: dict[str, dict[str, int]] = {}
    for r in records:
        row = found.setdefault(r["scene_type"], {str(lv): 0 for lv in range(1, 6)})
        row[str(r["level"])] += 1
    order = [t for t in (*SCENE_TYPES, *OOD_SCENE_TYPES) if t in found] + sorted(
        t for t in found if t not in SCENE_TYPES and t not in OOD_SCENE_TYPES
    )
    counts = {t: found[t] for t in order}  # Table 5's row order
    noise = {"careful": 0, "interpenetration": 0, "sunk": 0, "hover": 0}
    for r in records:
        nz = r.get("noise") or {}
        noise["careful"] += int(bool(nz.get("careful")))
        for k in ("interpenetration", "sunk", "hover"):
            noise[k] += len(nz.get(k, []))
    agreement = [r["hierarchy_agreement"] for r in records if "hierarchy_agreement" in r]
    stats = {
        "n": len(records),
        "counts": counts,
        "noise": noise,
        "distinct_instructions": len({r["instruction"] for r in records}),
        "mean_objects": round(sum(r["n_objects"] for r in records) / max(len(records), 1), 3),
    }
    if agreement:
        stats["hierarchy_agreement"] = round(sum(agreement) / len(agreement), 4)
    if measurer is not None and records:
        ref = measurer([_scene_of(r) for r in records])
        per_scene = ref.pop("per_scene_pairs")
        stats["reference"] = ref
        by_level: dict[str, list[int]] = {}
        for r, p in zip(records, per_scene):
            by_level.setdefault(str(r["level"]), []).append(int(p > 0))
        stats["reference"]["scr_0cm_by_level"] = {
            k: round(sum(v) / len(v), 4) for k, v in sorted(by_level.items())
        }
    return stats


def stats_markdown(stats: dict) -> str:
    """The stats as a Markdown table in the paper's Table 5 layout."""
    lines = [
        f"# {stats.get('split', '')} split: {stats['n']} scenes",
        "",
        "| Scene type | Level 1 (1-4) | Level 2 (5-8) | Level 3 (9-12) | Level 4 (13-16) | Level 5 (17+) "
        "| Total |",
        "|---|---|---|---|---|---|---|",
    ]
    totals = [0] * 5
    for scene_type, row in stats["counts"].items():
        vals = [row[str(lv)] for lv in range(1, 6)]
        totals = [a + b for a, b in zip(totals, vals)]
        lines.append(f"| {scene_type} | " + " | ".join(map(str, vals)) + f" | {sum(vals)} |")
    lines.append("| **Total** | " + " | ".join(f"**{v}**" for v in totals) + f" | **{sum(totals)}** |")
    lines += [
        "",
        f"Distinct instructions: {stats['distinct_instructions']}; mean objects per scene: "
        f"{stats['mean_objects']}.",
        f"Noise: {json.dumps(stats['noise'], sort_keys=True)}.",
    ]
    if "hierarchy_agreement" in stats:
        lines.append(
            f"Extracted hierarchy equals the intended one for {100 * stats['hierarchy_agreement']:.1f} % "
            "of objects."
        )
    ref = stats.get("reference")
    if ref:
        lines += [
            "",
            "Reference physics (engine, `physcene.eval.metrics`):",
            "",
            "| Threshold | SCR | ACR |",
            "|---|---|---|",
        ]
        for t, v in ref["collision"].items():
            lines.append(f"| {t} | {100 * v['SCR']:.1f} % | {100 * v['ACR']:.2f} % |")
        lines.append(
            f"\nFloating: {100 * ref['floating']['scenes']:.1f} % of scenes, "
            f"{100 * ref['floating']['objects']:.2f} % of objects."
        )
    return "\n".join(lines) + "\n"
