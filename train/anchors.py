"""Physically-projected semantic anchors (paper Sec. 3.3): S*_anchor = TTO(S_sft).

For every training prompt the SFT model writes a layout (greedy decoding), the layout is parsed
(``physcene.ctrc.parse``, against the record's own placement zone) and repaired by hierarchy-
constrained TTO (``physcene.tto.repair``); the repaired scene is written back as CTRC text
(``physcene.ctrc.completion_text``). Each output record is the input record plus

- ``anchor``: the TTO-repaired completion (PADA's target), ``""`` when the SFT output did not parse;
- ``anchor_raw``: the raw SFT completion (PADA*'s target), ``""`` when it did not parse;
- ``anchor_parse_error``: the parser's reason, or ``""``;
- ``sft_completion``: the raw SFT completion, parsed or not (what a failed parse looked like);
- ``sft_tokens`` / ``sft_truncated``: its length in tokens and whether it hit ``max_new_tokens``
  without EOS (a model that loops is told apart from one that writes a wrong but finished layout);
- ``anchor_energy_before`` / ``anchor_energy_after``: penetration energy (cm) before and after TTO.

On N processes (``accelerate launch``) each rank generates and repairs a contiguous shard on its
own GPU; the shards are gathered in order and rank 0 writes the JSONL and a summary JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch
from accelerate import PartialState
from accelerate.utils import gather_object
from omegaconf import DictConfig

from physcene.ctrc import ParseError, completion_text, parse
from physcene.files import write_atomic
from physcene.layout import load_layout
from physcene.scene import SceneError
from physcene.train.generate import generate_token_ids, input_format, load_for_generation, render_prompt
from physcene.train.models import load_tokenizer
from physcene.train.records import load_records, prompt_pool, write_records
from physcene.train.targets import teacher_forced_nll, tokenize_anchor
from physcene.tto import TTOConfig, repair

__all__ = ["anchor_nll", "anchor_prompts", "anchor_records", "anchor_summary", "completion_length",
           "run_anchors"]


def _record_zone(record: dict):
    """The record's placement zone (its ground-truth layout's), or None to trust the completion's."""
    layout = record.get("layout")
    if not isinstance(layout, dict) or "item_placement_zone" not in layout:
        return None
    try:
        return load_layout(layout, source=str(record.get("id", "<record>"))).zone
    except ValueError:
        return None


def anchor_records(records: list[dict], completions: list[str], *, tto_config=None, engine=None,
                   decimals: int | None = None, lengths: list[tuple[int, bool]] | None = None) -> list[dict]:
    """``records`` with the anchor columns filled from the SFT ``completions`` (one per record).

    All parsed layouts are repaired in one batched TTO call. ``lengths``: (tokens, truncated) per
    completion, from the generator, written as ``sft_tokens``/``sft_truncated``.
    """
    if len(records) != len(completions):
        raise ValueError(f"{len(records)} records but {len(completions)} completions")
    if lengths is not None and len(lengths) != len(completions):
        raise ValueError(f"{len(completions)} completions but {len(lengths)} lengths")
    scenes, errors = [], []
    for r, text in zip(records, completions):
        scene = parse(text, zone=_record_zone(r), scene_type=str(r.get("scene_type", "")),
                      instruction=str(r.get("instruction", "")))
        scenes.append(None if isinstance(scene, ParseError) else scene)
        errors.append(scene.reason if isinstance(scene, ParseError) else "")
    parsed = [i for i, s in enumerate(scenes) if s is not None]
    results = repair([scenes[i] for i in parsed], config=tto_config, engine=engine) if parsed else []
    repaired = dict(zip(parsed, results))
    text_kwargs = {} if decimals is None else {"decimals": int(decimals)}
    out = []
    for i, (r, text) in enumerate(zip(records, completions)):
        row = dict(r)
        res = repaired.get(i)
        anchor = ""
        if res is not None:
            try:
                anchor = completion_text(res.scene, **text_kwargs)
            except SceneError as exc:  # one odd layout must not cost the whole anchor run
                errors[i], res = f"anchor text: {exc}", None
        row["anchor"] = anchor
        row["anchor_raw"] = text if res is not None else ""
        row["anchor_parse_error"] = errors[i]
        row["anchor_energy_before"] = float(res.energy_before) if res is not None else None
        row["anchor_energy_after"] = float(res.energy_after) if res is not None else None
        row["sft_completion"] = text
        if lengths is not None:
            row["sft_tokens"], row["sft_truncated"] = int(lengths[i][0]), bool(lengths[i][1])
        out.append(row)
    return out


def anchor_summary(rows: list[dict]) -> dict:
    """Parse rate and mean/zero-energy figures of an anchor file (what ``anchors.summary.json`` holds)."""
    parsed = [r for r in rows if r.get("anchor")]
    before = [r["anchor_energy_before"] for r in parsed]
    after = [r["anchor_energy_after"] for r in parsed]
    mean = (lambda xs: sum(xs) / len(xs) if xs else None)  # noqa: E731
    from physcene.eval.metrics import parse_error_kinds

    tokens = [r["sft_tokens"] for r in rows if r.get("sft_tokens") is not None]
    return {
        "n": len(rows),
        "parse_rate": len(parsed) / max(len(rows), 1),
        "truncated_rate": mean([float(r["sft_truncated"]) for r in rows if "sft_truncated" in r]),
        "tokens_mean": mean(tokens),
        "tokens_max": max(tokens, default=None),
        "parse_error_kinds": parse_error_kinds(r["anchor_parse_error"] for r in rows
                                               if r.get("anchor_parse_error")),
        "energy_before_mean_cm": mean(before),
        "energy_after_mean_cm": mean(after),
        "collision_free_before": mean([float(e <= 0.0) for e in before]),
        "collision_free_after": mean([float(e <= 0.0) for e in after]),
    }


def completion_length(ids: list[int], tokenizer) -> tuple[int, bool]:
    """(tokens up to and including EOS, True when no EOS came: the row hit ``max_new_tokens``)."""
    eos = tokenizer.eos_token_id
    if eos in ids:
        return ids.index(eos) + 1, False
    return len(ids), True


def anchor_prompts(cfg) -> list[dict]:
    """The training records that get an anchor: levels <= ``anchors.max_level`` (by default
    ``pada.max_level``: no anchor is made for a prompt PADA never sees) and ``data.max_level``, then the
    first ``anchors.n_records``; or with ``anchors.pool_size`` a pool of that many whose reference fits
    ``pada.max_completion_length`` tokens, spread over the levels (:func:`.records.prompt_pool`).
    ``anchors.exclude`` (a record or anchor file) leaves its prompts out: held-out anchors for
    :func:`anchor_nll`, from prompts the RL pool does not hold."""
    a = cfg.anchors
    levels = [x for x in (cfg.data.get("max_level"), a.get("max_level")) if x is not None]
    records = load_records(str(cfg.data.train), seed=int(cfg.seed), max_level=min(levels) if levels else None)
    if a.get("exclude"):  # held-out anchors: none of the prompts of that (RL pool's) file
        taken = {r["id"] for r in load_records(str(a.exclude))}
        records = [r for r in records if r.get("id") not in taken]
    if a.get("pool_size") is not None:
        records, counts = prompt_pool(records, load_tokenizer(str(a.model)), size=int(a.pool_size),
                                      max_tokens=int(cfg.pada.max_completion_length))
        print("prompt pool: " + "; ".join(f"level {lv}: {c['picked']} of {c['fit']} that fit ({c['records']})"
                                          for lv, c in counts.items()), file=sys.stderr)
    elif a.get("n_records") is not None:
        records = records[:int(a.n_records)]
    return records


def run_anchors(cfg: DictConfig) -> Path:
    """Generate, parse and repair anchors for ``cfg.data.train`` with ``cfg.anchors.model``: the SFT model,
    or a LoRA checkpoint of an RL run merged into ``cfg.anchors.base`` (anchors refreshed from the policy).

    Writes ``cfg.anchors.output`` (JSONL) and ``<output>.summary.json``. An existing complete output is
    kept (rerun with ``anchors.overwrite=true`` to rebuild). Both files are renamed into place when
    complete, the anchors last: an interrupted run leaves no anchor file, or a whole one.
    """
    from physcene.physics import PhysicsEngine  # Warp: only when anchors are made

    a = cfg.anchors
    out = Path(str(a.output))
    have = len(load_records(str(out))) if out.is_file() and not a.get("overwrite", False) else None
    wanted = a.get("pool_size") if a.get("pool_size") is not None else a.get("n_records")
    if have is not None and wanted is not None and have == int(wanted):
        return out  # complete: no need for the training data (a later stage on another machine)
    records = anchor_prompts(cfg)
    if have == len(records):
        return out
    state = PartialState()
    device = str(state.device)
    indices = list(range(len(records)))
    with state.split_between_processes(indices) as shard:
        model, tokenizer, info = load_for_generation(a.model, device=device, base=a.get("base"))
        ids = generate_token_ids(model, tokenizer, [records[i]["prompt"] for i in shard],
                                 **input_format(info),
                                 max_new_tokens=int(a.max_new_tokens), batch_size=int(a.batch_size),
                                 cache=str(a.get("cache", "dynamic")),
                                 constrained=bool(a.get("constrained", False)))
        del model
        completions = [tokenizer.decode(row, skip_special_tokens=True) for row in ids]
        lengths = [completion_length(row, tokenizer) for row in ids]
        tto = TTOConfig.load([*a.tto, f"device={device}"])
        rows = anchor_records([records[i] for i in shard], completions, tto_config=tto,
                              engine=PhysicsEngine(device=device), decimals=a.get("decimals"),
                              lengths=lengths)
    rows = gather_object(rows)  # rank order = shard order = input order
    if state.is_main_process:
        # The anchor file is the one a later run checks for, so it comes last: the old one goes
        # first, then the summary and the anchors are each renamed into place when complete.
        out.unlink(missing_ok=True)
        write_atomic(out.with_suffix(".summary.json"), json.dumps(anchor_summary(rows), indent=2))
        write_records(rows, out)
    state.wait_for_everyone()
    return out


@torch.no_grad()
def anchor_nll(model_path: str | Path, records: list[dict], *, column: str = "anchor", max_length: int = 8192,
               device: str | None = None, batch_size: int = 16, base: str | Path | None = None,
               temperature: float = 1.0) -> dict:
    """How likely the model at ``model_path`` (an SFT model or an RL adapter on it) finds anchors:
    the mean NLL per anchor token (EOS included, as PADA's cross-entropy counts them) of the records'
    ``column`` text given their prompts, teacher-forced. Held-out anchors (``anchors.exclude``) make it
    the measure of what PADA claims: the policy kept close to the repaired layouts of prompts it did
    not train on. Returns ``{"nll", "tokens", "n"}`` (records without an anchor are left out). ``base``: an
    adapter's base model (:func:`physcene.train.generate.adapter_base`). ``temperature``: the NLL under
    ``softmax(logits / temperature)``; PADA's cross-entropy is taken at the rollouts' temperature
    (``pada.temperature``: TRL's log-probabilities divide the logits by it), so a run's own objective is
    read at that temperature, while 1 reads the model as it decodes greedily or samples at T = 1."""
    model, tokenizer, info = load_for_generation(model_path, device=device, base=base)
    fmt = input_format(info)
    rows = []
    for r in records:
        target, mask = tokenize_anchor(tokenizer, r.get(column) or "", max_length=max_length)
        if target:
            text = render_prompt(tokenizer, r["prompt"], **fmt)
            rows.append((tokenizer(text, add_special_tokens=False)["input_ids"], target, mask))
    rows.sort(key=lambda row: len(row[0]) + len(row[1]))  # batches of similar length: little padding
    total, tokens = 0.0, 0
    for start in range(0, len(rows), batch_size):
        nll, count = teacher_forced_nll(model, rows[start:start + batch_size], pad=tokenizer.pad_token_id,
                                        temperature=temperature)
        total += float(nll)
        tokens += int(count)
    return {"nll": total / max(tokens, 1), "tokens": tokens, "n": len(rows)}
