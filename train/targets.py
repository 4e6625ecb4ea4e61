"""Supervised targets of PADA's cross-entropy terms: the tokens of an anchor (or a denoising target)
with a loss mask, right padded into the batch tensors TRL shuffles and splits with the rollouts.

The CTRC span finders at the top (numbers of the geometry keys, object lines, the text placing each
object) say which characters a mask covers; they are the format's, not PADA's.
"""

from __future__ import annotations

import re

import numpy as np
import torch
from transformers import PreTrainedTokenizerBase

from physcene.ctrc import LAYOUT_HEADER

__all__ = [
    "GEOMETRY_KEYS",
    "OBJECT_CREDIT_SCOPES",
    "numeric_spans",
    "object_credit_scope_checked",
    "object_line_spans",
    "object_text_spans",
    "padded_targets",
    "tokenize_anchor",
    "tokenize_target",
]

# JSON keys whose numbers PADA* leaves to exploration: the geometry, not the semantics.
GEOMETRY_KEYS = ("relative_bbox", "relative_rotation_deg")
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def numeric_spans(text: str, keys: tuple[str, ...] | list[str] = GEOMETRY_KEYS) -> list[tuple[int, int]]:
    """Character spans ``[start, end)`` of the numbers inside the JSON values of ``keys`` in ``text``.

    A value is the bracketed list or the scalar after ``"key":``. Numbers elsewhere (instance ids such
    as ``pen_0``, layer indices, the zone) are semantic and stay supervised.
    """
    spans = []
    for key in keys:
        for m in re.finditer(rf'"{re.escape(key)}"\s*:\s*(\[[^\]]*\]|[-+0-9.eE]+)', text):
            base = m.start(1)
            spans.extend((base + n.start(), base + n.end()) for n in _NUMBER.finditer(m.group(1)))
    return sorted(spans)


def object_line_spans(text: str) -> list[tuple[int, int]]:
    """Character spans ``[start, end)`` of the object lines of a CTRC layout, in the order written
    (the lines with a ``relative_bbox``; the zone's line has none): object k of the parsed scene."""
    spans, start = [], 0
    for line in text.splitlines(keepends=True):
        if '"relative_bbox"' in line:
            spans.append((start, start + len(line.rstrip("\n"))))
        start += len(line)
    return spans


_INSTANCE_ID = re.compile(r'"instance_id": "([^"]*)"')
_PLAN_STEP = re.compile(r"\s*\d+\.\s+Place (\S+)\s")


OBJECT_CREDIT_SCOPES = ("line", "numbers")


def object_credit_scope_checked(scope: str) -> str:
    """``scope`` if it is one of :data:`OBJECT_CREDIT_SCOPES`, else a ValueError naming them."""
    if scope not in OBJECT_CREDIT_SCOPES:
        raise ValueError(f"object credit scope must be one of {list(OBJECT_CREDIT_SCOPES)}, got {scope!r}")
    return scope


def object_text_spans(text: str, scope: str = "line") -> list[list[tuple[int, int]]]:
    """Per object of a CTRC layout, in the order written (object k of the parsed scene): the
    character spans of the text that places it. ``scope`` ``line``: its plan step ("k. Place <id>
    ...", the first one naming it, when the plan has one) and its layout line
    (:func:`object_line_spans`); ``numbers``: only the numbers of its geometry (:data:`GEOMETRY_KEYS`)
    on that line, so its id, category, relation and description are never charged."""
    if object_credit_scope_checked(scope) == "numbers":
        return [[(a + x, a + y) for x, y in numeric_spans(text[a:b])] for a, b in object_line_spans(text)]
    plan_end = text.find(LAYOUT_HEADER)
    steps, start = {}, 0
    for line in text[:max(plan_end, 0)].splitlines(keepends=True):
        if (m := _PLAN_STEP.match(line)) is not None:
            steps.setdefault(m.group(1), (start, start + len(line.rstrip("\n"))))
        start += len(line)
    spans = []
    for a, b in object_line_spans(text):
        m = _INSTANCE_ID.search(text, a, b)
        step = steps.get(m.group(1)) if m is not None else None
        spans.append([s for s in (step, (a, b)) if s is not None])
    return spans


def tokenize_anchor(tokenizer: PreTrainedTokenizerBase, text: str, *, max_length: int,
                    numeric_mask: bool = False, keys=GEOMETRY_KEYS) -> tuple[list[int], list[int]]:
    """(token ids, loss mask) of an anchor completion, EOS appended, at most ``max_length`` tokens.

    The EOS is supervised like the generated completions' EOS (the model must learn to stop). With
    ``numeric_mask`` every token overlapping a geometry number gets loss mask 0. Empty text -> ``([], [])``.
    """
    if not text:
        return [], []
    enc = tokenizer(text, add_special_tokens=False, return_offsets_mapping=numeric_mask)
    ids = list(enc["input_ids"]) + [tokenizer.eos_token_id]
    mask = [1] * len(ids)
    if numeric_mask:
        for t in _tokens_over(enc["offset_mapping"], numeric_spans(text, keys)):
            mask[t] = 0
    return ids[:max_length], mask[:max_length]


def tokenize_target(tokenizer: PreTrainedTokenizerBase, text: str, spans: list[tuple[int, int]], *,
                    max_length: int) -> tuple[list[int], list[int]]:
    """(token ids, loss mask) of a completion, EOS appended, supervised only where a token overlaps one
    of the character ``spans`` (:mod:`physcene.train.denoise`'s rewritten numbers); at most
    ``max_length`` tokens. Empty text -> ``([], [])``."""
    if not text:
        return [], []
    enc = tokenizer(text, add_special_tokens=False, return_offsets_mapping=True)
    ids = list(enc["input_ids"]) + [tokenizer.eos_token_id]
    mask = [0] * len(ids)
    for t in _tokens_over(enc["offset_mapping"], spans):
        mask[t] = 1
    return ids[:max_length], mask[:max_length]


def padded_targets(name: str, rows: list[tuple[list[int], list[int]]], pad: int, device) -> dict:
    """``<name>_ids`` / ``<name>_attention_mask`` / ``<name>_loss_mask`` (B, T) of per-row (ids, loss
    mask), right padded like TRL's completion_ids so that [prompt | target] reads as prompt +
    completion; an empty row is all padding."""
    width = max(1, max((len(ids) for ids, _ in rows), default=0))
    return {
        f"{name}_ids": torch.tensor([ids + [pad] * (width - len(ids)) for ids, _ in rows], device=device),
        f"{name}_attention_mask": torch.tensor([[1] * len(ids) + [0] * (width - len(ids)) for ids, _ in rows],
                                               device=device),
        f"{name}_loss_mask": torch.tensor([m + [0] * (width - len(m)) for _, m in rows], device=device),
    }


def _tokens_over(offsets, spans: list[tuple[int, int]]) -> list[int]:
    """Indices of the tokens (character ``offsets``) that overlap any of the sorted ``spans``."""
    if not spans:
        return []
    starts = np.array([s for s, _ in spans])
    ends = np.maximum.accumulate(np.array([e for _, e in spans]))
    out = []
    for t, (a, b) in enumerate(offsets):
        k = int(np.searchsorted(starts, b, side="left")) - 1  # the last span starting before b
        if k >= 0 and ends[k] > a:
            out.append(t)
    return out
