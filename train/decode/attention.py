"""GQA attention without K/V expansion: the query heads of each KV head folded into the query axis.

transformers' sdpa path repeats K and V from ``num_key_value_heads`` to ``num_attention_heads`` in
every layer at every decoding step when a padding mask is present (``repeat_kv``: the whole cache
copied, ~28 GB of memory traffic per step at 256 rows of the ``small`` config). Folding the G query
heads that share a KV head into the query axis (q: ``[B, Hkv, G * Tq, D]`` against k, v:
``[B, Hkv, L, D]``) reads the cache once and gives the same logits: each query row meets the same
keys, values, mask and scale as under the repeat.

:data:`FOLDED_ATTENTION` is registered with transformers' ``AttentionInterface`` (and its mask
interface, as sdpa's mask) by :func:`register_folded_attention`, so ``model.set_attn_implementation``
takes it and HF ``generate`` runs with it as well.
"""

from __future__ import annotations

import functools

import torch

from physcene.train.decode.fuse import EAGER

__all__ = ["ATTENTIONS", "CUDNN_ATTENTION", "FLEX_ATTENTION", "FOLDED_ATTENTION", "MATMUL_ATTENTION",
           "flex_decode_attention", "fold_queries", "folded_cudnn_attention", "folded_gqa_attention",
           "folded_matmul_attention", "register_folded_attention"]

FOLDED_ATTENTION = "sdpa_folded_gqa"
CUDNN_ATTENTION = "cudnn_folded_gqa"
MATMUL_ATTENTION = "matmul_folded_gqa"
FLEX_ATTENTION = "flex_decode_gqa"


def fold_queries(query: torch.Tensor, groups: int) -> torch.Tensor:
    """``[B, H, Tq, D]`` -> ``[B, Hkv, G * Tq, D]``: query head ``h = kv * G + g`` (``repeat_kv``'s order)
    becomes rows ``g * Tq .. g * Tq + Tq - 1`` of KV head ``kv``."""
    b, h, t, d = query.shape
    return query.reshape(b, h // groups, groups * t, d)


def _fold_mask(mask: torch.Tensor | None, groups: int, q_length: int) -> torch.Tensor | None:
    """A ``[B, 1 | H, Tq, L]`` mask for the folded query axis (``[B, 1 | Hkv, G * Tq, L]``)."""
    if mask is None or mask.shape[-2] == 1 and mask.shape[1] == 1:
        return mask  # one row per batch entry: broadcasts over the folded axis
    b, h, t, kv = mask.shape
    if h == 1:
        mask = mask.expand(b, 1, q_length, kv)
        return mask[:, :, None].expand(b, 1, groups, q_length, kv).reshape(b, 1, groups * q_length, kv)
    return mask.reshape(b, h // groups, groups * t, kv)


def folded_gqa_attention(module: torch.nn.Module, query: torch.Tensor, key: torch.Tensor,
                         value: torch.Tensor, attention_mask: torch.Tensor | None, dropout: float = 0.0,
                         scaling: float | None = None, is_causal: bool | None = None,
                         **kwargs) -> tuple[torch.Tensor, None]:
    """transformers' attention-function signature (``sdpa_attention_forward``'s); returns
    ``([B, Tq, H, D], None)``. Decoding steps (``Tq == 1``) fold the query heads; prompt passes
    (``Tq > 1``, once per call) take transformers' own sdpa function."""
    groups = getattr(module, "num_key_value_groups", 1)
    q_length = query.shape[2]
    if groups == 1 or q_length > 1 or kwargs.get("position_bias") is not None:
        from transformers.integrations.sdpa_attention import sdpa_attention_forward

        return sdpa_attention_forward(module, query, key, value, attention_mask, dropout=dropout,
                                      scaling=scaling, is_causal=is_causal, **kwargs)
    batch, heads = query.shape[:2]
    out = torch.nn.functional.scaled_dot_product_attention(
        fold_queries(query, groups), key, value, attn_mask=_fold_mask(attention_mask, groups, q_length),
        dropout_p=dropout, scale=scaling, is_causal=False)
    # [B, Hkv, G, Dv] -> [B, 1, H, Dv]: the layout sdpa_attention_forward returns
    return out.reshape(batch, heads, 1, value.shape[-1]).transpose(1, 2).contiguous(), None


def folded_cudnn_attention(module: torch.nn.Module, query: torch.Tensor, key: torch.Tensor,
                           value: torch.Tensor, attention_mask: torch.Tensor | None, dropout: float = 0.0,
                           scaling: float | None = None, is_causal: bool | None = None,
                           **kwargs) -> tuple[torch.Tensor, None]:
    """:func:`folded_gqa_attention` with torch's cuDNN attention kernel allowed for the decoding steps.

    Training forbids that kernel (:func:`physcene.train.models.set_attention_kernels`: its backward
    writes NaN where a query row attends to nothing); a decoding step has no backward and every row
    attends at least to its own column. On an H100 at 512 rows x 1,024 columns the cuDNN kernel reads
    the cache in 2.06 ms a step where the memory-efficient one, which HF generate takes under that
    setting, needs about 2.9 (``benchmarks/decode_step_profile.py``). Not bitwise the memory-efficient
    kernel's (another reduction order); prompt passes as :func:`folded_gqa_attention`."""
    if not (query.is_cuda and _decoding_step(module, query, dropout, kwargs)):
        return folded_gqa_attention(module, query, key, value, attention_mask, dropout=dropout,
                                    scaling=scaling, is_causal=is_causal, **kwargs)
    from torch.nn.attention import SDPBackend, sdpa_kernel

    with sdpa_kernel([SDPBackend.CUDNN_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH],
                     set_priority=True):
        return folded_gqa_attention(module, query, key, value, attention_mask, dropout=dropout,
                                    scaling=scaling, is_causal=is_causal, **kwargs)


def folded_matmul_attention(module: torch.nn.Module, query: torch.Tensor, key: torch.Tensor,
                            value: torch.Tensor, attention_mask: torch.Tensor | None, dropout: float = 0.0,
                            scaling: float | None = None, is_causal: bool | None = None,
                            **kwargs) -> tuple[torch.Tensor, None]:
    """The folded decoding step as two batched matmuls (scores in float32, softmax, then the values):
    cuBLAS spreads the cache read over the whole GPU where sdpa's memory-efficient kernel gives each
    (row, KV head) one block. Not bitwise sdpa's (another reduction order); prompt passes as
    :func:`folded_gqa_attention`."""
    groups = getattr(module, "num_key_value_groups", 1)
    if not _decoding_step(module, query, dropout, kwargs):
        return folded_gqa_attention(module, query, key, value, attention_mask, dropout=dropout,
                                    scaling=scaling, is_causal=is_causal, **kwargs)
    batch, heads, _, dim = query.shape
    scale = scaling if scaling is not None else dim ** -0.5
    scores = _float_scores(fold_queries(query, groups), key.transpose(-1, -2)) * scale  # [B, Hkv, G, L]
    mask = _fold_mask(attention_mask, groups, 1)
    if mask is not None:
        scores = scores.masked_fill(~mask, float("-inf")) if mask.dtype == torch.bool else scores + mask
    out = torch.matmul(scores.softmax(dim=-1).to(value.dtype), value)
    return out.reshape(batch, heads, 1, value.shape[-1]).transpose(1, 2).contiguous(), None


def _decoding_step(module: torch.nn.Module, query: torch.Tensor, dropout: float, kwargs: dict) -> bool:
    """A step the alternative decoding attentions compute: one query position, no position bias, no
    dropout in training (anything else goes to :func:`folded_gqa_attention`)."""
    return query.shape[2] == 1 and kwargs.get("position_bias") is None and not (dropout and module.training)


_FLOAT_SCORES: dict[str, bool] = {}


def _float_scores(q: torch.Tensor, k_t: torch.Tensor) -> torch.Tensor:
    """``q @ k_t`` in float32 from bf16/fp16 operands without a float32 copy of the cache (``bmm``'s
    ``out_dtype`` on CUDA where this torch has it, else the half-precision product upcast)."""
    if q.dtype == torch.float32:
        return torch.matmul(q, k_t)
    lead = q.shape[:-2]
    q3, k3 = q.reshape(-1, *q.shape[-2:]), k_t.reshape(-1, *k_t.shape[-2:])
    if _FLOAT_SCORES.get(q.device.type, q.is_cuda):
        try:
            return torch.bmm(q3, k3, out_dtype=torch.float32).reshape(*lead, q.shape[-2], k_t.shape[-1])
        except (RuntimeError, TypeError):
            _FLOAT_SCORES[q.device.type] = False
    return torch.bmm(q3, k3).float().reshape(*lead, q.shape[-2], k_t.shape[-1])


def flex_decode_attention(module: torch.nn.Module, query: torch.Tensor, key: torch.Tensor,
                          value: torch.Tensor, attention_mask: torch.Tensor | None, dropout: float = 0.0,
                          scaling: float | None = None, is_causal: bool | None = None,
                          **kwargs) -> tuple[torch.Tensor, None]:
    """The decoding step through torch's FlexAttention: on a GPU its compiled form is flex-decoding, a
    split-KV Triton kernel that packs the query heads of each KV head (GQA without a K/V copy, as the
    fold does) and splits each row's cache over several blocks, so a few long rows still spread the
    read over the whole GPU (sdpa's memory-efficient kernel gives each (row, KV head) one block). The
    row's mask of written columns reaches it as a ``score_mod``. On a CPU it runs eagerly (the same
    arithmetic, for tests). Not bitwise sdpa's (another reduction order); prompt passes and masks
    that differ per head or query as :func:`folded_gqa_attention`."""
    groups = getattr(module, "num_key_value_groups", 1)
    per_row = attention_mask is None or attention_mask.shape[1] == 1 and attention_mask.shape[2] == 1
    if not (per_row and _decoding_step(module, query, dropout, kwargs)):
        return folded_gqa_attention(module, query, key, value, attention_mask, dropout=dropout,
                                    scaling=scaling, is_causal=is_causal, **kwargs)
    score_mod = None
    if attention_mask is not None:
        keep = attention_mask[:, 0, 0, :]
        if keep.dtype != torch.bool:  # an additive mask: 0 where attended, a large negative value elsewhere
            keep = keep > torch.finfo(keep.dtype).min / 2

        def score_mod(score, b, h, q_idx, kv_idx):
            return torch.where(keep[b, kv_idx], score, -float("inf"))

    out = _flex(query.device)(query, key, value, score_mod=score_mod, scale=scaling, enable_gqa=groups > 1)
    return out.transpose(1, 2).contiguous(), None  # [B, H, 1, D] -> [B, 1, H, D]


def _eager_flex(*args, **kwargs):
    """``flex_attention`` uncompiled, without its advice to compile (the CPU path is for tests)."""
    import warnings

    from torch.nn.attention.flex_attention import flex_attention

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="flex_attention called without torch.compile")
        return flex_attention(*args, **kwargs)


def _flex(device: torch.device):
    """``flex_attention``, compiled once per process on CUDA (uncompiled it falls back to a slow math
    path there); eager on other devices."""
    return _compiled_flex() if device.type == "cuda" else _eager_flex


@functools.cache
def _compiled_flex():
    from torch.nn.attention.flex_attention import flex_attention

    return torch.compile(flex_attention)  # shapes made dynamic after the first new length


ATTENTIONS = {"sdpa": (FOLDED_ATTENTION, folded_gqa_attention),
              "cudnn": (CUDNN_ATTENTION, folded_cudnn_attention),
              "matmul": (MATMUL_ATTENTION, folded_matmul_attention),
              "flex": (FLEX_ATTENTION, flex_decode_attention)}
"""The fast decoder's attention choices: name -> (registered name, function)."""


def register_folded_attention(kind: str = "sdpa") -> str:
    """Register the folded attention ``kind`` (:data:`ATTENTIONS`) with transformers (idempotent); its
    registered name."""
    from transformers import AttentionInterface
    from transformers.masking_utils import AttentionMaskInterface, sdpa_mask

    if kind not in ATTENTIONS:
        raise ValueError(f"fast decoding attention {kind!r}: expected one of {', '.join(ATTENTIONS)}")
    name, function = ATTENTIONS[kind]
    # outside the compiled graphs of fused layers (train/decode/fuse.py): the cache's read length varies
    AttentionInterface.register(name, EAGER(function))
    AttentionMaskInterface.register(name, sdpa_mask)
    return name
