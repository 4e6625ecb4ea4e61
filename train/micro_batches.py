"""Micro-batches of similar length, each cut to its longest row (``pada.length_grouping``).

TRL pads a generation round's completions to the round's longest and cuts the round into
micro-batches at random, so a micro-batch of short rollouts still computes the longest one's width.
Within one optimizer step the micro-batches' gradients are summed, and the loss PADA trains with
(TRL's ``dapo``: token losses over the round's token count; the anchor CE over the round's anchor
tokens) does not depend on which micro-batch a row is in. So the rows of each optimizer step are
regrouped by completion length (:func:`grouped_by_length`) and each micro-batch is cut to the
columns its rows use (:func:`trimmed`): the step's gradient is the same sum in another order, and
the padding's compute is not spent. Rounds with image fields, or with a per-token tensor this module
does not know, are left as TRL made them.
"""

from __future__ import annotations

import logging

import torch

__all__ = ["COMPLETION_KEYS", "PROMPT_KEYS", "grouped_by_length", "trimmed"]

logger = logging.getLogger(__name__)

COMPLETION_KEYS = ("completion_ids", "completion_mask", "old_per_token_logps", "ref_per_token_logps",
                   "sampling_per_token_logps", "importance_sampling_ratio", "tool_mask", "advantages")
"""Per-row tensors whose second axis is the completion's tokens (when they have one)."""
PROMPT_KEYS = ("prompt_ids", "prompt_mask")
"""Per-row tensors whose second axis is the left-padded prompt's tokens."""
_IMAGE_KEYS = ("pixel_values", "image_grid_thw", "pixel_attention_mask", "token_type_ids",
               "mm_token_type_ids", "image_position_ids", "spatial_shapes", "image_sizes")
_OWN_WIDTH = ("anchor_", "denoise_")  # [prompt | target] tensors of their own width (train/targets.py)
_warned: set[str] = set()


def _rows(batch: dict) -> int:
    return int(batch["completion_ids"].shape[0])


def _groupable(batch: dict) -> bool:
    """Text rows only: no image field carries a value."""
    return "completion_ids" in batch and all(batch.get(k) is None for k in _IMAGE_KEYS)


def _concat(batches: list[dict]) -> dict | None:
    """The micro-batches as one (rows concatenated; 0-d tensors and None kept), or None when a value
    is neither a per-row tensor or list, a 0-d tensor nor None."""
    rows = [_rows(b) for b in batches]
    out = {}
    for key in batches[0]:
        values = [b[key] for b in batches]
        first = values[0]
        if first is None or isinstance(first, torch.Tensor) and first.ndim == 0:
            out[key] = first
        elif isinstance(first, torch.Tensor) and all(v.shape[0] == n for v, n in zip(values, rows)):
            out[key] = torch.cat(values)
        elif isinstance(first, list) and all(len(v) == n for v, n in zip(values, rows)):
            out[key] = [x for v in values for x in v]
        else:
            return None
    return out


def _take(batch: dict, index: torch.Tensor, n: int) -> dict:
    """Rows ``index`` of a concatenated batch of ``n`` rows."""
    out = {}
    for key, value in batch.items():
        if isinstance(value, torch.Tensor) and value.ndim > 0 and value.shape[0] == n:
            out[key] = value.index_select(0, index.to(value.device))
        elif isinstance(value, list) and len(value) == n:
            out[key] = [value[i] for i in index.tolist()]
        else:
            out[key] = value
    return out


def grouped_by_length(buffer: list[dict], per_step: int) -> list[dict]:
    """The round's micro-batches (TRL's buffer), regrouped within each optimizer step (``per_step``
    consecutive micro-batches) so that rows of similar completion length share a micro-batch; the
    same rows per step and the same number of rows per micro-batch. Left as it is when the buffer
    does not divide into steps or a micro-batch holds what :func:`_concat` cannot join."""
    if per_step < 2 or len(buffer) % per_step or not all(_groupable(b) for b in buffer):
        return buffer
    out = []
    for start in range(0, len(buffer), per_step):
        step = buffer[start:start + per_step]
        joined = _concat(step)
        if joined is None:
            return buffer
        n, size = _rows(joined), _rows(step[0])
        if any(_rows(b) != size for b in step):
            return buffer
        lengths = joined["completion_mask"].sum(dim=1)
        order = torch.argsort(lengths, descending=True, stable=True)
        out += [_take(joined, order[k * size:(k + 1) * size], n) for k in range(per_step)]
    return out


def trimmed(batch: dict) -> dict:
    """``batch`` without the completion columns that no row uses (at the right) and the prompt
    columns that are padding in every row (at the left). Unchanged when a per-row tensor of the
    completion's or the prompt's width is not in :data:`COMPLETION_KEYS` / :data:`PROMPT_KEYS` (it
    could not be cut with them), or for image rows."""
    if not _groupable(batch):
        return batch
    n = _rows(batch)
    width, prompt_width = batch["completion_ids"].shape[1], batch["prompt_ids"].shape[1]
    for key, value in batch.items():
        if (isinstance(value, torch.Tensor) and value.ndim == 2 and value.shape[0] == n
                and key not in COMPLETION_KEYS + PROMPT_KEYS and not key.startswith(_OWN_WIDTH)
                and value.shape[1] in (width, prompt_width)):
            if key not in _warned:
                _warned.add(key)
                logger.info("micro-batches not cut: %r has the width of the completions or prompts", key)
            return batch
    used = batch["completion_mask"].any(dim=0).nonzero()
    keep = int(used.max()) + 1 if used.numel() else 1
    padded = (~batch["prompt_mask"].bool()).all(dim=0)
    lead = int(padded.long().cumprod(0).sum())  # leading columns that are padding in every row
    lead = min(lead, prompt_width - 1)
    if keep == width and lead == 0:
        return batch
    out = dict(batch)
    for key in COMPLETION_KEYS:
        value = out.get(key)
        if isinstance(value, torch.Tensor) and value.ndim >= 2 and value.shape[1] == width:
            out[key] = value[:, :keep]
    for key in PROMPT_KEYS:
        out[key] = out[key][:, lead:]
    return out
