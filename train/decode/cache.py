"""The static KV cache of the fast decoder: one preallocated ``[B, Hkv, L, D]`` buffer per layer and
per-row write positions, so a decoding step has fixed shapes (a CUDA graph replays it) and rows may
stand still for a step (the constraint's repair, :mod:`physcene.train.decode.loop`)."""

from __future__ import annotations

import torch

from physcene.train.decode.fuse import EAGER

__all__ = ["StaticKV"]


class StaticKV:
    """What the model's attention layers call: ``update(key, value, layer_idx, ...)`` stores the new
    keys/values and returns the keys/values to attend to.

    A prompt pass (``T > 1`` new positions) writes columns ``[0, T)`` of every row and returns them;
    a decoding step (``T == 1``) writes column ``positions[b]`` of row ``b`` (``positions``: a device
    tensor the decoder owns) and returns the first ``read_length`` columns (the decoder keeps it at
    or past every row's position: attention reads only what has been written, plus the mask's
    padding). Columns never written are zero (finite: a masked key must not turn a score into NaN).
    Duck-typed for transformers' Qwen3 / Qwen3-VL text layers (``update``, ``get_seq_length``).
    """

    def __init__(self, layers: int, batch: int, kv_heads: int, length: int, head_dim: int, *,
                 dtype: torch.dtype, device: torch.device, positions: torch.Tensor):
        self.shape = (batch, kv_heads, length, head_dim)
        # not ``dtype``: accelerate's mixed-precision forward wrapper casts every output that has a
        # bf16 ``dtype`` to float32, this cache included (StaticKV has no ``.float()``)
        self.kv_dtype, self.device = dtype, device
        # allocated by the first prompt pass in the dtypes the layers produce (under autocast keys
        # and values can differ from the weights and from each other); later writes are cast to them
        self.keys: list[torch.Tensor | None] = [None] * layers
        self.values: list[torch.Tensor | None] = [None] * layers
        self.positions = positions
        self.allocations = 0
        self.length = length
        self.read_length = length
        self.seen = 0  # columns filled by the prompt pass (host-side, for get_seq_length)
        if "update" not in StaticKV.__dict__:
            # outside fused layers' compiled graphs (train/decode/fuse.py): a step reads the host's
            # read_length. Set on the class on first use (the wrapper imports torch._dynamo), not on the
            # instance: a bound method kept on the instance is a reference cycle, which held every
            # dropped decoder's buffers until the garbage collector's next full pass (a CPU decode of
            # batches whose caches are not kept grew by one cache per batch)
            StaticKV.update = EAGER(StaticKV._update)

    def _update(self, key: torch.Tensor, value: torch.Tensor, layer_idx: int, *args, **kwargs):
        k, v = self.keys[layer_idx], self.values[layer_idx]
        new = key.shape[2]
        if k is None or new > 1 and (k.dtype != key.dtype or v.dtype != value.dtype):
            k = self.keys[layer_idx] = torch.zeros(self.shape, dtype=key.dtype, device=self.device)
            v = self.values[layer_idx] = torch.zeros(self.shape, dtype=value.dtype, device=self.device)
            self.allocations += 1  # graphs captured on the old buffers are void
        if new > 1:
            k[:, :, :new].copy_(key)
            v[:, :, :new].copy_(value)
            self.seen = new
            return k[:, :, :new], v[:, :, :new]
        index = self.positions.view(-1, 1, 1, 1).expand(-1, key.shape[1], 1, key.shape[3])
        k.scatter_(2, index, key.to(k.dtype))
        v.scatter_(2, index, value.to(v.dtype))
        return k[:, :, :self.read_length], v[:, :, :self.read_length]

    def get_seq_length(self, layer_idx: int = 0) -> int:
        return self.seen

    def bytes_per_column(self) -> int:
        """KV bytes of one column (one token of one row) over all layers."""
        size = self.keys[0].element_size() if self.keys[0] is not None else self.kv_dtype.itemsize
        return 2 * len(self.keys) * self.shape[1] * self.shape[3] * size
