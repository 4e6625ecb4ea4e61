"""Training records: the prompt/completion JSONL of ``physcene data synth`` and the datasets built from it.

A record is ``{id, scene_type, level, instruction, prompt, completion, layout}`` (the data contract);
anchor files add ``anchor`` (TTO-repaired SFT output, CTRC text) and ``anchor_raw`` (raw SFT output).
``data.train`` in a training config is either a JSONL path or ``synth:SPLIT:N`` (synthesised on the fly
with ``physcene.data.synthesize(SPLIT, N, seed)``, handy for tests and quick runs).
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

from datasets import Dataset

from physcene.ctrc.prompts import with_physics
from physcene.files import open_atomic

__all__ = ["LEVELS", "PHYSICS_PROMPTS", "load_records", "model_prompt", "prompt_pool",
           "reference_collision_free", "to_chat", "training_dataset", "write_records"]

# The difficulty levels of physcene.data (1: 1-4 objects ... 5: the most crowded tables).
LEVELS = (1, 2, 3, 4, 5)


def load_records(spec: str, *, seed: int = 0, max_level: int | None = None) -> list[dict]:
    """Records from a JSONL path (gzipped if it ends in ``.gz``) or ``synth:SPLIT:N``; only levels <=
    ``max_level`` when given."""
    if spec.startswith("synth:"):
        parts = spec.split(":")
        if len(parts) != 3 or not parts[2].isdigit():
            raise ValueError(f"synthetic data spec must be synth:SPLIT:N, got {spec!r}")
        from physcene.data import synthesize

        # Over-draw so that the level filter still leaves N records for small N.
        n = int(parts[2])
        records = list(synthesize(parts[1], n if max_level is None else 8 * n, seed=seed))
    else:
        path = Path(spec)
        if not path.is_file():
            raise FileNotFoundError(f"training data {spec!r} does not exist (`physcene data synth` makes it)")
        records = []
        with (gzip.open(path, "rt") if path.suffix == ".gz" else path.open()) as f:
            for line_no, line in enumerate(f, 1):
                if line.strip():
                    try:
                        records.append(json.loads(line))
                    except json.JSONDecodeError as exc:
                        raise ValueError(f"{spec}:{line_no}: not JSON: {exc}") from exc
        n = None
    for i, r in enumerate(records):
        missing = {"prompt", "completion"} - set(r)
        if missing:
            raise ValueError(f"{spec}: record {i} ({r.get('id', '?')}) lacks {sorted(missing)}")
    if max_level is not None:
        records = [r for r in records if int(r.get("level", 1)) <= max_level]
    return records[:n] if n is not None else records


def write_records(records: list[dict], path: str | Path) -> None:
    """One JSON object per line (gzipped when the name ends in ``.gz``, as :func:`load_records` reads
    it), written to a temp file then renamed (a crash leaves no half file)."""
    path = Path(path)
    with open_atomic(path, "wb") as raw:
        # the gzip header names the final file, not the temporary one
        packed = gzip.GzipFile(filename=str(path), mode="wb", fileobj=raw) if path.suffix == ".gz" else None
        out = packed or raw
        for r in records:
            out.write((json.dumps(r) + "\n").encode("utf-8"))
        if packed is not None:
            packed.close()  # writes the gzip trailer into raw (it leaves raw open)


def prompt_pool(records: list[dict], tokenizer, *, size: int, max_tokens: int,
                levels: tuple[int, ...] = LEVELS, reserve: int = 1) -> tuple[list[dict], dict[int, dict]]:
    """Up to ``size`` RL training prompts whose reference completion fits a rollout of ``max_tokens``
    tokens under ``tokenizer`` (``reserve`` of them kept for the end of text), taken from every level
    in turn so that the levels the rollout length allows share the pool; returns (the records in the
    order of ``records``, ``{level: {"records", "fit", "picked"}}``). A rollout too short for a level's
    layouts is cut before it parses: such prompts teach the policy nothing but the unparsable reward."""
    if size < 1 or max_tokens < 1:
        raise ValueError(f"prompt pool: size and max_tokens must be >= 1, got {size}, {max_tokens}")
    kept = [k for k, r in enumerate(records) if int(r.get("level", 1)) in levels]
    texts = [records[k]["completion"] for k in kept]
    ids = tokenizer(texts, add_special_tokens=False)["input_ids"] if texts else []
    fitting: dict[int, list[int]] = {level: [] for level in levels}
    counts = {level: {"records": 0, "fit": 0, "picked": 0} for level in levels}
    for k, tokens in zip(kept, ids):
        level = int(records[k].get("level", 1))
        counts[level]["records"] += 1
        if len(tokens) + reserve <= max_tokens:
            fitting[level].append(k)
            counts[level]["fit"] += 1
    picked: list[int] = []
    queues = {level: iter(fitting[level]) for level in levels}
    while len(picked) < size and queues:
        for level in list(queues):  # one prompt of each level per round, until the pool is full
            k = next(queues[level], None)
            if k is None:
                del queues[level]
            elif len(picked) < size:
                picked.append(k)
                counts[level]["picked"] += 1
    return [records[k] for k in sorted(picked)], counts


def to_chat(prompt: str) -> list[dict]:
    """A user turn holding the CTRC prompt (chat-format models, e.g. Qwen3-VL)."""
    return [{"role": "user", "content": prompt}]


PHYSICS_PROMPTS = (None, "reference", "requested")
"""How a physics-conditioned model's prompts end (:func:`physcene.ctrc.with_physics`): not at all (None),
with the training layout's measured state (``reference``: SFT), or asking for a collision-free one
(``requested``: generation, RL)."""


def reference_collision_free(record: dict) -> bool:
    """Whether ``record``'s layout is collision-free, as ``physcene data measure`` wrote it."""
    physics = record.get("reference_physics")
    if not isinstance(physics, dict) or not isinstance(physics.get("collision_free"), bool):
        raise ValueError(f"record {record.get('id', '?')!r} has no reference_physics.collision_free, which a "
                         "physics-conditioned SFT reads: add it with `physcene data measure FILE --out FILE`")
    return physics["collision_free"]


def model_prompt(record: dict, physics: str | None) -> str:
    """The prompt text of ``record`` as a model reads it, per :data:`PHYSICS_PROMPTS`."""
    if physics not in PHYSICS_PROMPTS:
        raise ValueError(f"physics {physics!r}: expected one of {list(PHYSICS_PROMPTS)}")
    if physics is None:
        return record["prompt"]
    return with_physics(record["prompt"], physics == "requested" or reference_collision_free(record))


def training_dataset(records: list[dict], *, chat_format: bool, columns: tuple[str, ...] = ("completion",),
                     physics: str | None = None) -> Dataset:
    """A TRL prompt/completion dataset (string or conversational), with extra string ``columns`` kept;
    ``physics``: how the prompts end (:data:`PHYSICS_PROMPTS`).

    Only strings go into Arrow: nested layouts differ per record and would not share one schema.
    """
    rows = []
    for r in records:
        prompt = model_prompt(r, physics)
        row = {"prompt": to_chat(prompt) if chat_format else prompt, "id": str(r.get("id", ""))}
        for c in columns:
            value = r.get(c) or ""
            chat_turn = c == "completion" and chat_format
            row[c] = [{"role": "assistant", "content": value}] if chat_turn else value
        rows.append(row)
    return Dataset.from_list(rows)
