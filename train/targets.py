"""Supervised targets of PADA's cross-entropy terms: the tokens of an anchor (or a denoising target)
with a loss mask, right padded into the batch tensors TRL shuffles and splits with the rollouts.

The CTRC span finders (numbers of the geometry keys, object lines, the text placing each object) say
which characters a mask covers; they are the format's, not PADA's: :mod:`physcene.ctrc.spans`.
"""

from __future__ import annotations

import numpy as np
import torch
from transformers import PreTrainedTokenizerBase

from physcene.ctrc.spans import (
    GEOMETRY_KEYS,
    OBJECT_TEXT_SCOPES,
    numeric_spans,
    object_line_spans,
    object_text_spans,
)

__all__ = [
    "ANCHOR_ROW_KEYS",
    "GEOMETRY_KEYS",
    "OBJECT_CREDIT_SCOPES",
    "numeric_spans",
    "object_credit_scope_checked",
    "object_line_spans",
    "object_text_spans",
    "padded_targets",
    "teacher_forced_nll",
    "tokenize_anchor",
    "tokenize_target",
]

# The scope names of the object credit are the span finders' (physcene.ctrc.spans).
OBJECT_CREDIT_SCOPES = OBJECT_TEXT_SCOPES


def object_credit_scope_checked(scope: str) -> str:
    """``scope`` if it is one of :data:`OBJECT_CREDIT_SCOPES`, else a ValueError naming them."""
    if scope not in OBJECT_CREDIT_SCOPES:
        raise ValueError(f"object credit scope must be one of {list(OBJECT_CREDIT_SCOPES)}, got {scope!r}")
    return scope


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


ANCHOR_ROW_KEYS = ("prompt_ids", "prompt_mask", "anchor_ids", "anchor_attention_mask", "anchor_loss_mask")
"""The per-row tensors of a PADA batch that the anchor CE reads."""


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


def teacher_forced_nll(model, rows: list[tuple[list[int], list[int], list[int]]],
                       pad: int = 0, temperature: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(summed NLL, supervised token count) of ``rows`` of (prompt ids, target ids, target loss mask),
    each read as [prompt | target] right padded with ``pad``, teacher-forced: the NLL of every target
    token whose mask is set, given everything before it, under ``softmax(logits / temperature)``.
    Differentiable (callers that only measure wrap it in ``torch.no_grad``)."""
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    width = max(len(p) + len(t) for p, t, _ in rows)
    ids = torch.full((len(rows), width), pad, dtype=torch.long)
    attention = torch.zeros((len(rows), width), dtype=torch.long)
    supervised = torch.zeros((len(rows), width), dtype=torch.bool)
    for k, (p, t, m) in enumerate(rows):  # positions count from the prompt's first token
        ids[k, :len(p) + len(t)] = torch.tensor(p + t, dtype=torch.long)
        attention[k, :len(p) + len(t)] = 1
        supervised[k, len(p):len(p) + len(t)] = torch.tensor(m, dtype=torch.bool)
    device = next(model.parameters()).device
    ids, attention, supervised = (x.to(device) for x in (ids, attention, supervised))
    logits = model(input_ids=ids, attention_mask=attention).logits[:, :-1].float() / temperature
    nll = torch.nn.functional.cross_entropy(logits.transpose(1, 2), ids[:, 1:], reduction="none")
    keep = supervised[:, 1:]
    return nll[keep].sum(), keep.sum()
