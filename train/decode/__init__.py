"""Fast decoding for rollouts and evaluation (``cache: fast``): near the KV-cache-read limit.

HF ``generate`` (``train/generate.py``'s other cache modes) stays the reference the fast path is
tested against. What the fast path changes, each part in its own module:

- :mod:`~physcene.train.decode.attention`: GQA attention without K/V expansion (the query heads of a
  KV head folded into the query axis), registered with transformers' ``AttentionInterface``;
- :mod:`~physcene.train.decode.cache`: a static KV cache with per-row write positions;
- :mod:`~physcene.train.decode.loop`: one prompt pass, then fixed-shape decoding steps replayed as
  CUDA graphs, reading the cache only up to a bucketed length, rows stopping at EOS;
- :mod:`~physcene.train.decode.overlap`: the CTRC constraint checked on the host while the GPU runs
  the next step, a refused row repaired by standing still for one step;
- :mod:`~physcene.train.decode.fuse`: each decoder layer's norms, projections, rotary embedding and
  MLP compiled into a few fused kernels around the cache write and the attention;
- :mod:`~physcene.train.decode.merge`: a LoRA policy's adapters merged into a decoding copy of each
  projection's weight (one matmul per projection; PADA's ``pada.merge_adapters``).
- :mod:`~physcene.train.decode.shards`: the constraint's host check spread over worker processes
  (PADA's ``pada.constraint_workers``).

The generation ``cache`` settings that select it (:data:`FAST_CACHES`): ``fast`` plus ``+fused``
and/or ``+cudnn`` / ``+matmul`` / ``+flex``, e.g. ``cache: fast+fused+cudnn``.

:func:`fast_generate` is the entry point: it switches the model to eval mode (no dropout, LoRA's
included) and to the folded attention for the call, and restores both afterwards.
"""

from __future__ import annotations

import contextlib
import logging
import weakref

import torch

from physcene.train.decode.attention import (
    ATTENTIONS,
    FOLDED_ATTENTION,
    flex_decode_attention,
    folded_cudnn_attention,
    folded_gqa_attention,
    folded_matmul_attention,
    register_folded_attention,
)
from physcene.train.decode.cache import StaticKV
from physcene.train.decode.fuse import compiled_layers, fused_layers
from physcene.train.decode.loop import DecodeResult, FastDecoder, cut_at_eos, text_model
from physcene.train.decode.merge import lora_projections, merged_lora
from physcene.train.decode.overlap import OverlappedConstraint
from physcene.train.decode.shards import ShardedConstraint, constraint_pool

__all__ = ["ATTENTIONS", "FAST_CACHES", "FOLDED_ATTENTION", "DecodeResult", "FastDecoder",
           "OverlappedConstraint", "ShardedConstraint", "StaticKV", "compiled_layers", "constraint_pool",
           "cut_at_eos", "decoder_for", "fast_generate", "flex_decode_attention", "folded_cudnn_attention",
           "folded_gqa_attention", "folded_matmul_attention", "fused_layers", "lora_projections",
           "merged_lora", "register_folded_attention", "sampling_mode", "text_model"]

logger = logging.getLogger(__name__)

FAST_CACHES = {"fast" + ("+fused" if fuse else "") + ("" if attention == "sdpa" else f"+{attention}"):
               (attention, fuse) for fuse in (False, True) for attention in ATTENTIONS}
"""The generation ``cache`` settings of the fast decoder -> (attention, fused layers): ``fast`` (the folded
sdpa attention, eager layers: HF generate's ids), ``+cudnn`` / ``+matmul`` / ``+flex`` another decoding
attention, ``+fused`` the compiled layers (:mod:`~physcene.train.decode.fuse`)."""

# model -> {(batch, length, graphs, attention, fuse): decoder}
_DECODERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_KEPT_SHARE = 0.25  # a decoder whose cache takes more of the GPU is dropped after its call (an 8B model's)
_KEPT_BYTES_CPU = 4 << 30


@contextlib.contextmanager
def sampling_mode(model: torch.nn.Module, attention: str = "sdpa"):
    """The model in eval mode (dropout off: attention, LoRA) with the folded GQA attention ``attention``
    (:data:`ATTENTIONS`) on its text model, restored on exit."""
    text = text_model(model)
    training = model.training
    previous = text.config._attn_implementation
    switched = False
    model.eval()
    try:
        folded = {name for name, _ in ATTENTIONS.values()}
        if (previous == "sdpa" or previous in folded) and hasattr(text, "set_attn_implementation"):
            try:
                text.set_attn_implementation(register_folded_attention(attention))
                switched = True
            except (ValueError, KeyError, AttributeError) as error:  # an older transformers: plain sdpa
                logger.warning("folded GQA attention not set (%s): decoding with %s", error, previous)
        yield model
    finally:
        if switched:
            text.set_attn_implementation(previous)
        model.train(training)


def decoder_for(model: torch.nn.Module, batch: int, length: int, graphs: bool = True,
                attention: str = "sdpa", fuse: bool = False, merge: bool = False) -> FastDecoder:
    """The model's :class:`FastDecoder` for ``batch`` rows x ``length`` columns (made once, kept while
    the model lives unless its cache takes over a quarter of the GPU's memory (4 GiB on CPU): training
    needs it back; another shape replaces it). ``merge``: its calls run under :func:`merged_lora`."""
    kept = _DECODERS.setdefault(model, {})
    # a graph bakes these in
    key = (int(batch), int(length), bool(graphs), attention, bool(fuse), bool(merge))
    decoder = kept.get(key)
    if decoder is None:
        kept.clear()  # one shape at a time: PADA's rounds and eval's batches keep theirs
        decoder = FastDecoder(model, batch=batch, length=length, graphs=graphs, attention=attention,
                              fuse=fuse)
        device = decoder.device
        limit = (_KEPT_SHARE * torch.cuda.get_device_properties(device).total_memory
                 if device.type == "cuda" else _KEPT_BYTES_CPU)
        if decoder.cache.bytes_per_column() * batch * length <= limit:
            kept[key] = decoder
    return decoder


@torch.no_grad()
def fast_generate(model: torch.nn.Module, input_ids: torch.Tensor, attention_mask: torch.Tensor, *,
                  max_new_tokens: int, eos: list[int], pad: int, min_new_tokens: int = 0,
                  warpers=None, sampling: bool = False, constraint=None, length: int | None = None,
                  graphs: bool = True, attention: str = "sdpa", fuse: bool = False,
                  merge_lora: bool = False, constraint_workers: int = 0) -> DecodeResult:
    """Completions of left-padded prompts with the fast decoder.

    ``sampling`` with ``warpers`` (temperature/top-k/top-p as transformers' warpers,
    :func:`~physcene.train.constrained.sampling_warpers`) or greedy; ``constraint``: a
    :class:`~physcene.train.constrained.CTRCConstraint` built for these rows. ``length``: the cache's
    columns (default: this prompt length + ``max_new_tokens``); pass one value for calls of varying
    prompt length so one decoder and its graphs serve them all. ``attention``: ``sdpa`` (the folded
    query heads through torch's sdpa: HF generate's numbers), ``matmul`` (two batched matmuls; see
    :func:`~physcene.train.decode.attention.folded_matmul_attention`) or ``flex`` (torch's FlexAttention,
    a split-KV kernel on a GPU: :func:`~physcene.train.decode.attention.flex_decode_attention`).
    ``fuse``: the decoder layers compiled (:func:`~physcene.train.decode.fuse.fused_layers`; not bitwise
    eager). ``merge_lora``: a LoRA model decodes with its adapters merged into a copy of each projection's
    weight (:func:`~physcene.train.decode.merge.merged_lora`; not bitwise the unmerged model).
    ``constraint_workers``: the constraint's host check spread over that many worker processes
    (:mod:`~physcene.train.decode.shards`; 0: in this process). The same tokens either way.
    """
    batch, prompt = input_ids.shape
    length = max(int(length or 0), prompt + int(max_new_tokens))
    if attention not in ATTENTIONS:
        raise ValueError(f"fast decoding attention {attention!r}: expected one of {', '.join(ATTENTIONS)}")
    decoder = decoder_for(model, batch, length, graphs, attention, fuse, merge_lora)
    overlapped = None
    if constraint is not None:
        # a refused draw's redraw is seeded per (call, row, position): any number of workers, one result
        seed = int(torch.randint(0, 2**62, (1,)).item()) if sampling else 0
        kwargs = dict(max_new_tokens=max_new_tokens, eos=eos, warpers=warpers if sampling else None,
                      seed=seed)
        if constraint_workers > 0:
            pool = constraint_pool(constraint.tokenizer, int(constraint_workers))
            overlapped = ShardedConstraint(constraint, pool=pool, **kwargs)
        else:
            overlapped = OverlappedConstraint(constraint, **kwargs)
    merging = merged_lora(model) if merge_lora else contextlib.nullcontext(0)
    with sampling_mode(model, attention), merging as merged:
        result = decoder.generate(input_ids, attention_mask, max_new_tokens=max_new_tokens, eos=eos, pad=pad,
                                  min_new_tokens=min_new_tokens, sampling=sampling, warpers=warpers,
                                  constraint=overlapped)
    result.merged_projections = merged
    return result
