"""The ``model:PATH`` generator: a checkpoint trained with ``physcene train`` (or a local Qwen3 /
Qwen3-VL checkpoint with a chat template), decoded under the CTRC constraint.

The prompt is the CTRC generation prompt (:func:`physcene.ctrc.build_prompt`) with the instruction,
the table type, the zone and the object list of the procedural plan; decoding is constrained
(:mod:`physcene.train.constrained`: the grammar, the listed objects and the completion's own plan),
so every completion parses. One sample is decoded at a time under a progress bar; with more than one
sample they are drawn (temperature ``temperature``), one seed each, else greedy. ``physcene.train``
(transformers) is imported when the generator runs, never at import.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from tqdm.auto import tqdm

from physcene.generation.procedural import GenerationError

__all__ = ["model_completions"]


def model_completions(path, prompts: Sequence[str], *, max_new_tokens: int = 4096, temperature: float = 0.7,
                      seed: int = 0, device: str | None = None, progress: bool = True) -> list[str]:
    """One CTRC completion per prompt from the checkpoint at ``path``; a missing or unreadable
    checkpoint is one :class:`GenerationError`."""
    folder = Path(path)
    if not folder.is_dir():
        raise GenerationError(f"generator model:{path}: no such checkpoint directory "
                              "(train one with `physcene train sft`, or name a local Qwen3 checkpoint)")
    try:
        # transformers and the trained-model code load only when this generator runs
        from physcene.train.generate import generate_with, load_for_generation
    except ImportError as exc:
        raise GenerationError(f"generator model:{path}: the training extras are not installed "
                              f"({exc})") from None
    try:
        model, tokenizer, info = load_for_generation(folder, device=device)
    except (OSError, ValueError) as exc:
        raise GenerationError(f"generator model:{path}: cannot load the checkpoint ({exc})") from None
    chat = bool(info.get("chat_format", not info and tokenizer.chat_template is not None))
    physics = bool(info.get("physics_conditioned", False))
    sample = len(prompts) > 1
    out = []
    for k, prompt in enumerate(tqdm(prompts, desc="model", unit="scene", disable=not progress)):
        out += generate_with(model, tokenizer, [prompt], chat_format=chat, physics=physics,
                             max_new_tokens=max_new_tokens,
                             batch_size=1, do_sample=sample, temperature=temperature, seed=seed + k,
                             constrained=True)
    return out
