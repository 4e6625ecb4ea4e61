"""LoRA adapters merged for decoding: each adapted projection one matmul, the trained weights untouched.

A PEFT LoRA projection runs its base matmul, then ``lora_B(lora_A(dropout(x))) * scaling`` and the
add: three matmuls and a few pointwise kernels where the base model has one matmul. A decoding step
of a small model is bound by how many kernels it launches (:mod:`~physcene.train.decode.fuse`), and
PADA decodes through the policy's adapters at every rollout step: ``small``'s 56 adapted projections
add about 170 kernels to a step.

:func:`merged_lora` gives each plain LoRA projection (``peft``'s ``lora.Linear`` over an
``nn.Linear``, no DoRA or other variant, no LoRA bias) a decoding weight ``W + Σ scaling·B·A`` of its
active adapters, computed in float32 and rounded once, and runs the projection as one ``F.linear``
with it inside the block. PEFT's ``merge_adapter`` / ``unmerge_adapter`` would add the delta to the
base weight and subtract it again, which in bf16 does not give the base weight back: over an RL run of
hundreds of rounds the frozen base would drift. Here the base weight is only read.

The decoding weight of each projection is kept between calls (one buffer per projection, rewritten in
place at every call): a CUDA graph captured on it reads the current adapter's weights at its next
replay. Memory: one copy of the adapted projections' weights (``small``: 19 M parameters, 38 MB in
bf16; an 8B model's seven projections per layer: about 13 GB).

Not bitwise the unmerged model: ``(W + BA)x`` rounds once where ``Wx + B(Ax)`` rounds per matmul, as
a vLLM server sampling from merged weights does.
"""

from __future__ import annotations

import contextlib
import types

import torch
import torch.nn.functional as F

__all__ = ["lora_projections", "merged_lora"]

_WEIGHT = "_physcene_decoding_weight"  # the module attribute holding a projection's merged weight


def lora_projections(model: torch.nn.Module) -> list[torch.nn.Module]:
    """The projections of ``model`` whose adapters :func:`merged_lora` merges: PEFT ``lora.Linear``
    modules over an ``nn.Linear`` with plain LoRA adapters active (no DoRA or other variant, no LoRA
    bias), adapters enabled and not already merged."""
    try:
        from peft.tuners.lora.layer import Linear as LoraLinear
    except ImportError:  # no peft: no adapters
        return []
    found = []
    for module in model.modules():
        if not isinstance(module, LoraLinear) or module.merged or module.disable_adapters:
            continue
        if not isinstance(module.get_base_layer(), torch.nn.Linear):
            continue
        active = [a for a in module.active_adapters if a in module.lora_A]
        if not active or any(a in module.lora_variant or module.lora_bias.get(a, False) for a in active):
            continue
        found.append(module)
    return found


def _merged_forward(self, x: torch.Tensor, *args, **kwargs) -> torch.Tensor:
    return F.linear(x, getattr(self, _WEIGHT), self.get_base_layer().bias)


@torch.no_grad()
def _refresh(module: torch.nn.Module) -> None:
    """Write ``W + Σ scaling·B·A`` of the module's active adapters into its decoding weight (made once)."""
    weight = module.get_base_layer().weight
    merged = getattr(module, _WEIGHT, None)
    if merged is None or merged.shape != weight.shape or merged.dtype != weight.dtype \
            or merged.device != weight.device:
        merged = torch.empty_like(weight)
        object.__setattr__(module, _WEIGHT, merged)  # a plain attribute: not a buffer, not saved
    total = weight.float()
    for adapter in module.active_adapters:
        if adapter in module.lora_A:
            total = total + module.get_delta_weight(adapter).float()
    merged.copy_(total)


@contextlib.contextmanager
def merged_lora(model: torch.nn.Module):
    """Within the block, every projection of :func:`lora_projections` runs one matmul with its merged
    decoding weight (refreshed on entry from the current adapter weights); restored on exit. Yields the
    number of projections merged (0: a model without adapters runs as it is)."""
    patched = []
    try:
        for module in lora_projections(model):
            _refresh(module)
            module.forward = types.MethodType(_merged_forward, module)
            patched.append(module)
        yield len(patched)
    finally:
        for module in patched:
            del module.forward
