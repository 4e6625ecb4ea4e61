"""Fused decoding layers: each decoder layer's pointwise work compiled by torch's inductor.

A decoding step of a small model is not bound by its arithmetic but by how many kernels it launches:
a Qwen3 layer run eagerly is about 55 of them (each RMSNorm six, the rotary embedding ten, the
residual adds, the SwiGLU product), so at 8 layers a step costs ~2.8 ms on an H100 whatever the batch
(``physcene bench generate``'s figures at 128 and 512 rows, docs/training.md "Generation speed").
:func:`fused_layers` compiles the decoder layer's ``forward`` (one compiled function per layer class,
shared by every layer: parameters are its inputs) with the KV-cache write and the attention left
outside the compiled graphs (:data:`EAGER`: they read a bucketed cache length that changes during a
call), so the norms, projections, rotary embedding and MLP around them become a few fused kernels.
The CUDA graphs of :class:`~physcene.train.decode.loop.FastDecoder` then capture those kernels.

Not bitwise eager: inductor reduces an RMSNorm in another order, which in bf16 can flip a greedy
near-tie (``physcene bench generate --model small-sft`` measures the share of rows kept).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import types

import torch

__all__ = ["EAGER", "compiled_layers", "decoder_layers", "fused_layers"]

logger = logging.getLogger(__name__)


def EAGER(function):  # noqa: N802 - a decorator named like the constant it stands for
    """``function`` run outside any compiled graph (a graph break where a fused layer calls it); applied
    where it is used, not at import (the wrapper imports torch._dynamo: a second)."""
    return torch.compiler.disable(function, recursive=True)


def decoder_layers(text: torch.nn.Module) -> list[torch.nn.Module]:
    """The decoder layers of a transformers text model (``.layers`` of it or of its ``.model``)."""
    layers = getattr(text, "layers", None)
    if layers is None:
        layers = getattr(getattr(text, "model", None), "layers", None)
    if not isinstance(layers, torch.nn.ModuleList) or not len(layers):
        raise ValueError(f"{type(text).__name__} has no decoder layers (.layers) to fuse")
    return list(layers)


@functools.cache
def _compiled_forward(layer_class: type, dynamic: bool | None = None, backend: str = "inductor"):
    # decoding: dynamic=None, the mask's read length specialised once, then made symbolic (one
    # recompile); the update's passes (compiled_layers): dynamic=True, every length one graph
    compiled = torch.compile(layer_class.forward, fullgraph=False, dynamic=dynamic, backend=backend)

    @functools.wraps(layer_class.forward)
    def forward(self, *args, **kwargs):
        # integer module attributes (``layer_idx``) as inputs, not constants: one compiled function for
        # every layer instead of one per layer (which would pass dynamo's recompile limit at 8 layers)
        with torch._dynamo.config.patch(allow_unspec_int_on_nn_module=True):
            return compiled(self, *args, **kwargs)

    return forward


@contextlib.contextmanager
def compiled_layers(text: torch.nn.Module, dynamic: bool | None = None, backend: str = "inductor"):
    """Within the block, every decoder layer of ``text`` runs its ``forward`` compiled (one compiled
    function per layer class and setting, shared by every layer: regional compilation, a layer's compile
    instead of the whole model's); restored on exit. A backward run after the block runs the compiled
    backward its forward recorded."""
    layers = decoder_layers(text)
    patched = []
    try:
        for layer in layers:
            if "forward" in vars(layer):  # already compiled (a nested call) or patched by someone else
                continue
            layer.forward = types.MethodType(_compiled_forward(type(layer), dynamic, backend), layer)
            patched.append(layer)
        yield text
    finally:
        for layer in patched:
            del layer.forward


def fused_layers(text: torch.nn.Module):
    """Within the block, every decoder layer of ``text`` runs its compiled ``forward`` (the decoding
    setting of :func:`compiled_layers`); restored on exit (training and HF ``generate`` see the model as
    it was)."""
    return compiled_layers(text)
