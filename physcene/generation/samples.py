"""``generate``: an instruction in, K layouts out, each checked, optionally repaired, rendered, exported.

Every generator starts from the procedural plan of the instruction (scene type, zone, the named
objects plus fill-ins, :mod:`physcene.generation.procedural`): ``procedural`` returns it as it
is; ``endpoint:URL`` and ``model:PATH`` are given its zone and object list and write the poses
themselves. Per sample, with ``out``::

    sample_<k>/completion.txt        the CTRC completion of the layout (physcene.ctrc)
    sample_<k>/reply.txt             the endpoint's or model's own text (those generators)
    sample_<k>/layout.json           MesaTask layout (cm), parent/relation kept
    sample_<k>/check.json            pairs by id, floating ids, table penetration
    sample_<k>/front.png, perspective.png   renders of the final layout (repaired one with repair)
    sample_<k>/repaired.layout.json, repair.json   with repair: TTO's layout, its report and check
    sample_<k>/export/<fmt>/...      with export: simulator files of the final layout
    generate.json                    the instruction as read and every sample's files and verdicts
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from physcene import api
from physcene.ctrc import ParseError, build_prompt, completion_text, parse, zero_shot_prompt
from physcene.generation.endpoint import endpoint_replies
from physcene.generation.instruction import Instruction, read_instruction
from physcene.generation.model import model_completions
from physcene.generation.procedural import GenerationError, procedural_scene
from physcene.scene import Scene

__all__ = ["EXPORT_FORMATS", "GENERATORS", "Generation", "Sample", "generate"]

GENERATORS = ("procedural", "endpoint:URL", "model:PATH")
EXPORT_FORMATS = ("mjcf", "urdf", "glb")


@dataclass
class Sample:
    """One generated layout and what was made of it."""

    index: int
    """Sample number, 0-based."""
    scene: Scene | None
    """The generated layout (None when the generator's text did not parse: see ``error``)."""
    completion: str = ""
    """The layout's CTRC completion."""
    reply: str | None = None
    """The endpoint's or model's own text (None for the procedural generator)."""
    check: dict | None = None
    """:func:`physcene.check` report of ``scene``."""
    repaired: Scene | None = None
    """With repair: TTO's layout."""
    repair_report: dict | None = None
    """With repair: TTO's report (energies, displacement, relations kept) and ``check`` of ``repaired``."""
    files: dict = field(default_factory=dict)
    """Name -> path of every file written for the sample."""
    error: str | None = None
    """Why no layout came out (an unparsable reply), else None."""

    @property
    def final(self) -> Scene | None:
        """The repaired layout when there is one, else the generated one."""
        return self.repaired if self.repaired is not None else self.scene

    def summary(self) -> dict:
        return {"index": self.index, "error": self.error,
                "objects": self.scene.ids() if self.scene is not None else [],
                "check": self.check, "repair": self.repair_report,
                "files": {k: str(v) for k, v in self.files.items()}}


@dataclass
class Generation:
    """What :func:`generate` returns: the reading of the instruction and the samples (iterable)."""

    instruction: Instruction
    """The reading of the instruction (scene type, objects, relations, words not understood)."""
    generator: str
    """``procedural``, ``endpoint:URL`` or ``model:PATH``."""
    seed: int
    """The seed sample ``k`` drew its plan from (``numpy`` generator seeded ``[seed, k]``)."""
    samples: list[Sample]
    """One per requested sample, in order."""
    out: Path | None = None
    """Where the files went (None: nothing written)."""

    def __iter__(self):
        return iter(self.samples)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, k: int) -> Sample:
        return self.samples[k]

    def summary(self) -> dict:
        return {"instruction": self.instruction.text, "reading": self.instruction.summary(),
                "generator": self.generator, "seed": self.seed, "out": str(self.out) if self.out else None,
                "samples": [s.summary() for s in self.samples]}


def _check_generator(generator: str) -> str:
    kind, _, target = generator.partition(":")
    if generator == "procedural" or kind in ("endpoint", "model") and target:
        return generator
    raise GenerationError(f"unknown generator {generator!r}; expected one of {', '.join(GENERATORS)}")


def _layouts(instruction: Instruction, plans: list[Scene], generator: str, *, seed: int, progress: bool,
             endpoint_model: str, device: str | None,
             max_new_tokens: int) -> list[tuple[Scene | ParseError, str | None]]:
    """(layout or ParseError, the generator's own text) per plan."""
    if generator == "procedural":
        return [(p, None) for p in plans]
    if generator.startswith("endpoint:"):
        prompts = [zero_shot_prompt(instruction.text, p.zone, p.objects) for p in plans]
        texts = endpoint_replies(generator[9:], prompts, model=endpoint_model, seed=seed, progress=progress)
    else:
        prompts = [build_prompt(instruction.text, instruction.scene_type, p.zone, p.objects,
                                restricted_zones=p.restricted_zones) for p in plans]
        texts = model_completions(generator[6:], prompts, seed=seed, device=device, progress=progress,
                                  max_new_tokens=max_new_tokens)
    out = []
    for plan, text in zip(plans, texts):
        scene = parse(text, zone=plan.zone, scene_type=instruction.scene_type, instruction=instruction.text)
        if not isinstance(scene, ParseError) and not scene.restricted_zones and plan.restricted_zones:
            scene = Scene(scene.zone, scene.objects, scene.scene_type, scene.instruction,
                          plan.restricted_zones, scene.meta)
        out.append((scene, text))
    return out


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def _write_sample(sample: Sample, folder: Path, export: Sequence[str], render: bool) -> None:
    files = sample.files
    if sample.reply is not None:
        files["reply"] = _write(folder / "reply.txt", sample.reply)
    if sample.scene is None:
        files["error"] = _write(folder / "error.txt", f"{sample.error}\n")
        return
    files["completion"] = _write(folder / "completion.txt", sample.completion)
    files["layout"] = api.save_layout(sample.scene, folder / "layout.json")
    files["check"] = _write(folder / "check.json", json.dumps(sample.check, indent=1) + "\n")
    if sample.repaired is not None:
        files["repaired_layout"] = api.save_layout(sample.repaired, folder / "repaired.layout.json")
        files["repair_report"] = _write(folder / "repair.json",
                                        json.dumps(sample.repair_report, indent=1) + "\n")
    if render:
        for view in ("front", "perspective"):
            files[f"render_{view}"] = folder / f"{view}.png"
            api.render(sample.final, files[f"render_{view}"], view=view)
    for fmt in export:
        files[f"export_{fmt}"] = api.export(sample.final, folder / "export" / fmt, fmt)


def generate(instruction: str, *, generator: str = "procedural", n: int = 1, seed: int = 0,
             repair: bool = False, out=None, export: Sequence[str] | str = (), render: bool = True,
             scene_type: str | None = None, device: str = "cpu", endpoint_model: str = "default",
             max_new_tokens: int = 4096, progress: bool = False) -> Generation:
    """``n`` layouts for ``instruction`` (see the module docstring), checked by the physics engine,
    repaired by TTO with ``repair``; files are written under ``out`` when it is given (renders with
    ``render``, simulator files for each format of ``export``: mjcf, urdf, glb).

    ``generator``: ``procedural`` (offline), ``endpoint:URL`` (OpenAI-compatible chat server,
    key in ``$PHYSCENE_GENERATOR_API_KEY``, model name ``endpoint_model``) or ``model:PATH``.
    ``max_new_tokens`` bounds a model's completion; ``scene_type`` overrides the one the instruction
    names. Raises :class:`GenerationError` (a
    ``ValueError``) when the generator cannot run or nothing could be fitted.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise GenerationError(f"n must be a whole number >= 1, got {n!r}")
    export = (export,) if isinstance(export, str) else tuple(export)
    bad = [f for f in export if f not in EXPORT_FORMATS]
    if bad:
        raise GenerationError(f"unknown export format {bad[0]!r}; "
                              f"expected one of {', '.join(EXPORT_FORMATS)}")
    generator = _check_generator(generator)
    reading = read_instruction(instruction, scene_type)
    plans = [procedural_scene(reading, np.random.default_rng([seed, k])) for k in range(n)]
    samples = []
    for k, (layout, text) in enumerate(_layouts(reading, plans, generator, seed=seed, progress=progress,
                                                 endpoint_model=endpoint_model, device=device,
                                                 max_new_tokens=max_new_tokens)):
        if isinstance(layout, ParseError):
            error = f"the {generator} output did not parse: {layout.reason}"
            samples.append(Sample(k, None, reply=text, error=error))
        else:
            samples.append(Sample(k, layout, completion_text(layout), reply=text))
    good = [s for s in samples if s.scene is not None]
    engine = None
    if good:
        from physcene.physics import PhysicsEngine  # torch + Warp: only once there is something to check

        engine = PhysicsEngine(device=device)
        for s, report in zip(good, api.check([s.scene for s in good], engine=engine)):
            s.check = report
    if repair and good:
        fixed = api.repair([s.scene for s in good], device=device, engine=engine)
        for s, (scene, report), verdict in zip(good, fixed, api.check([f for f, _ in fixed], engine=engine)):
            s.repaired, s.repair_report = scene, {"tto": report, "check": verdict}
    result = Generation(reading, generator, seed, samples, Path(out) if out is not None else None)
    if result.out is not None:
        for s in tqdm(samples, desc="write", unit="scene", disable=not progress):
            _write_sample(s, result.out / f"sample_{s.index}", export, render)
        _write(result.out / "generate.json", json.dumps(result.summary(), indent=1) + "\n")
    return result
