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

from physcene.files import open_atomic

__all__ = ["load_records", "to_chat", "training_dataset", "write_records"]


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


def to_chat(prompt: str) -> list[dict]:
    """A user turn holding the CTRC prompt (chat-format models, e.g. Qwen3-VL)."""
    return [{"role": "user", "content": prompt}]


def training_dataset(records: list[dict], *, chat_format: bool,
                     columns: tuple[str, ...] = ("completion",)) -> Dataset:
    """A TRL prompt/completion dataset (string or conversational), with extra string ``columns`` kept.

    Only strings go into Arrow: nested layouts differ per record and would not share one schema.
    """
    rows = []
    for r in records:
        row = {"prompt": to_chat(r["prompt"]) if chat_format else r["prompt"], "id": str(r.get("id", ""))}
        for c in columns:
            value = r.get(c) or ""
            chat_turn = c == "completion" and chat_format
            row[c] = [{"role": "assistant", "content": value}] if chat_turn else value
        rows.append(row)
    return Dataset.from_list(rows)
