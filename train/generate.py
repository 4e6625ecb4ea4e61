"""Batched text generation with a trained checkpoint: anchors, eval's ``model:PATH`` generator, ablations.

``generate(model_path, prompts)`` loads a plain checkpoint or a PEFT adapter directory (the adapter
is merged into its base for speed), feeds the prompts the way the checkpoint was trained (chat
template or plain text, from its ``physcene_run.json``), and returns the completion strings only.
Prompts are sorted by length before batching so left padding stays small.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import torch
from physcene.train.models import TrainingSetupError, load_model, load_tokenizer, read_run_info, torch_dtype
from transformers import PreTrainedModel, PreTrainedTokenizerBase

__all__ = ["generate", "generate_with", "load_for_generation"]


def load_for_generation(model_path: str | Path, device: str | torch.device | None = None,
                        dtype: str | None = None) -> tuple[PreTrainedModel, PreTrainedTokenizerBase, dict]:
    """(model in eval mode on ``device``, left-padding tokenizer, run info) for ``model_path``."""
    path = Path(model_path)
    if not path.is_dir():
        raise TrainingSetupError(f"model path {str(path)!r} is not a directory")
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if dtype is None:
        dtype = "bfloat16" if device.type == "cuda" else "float32"
    info = read_run_info(path)
    adapter = path / "adapter_config.json"
    if adapter.is_file():
        from peft import PeftModel

        base_path = json.loads(adapter.read_text())["base_model_name_or_path"]
        model = PeftModel.from_pretrained(load_model(base_path, dtype=dtype), str(path)).merge_and_unload()
        if not info:
            info = read_run_info(base_path)
    else:
        model = load_model(path, dtype=dtype)
    model.to(device).eval()
    return model, load_tokenizer(path), info


def _render(tokenizer: PreTrainedTokenizerBase, prompt: str, chat_format: bool) -> str:
    if not chat_format:
        return prompt
    return tokenizer.apply_chat_template([{"role": "user", "content": prompt}], tokenize=False,
                                         add_generation_prompt=True)


@torch.no_grad()
def generate_with(model: PreTrainedModel, tokenizer: PreTrainedTokenizerBase, prompts: Sequence[str], *,
                  chat_format: bool = False, max_new_tokens: int = 1024, batch_size: int = 16,
                  do_sample: bool = False, temperature: float = 1.0, seed: int = 0) -> list[str]:
    """Completions (decoded, special tokens dropped) of ``prompts`` with a loaded model, in input order."""
    if batch_size < 1 or max_new_tokens < 1:
        raise ValueError(f"batch_size and max_new_tokens must be >= 1, got {batch_size}, {max_new_tokens}")
    torch.manual_seed(seed)
    device = next(model.parameters()).device
    texts = [_render(tokenizer, p, chat_format) for p in prompts]
    order = sorted(range(len(texts)), key=lambda i: len(texts[i]))
    out: list[str] = [""] * len(texts)
    tokenizer.padding_side = "left"
    for start in range(0, len(order), batch_size):
        idx = order[start:start + batch_size]
        enc = tokenizer([texts[i] for i in idx], return_tensors="pt", padding=True,
                        add_special_tokens=False).to(device)
        kwargs = {"do_sample": do_sample, "max_new_tokens": max_new_tokens,
                  "pad_token_id": tokenizer.pad_token_id, "eos_token_id": tokenizer.eos_token_id}
        if do_sample:
            kwargs["temperature"] = temperature
        ids = model.generate(**enc, **kwargs)[:, enc["input_ids"].shape[1]:]
        for i, row in zip(idx, ids):
            out[i] = tokenizer.decode(row, skip_special_tokens=True)
    return out


def generate(model_path: str | Path, prompts: Sequence[str], *, max_new_tokens: int = 1024,
             batch_size: int | None = None, do_sample: bool = False, temperature: float = 1.0, seed: int = 0,
             device: str | torch.device | None = None, dtype: str | None = None) -> list[str]:
    """Completions of ``prompts`` by the checkpoint at ``model_path`` (greedy unless ``do_sample``).

    ``prompts`` are CTRC prompt strings (``physcene.ctrc.build_prompt``); chat-format checkpoints get
    them wrapped in a user turn. ``batch_size`` defaults to the checkpoint's ``eval_batch_size``
    (its training config's ``eval.batch_size``; 16 for foreign checkpoints). Returns one completion
    string per prompt, in order.
    """
    if dtype is not None:
        torch_dtype(dtype)  # validate early
    model, tokenizer, info = load_for_generation(model_path, device=device, dtype=dtype)
    batch_size = batch_size or int(info.get("eval_batch_size", 16))
    return generate_with(model, tokenizer, prompts, chat_format=bool(info.get("chat_format", False)),
                         max_new_tokens=max_new_tokens, batch_size=batch_size, do_sample=do_sample,
                         temperature=temperature, seed=seed)
