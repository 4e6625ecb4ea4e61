"""Batched text generation with a trained checkpoint: anchors, eval's ``model:PATH`` generator, ablations.

``generate(model_path, prompts)`` loads a plain checkpoint or a PEFT adapter directory (the adapter
is merged into its base for speed), feeds the prompts the way the checkpoint was trained (chat
template or plain text, from its ``physcene_run.json``), and returns the completion strings only.
Prompts are sorted by length before batching so left padding stays small.

``cache`` picks the KV cache of HF ``generate`` (configs: ``anchors.cache``, ``eval.cache``,
``pada.cache``; docs/training.md "Generation speed"):

- ``dynamic``: ``DynamicCache`` (grows by concatenation every step; HF's default);
- ``static``: ``cache_implementation="static"`` with ``disable_compile`` (a preallocated cache,
  eager forward; transformers would otherwise auto-compile on CUDA);
- ``static_compile``: the static cache and HF's ``torch.compile``d decoding forward
  (``CompileConfig``, mode ``reduce-overhead`` = CUDA graphs on CUDA; also honoured on CPU);
- ``fast``: not HF ``generate`` but :mod:`physcene.train.decode` (folded GQA attention, a static
  cache read up to a bucketed length, decoding steps replayed as CUDA graphs, the CTRC constraint
  checked on the host while the GPU runs the next step, dropout off). HF ``generate`` stays the
  reference it is tested against.

For the static modes the cache is sized once for the longest prompt of the whole call plus
``max_new_tokens`` (``max_cache_len``) so every batch reuses one shape and one compiled graph.

``progress=True`` shows a bar on stderr advanced by the prompts of each decoded batch (``physcene
eval`` with a ``model:`` generator, unless ``--quiet``); it is off by default, for the callers that
decode inside their own loop (ablation, anchors, PADA, benchmarks).
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import torch
from tqdm.auto import tqdm
from transformers import CompileConfig, LogitsProcessorList, PreTrainedModel, PreTrainedTokenizerBase
from transformers.utils import logging as transformers_logging

from physcene.artifacts import checkpoint_digest
from physcene.ctrc.prompts import with_physics
from physcene.train.checkpoints import run_folder
from physcene.train.constrained import CTRCConstraint, sampling_warpers
from physcene.train.decode import FAST_CACHES
from physcene.train.models import (
    TrainingSetupError,
    load_model,
    load_tokenizer,
    read_run_info,
    recorded_base_digest,
    torch_dtype,
)

__all__ = ["CACHE_MODES", "cache_generate_kwargs", "check_cache", "generate", "generate_token_ids",
           "generate_with", "input_format", "load_for_generation", "longest_prompt_tokens", "render_prompt",
           "sampling",
           "set_trainer_cache"]

CACHE_MODES = ("dynamic", "static", "static_compile", *FAST_CACHES)
"""HF generate's KV caches (``dynamic``, ``static``, ``static_compile``) and the fast decoder's settings
(:data:`physcene.train.decode.FAST_CACHES`: ``fast``, ``fast+fused``, ``fast+flex``, ...)."""


def sampling(temperature: float) -> dict:
    """The ``do_sample`` / ``temperature`` arguments of the generate functions for an evaluation's
    ``temperature`` setting: 0 is greedy, a positive value samples at it."""
    return {"do_sample": temperature > 0, "temperature": temperature or 1.0}


def check_cache(cache: str) -> str:
    """``cache`` if it names one of :data:`CACHE_MODES`, else a :class:`TrainingSetupError` naming it."""
    if cache not in CACHE_MODES:
        raise TrainingSetupError(f"generation cache {cache!r}: expected one of {', '.join(CACHE_MODES)}")
    return cache


def cache_generate_kwargs(cache: str, device: str | torch.device = "cpu",
                          max_cache_len: int | None = None) -> dict:
    """``model.generate`` keyword arguments for a :data:`CACHE_MODES` entry.

    ``max_cache_len`` (tokens: longest prompt + max_new_tokens) sizes a static cache for every call.
    """
    check_cache(cache)
    if cache in FAST_CACHES:
        raise ValueError(f"cache {cache!r} is not an HF generate mode: generate_token_ids runs it itself")
    if cache == "dynamic":
        return {"cache_implementation": "dynamic"}
    kwargs: dict = {"cache_implementation": "static"}
    if max_cache_len is not None:
        kwargs["max_cache_len"] = int(max_cache_len)
    if cache == "static":
        kwargs["disable_compile"] = True  # transformers compiles a static-cache decode on CUDA by default
        return kwargs
    config = CompileConfig()
    if torch.device(device).type != "cuda":
        # transformers compiles on CUDA/XPU only unless told; honour an explicit request elsewhere
        config._compile_all_devices = True
    kwargs["compile_config"] = config
    kwargs["disable_compile"] = False
    return kwargs


def longest_prompt_tokens(tokenizer: PreTrainedTokenizerBase, prompts) -> int:
    """Tokens of the longest prompt as TRL feeds it (a conversational prompt through the chat template)."""
    texts = [p if isinstance(p, str) else
             tokenizer.apply_chat_template(p, tokenize=False, add_generation_prompt=True) for p in prompts]
    return max((len(ids) for ids in tokenizer(texts, add_special_tokens=False)["input_ids"]), default=0)


def set_trainer_cache(generation_config, *, static: bool, compiled: bool, tokenizer: PreTrainedTokenizerBase,
                      prompts, max_new_tokens: int, device: str | torch.device) -> None:
    """Fit a trainer's ``GenerationConfig`` to the :data:`CACHE_MODES` entry TRL was given.

    ``static``: one static cache size for the whole run (longest of ``prompts`` + ``max_new_tokens``):
    HF sizes it per call otherwise, and each longer batch would recompile the compiled decoding
    forward. ``compiled``: TRL builds its GenerationConfig with ``disable_compile=True``;
    ``static_compile`` turns HF's compiled static-cache decoding back on (the same CompileConfig as
    :func:`generate_token_ids`).
    """
    if static:
        generation_config.max_cache_len = longest_prompt_tokens(tokenizer, prompts) + max_new_tokens
    if compiled:
        generation_config.disable_compile = False
        generation_config.compile_config = cache_generate_kwargs("static_compile", device)["compile_config"]


def load_for_generation(model_path: str | Path, device: str | torch.device | None = None,
                        dtype: str | None = None, base: str | Path | None = None,
                        ) -> tuple[PreTrainedModel, PreTrainedTokenizerBase, dict]:
    """(model in eval mode on ``device``, left-padding tokenizer, run info) for ``model_path``. A LoRA
    adapter is merged into its base: ``base`` where given (:func:`adapter_base`; a full checkpoint
    ignores it), else the folder its ``adapter_config.json`` names; an adapter folder without a tokenizer
    (a curve point kept without one) takes its base's."""
    path = Path(model_path)
    if not path.is_dir():
        raise TrainingSetupError(f"model path {str(path)!r} is not a directory")
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if dtype is None:
        dtype = "bfloat16" if device.type == "cuda" else "float32"
    info = read_run_info(path)
    adapter = path / "adapter_config.json"
    tokenizer_path = path
    if adapter.is_file():
        from peft import PeftModel

        base_path = adapter_base(path, base)
        model = PeftModel.from_pretrained(load_model(base_path, dtype=dtype), str(path)).merge_and_unload()
        if not info:
            info = read_run_info(base_path)
        if not any((path / f).is_file() for f in ("tokenizer.json", "tokenizer_config.json")):
            tokenizer_path = Path(base_path)  # a curve point kept without it: LoRA leaves the base's as it is
    else:
        model = load_model(path, dtype=dtype)
    model.to(device).eval()
    return model, load_tokenizer(tokenizer_path), info


def adapter_base(adapter_dir: str | Path, base: str | Path | None = None) -> str:
    """The base model folder of the LoRA adapter at ``adapter_dir`` (a run's final adapter or one of
    its ``checkpoint-N``): ``base`` where given, checked against the base digest the run recorded
    (``base_sha256``, :func:`physcene.train.models.base_checked`); else the folder the adapter config
    names, which is the training host's path and need not exist where the adapter was carried to
    (an error then says to pass ``base``)."""
    folder = Path(adapter_dir)
    named = json.loads((folder / "adapter_config.json").read_text()).get("base_model_name_or_path") or ""
    recorded = recorded_base_digest(run_folder(folder))
    if base is None:
        if not named or not Path(named).is_dir():
            where = f"on the base {named!r}, which is not here" if named else "that names no base"
            raise TrainingSetupError(f"{folder}: a LoRA adapter {where}; pass the base it was trained on "
                                     f"(base=...{f', sha256 {recorded}' if recorded else ''})")
        return named
    if not (Path(base) / "config.json").is_file():
        raise TrainingSetupError(f"base {str(base)!r} for the adapter {folder} has no config.json")
    if recorded is not None and (digest := checkpoint_digest(base)) != recorded:
        raise TrainingSetupError(f"{folder} was trained on a base with sha256 {recorded}; {base} has sha256 "
                                 f"{digest}: pass the base it was trained on")
    return str(base)


def input_format(info: dict) -> dict:
    """``chat_format`` and ``physics`` (:func:`render_prompt`) of a checkpoint, from its run info."""
    return {"chat_format": bool(info.get("chat_format", False)),
            "physics": bool(info.get("physics_conditioned", False))}


def render_prompt(tokenizer: PreTrainedTokenizerBase, prompt: str, chat_format: bool,
                  physics: bool = False) -> str:
    """The prompt as the model reads it: the text itself, or the chat template's user turn; ``physics``:
    a physics-conditioned model's, asking for a collision-free layout (:func:`physcene.ctrc.with_physics`)."""
    if physics:
        prompt = with_physics(prompt)
    if not chat_format:
        return prompt
    return tokenizer.apply_chat_template([{"role": "user", "content": prompt}], tokenize=False,
                                         add_generation_prompt=True)


@torch.no_grad()
def generate_token_ids(model: PreTrainedModel, tokenizer: PreTrainedTokenizerBase, prompts: Sequence[str], *,
                       chat_format: bool = False, physics: bool = False, max_new_tokens: int = 1024,
                       batch_size: int = 16, do_sample: bool = False, temperature: float = 1.0, seed: int = 0,
                       cache: str = "dynamic", min_new_tokens: int | None = None,
                       constrained: bool = False, follow_plan: bool = True,
                       report: list | None = None, progress: bool = False,
                       merge_lora: bool = False) -> list[list[int]]:
    """Completion token ids of ``prompts`` (prompt and left padding cut off; each row is
    ``max_new_tokens`` long or ends in EOS + pad), in input order. ``chat_format``, ``physics``: how the
    model reads its prompts (:func:`render_prompt`; its run info says: :func:`input_format`).

    ``cache``: one of :data:`CACHE_MODES`. ``min_new_tokens`` forbids EOS before that many tokens
    (benchmarks force equal lengths with it). ``constrained``: decode under
    :class:`physcene.train.constrained.CTRCConstraint` (CTRC grammar + the prompt's Object List);
    ``follow_plan``: its layout follows the completion's own plan (order, parents, relations).
    ``report``: a list that the fast decoder (``cache="fast"``, ``"fast+fused"``, ...) appends each
    batch's :class:`~physcene.train.decode.DecodeResult` to (graphs used, bytes read, repairs, timings).
    ``progress``: a bar on stderr over the prompts, advanced as each batch is decoded. ``merge_lora``
    (fast caches): a LoRA model decodes with its adapters merged (:mod:`physcene.train.decode.merge`).
    """
    if batch_size < 1 or max_new_tokens < 1:
        raise ValueError(f"batch_size and max_new_tokens must be >= 1, got {batch_size}, {max_new_tokens}")
    check_cache(cache)
    torch.manual_seed(seed)
    texts = [render_prompt(tokenizer, p, chat_format, physics) for p in prompts]
    order = sorted(range(len(texts)), key=lambda i: len(texts[i]))
    tokenizer.padding_side = "left"
    encoded = [tokenizer([texts[i] for i in order[start:start + batch_size]], return_tensors="pt",
                         padding=True, add_special_tokens=False)
               for start in range(0, len(order), batch_size)]
    longest = max((enc["input_ids"].shape[1] for enc in encoded), default=0)
    options = dict(batch_size=batch_size, max_new_tokens=max_new_tokens, do_sample=do_sample,
                   temperature=temperature, constrained=constrained, follow_plan=follow_plan,
                   length=longest + max_new_tokens)
    with tqdm(total=len(prompts), desc="decode", unit="prompt", disable=not progress) as bar:
        if cache in FAST_CACHES:
            return _fast_token_ids(model, tokenizer, prompts, order, encoded, bar, **options,
                                   min_new_tokens=min_new_tokens or 0, report=report, cache=cache,
                                   merge_lora=merge_lora)
        return _hf_token_ids(model, tokenizer, prompts, order, encoded, bar, **options,
                             min_new_tokens=min_new_tokens, cache=cache)


def _hf_token_ids(model, tokenizer, prompts, order, encoded, bar, *, batch_size: int, max_new_tokens: int,
                  min_new_tokens: int | None, do_sample: bool, temperature: float, constrained: bool,
                  follow_plan: bool, length: int, cache: str) -> list[list[int]]:
    """:func:`generate_token_ids` with HF ``model.generate``, one call per batch of ``encoded``;
    ``bar`` advances by each batch's prompts."""
    device = next(model.parameters()).device
    kwargs = {"do_sample": do_sample, "max_new_tokens": max_new_tokens,
              "pad_token_id": tokenizer.pad_token_id, "eos_token_id": tokenizer.eos_token_id,
              **cache_generate_kwargs(cache, device, max_cache_len=length)}
    if do_sample:
        kwargs["temperature"] = temperature
    if min_new_tokens is not None:
        kwargs["min_new_tokens"] = int(min_new_tokens)
    warpers = None
    if constrained and do_sample:  # the warpers generate applies after the constraint, for its draws
        config = copy.deepcopy(model.generation_config)
        config.update(do_sample=True, temperature=temperature)
        warpers = sampling_warpers(config)
    out: list[list[int]] = [[] for _ in prompts]
    for k, enc in enumerate(encoded):
        idx = order[k * batch_size:(k + 1) * batch_size]
        enc = enc.to(device)
        if constrained:
            kwargs["logits_processor"] = LogitsProcessorList([CTRCConstraint(
                tokenizer, [prompts[i] for i in idx], greedy=not do_sample, warpers=warpers,
                follow_plan=follow_plan)])
        ids = model.generate(**enc, **kwargs)[:, enc["input_ids"].shape[1]:]
        for i, row in zip(idx, ids.tolist()):
            out[i] = row
        bar.update(len(idx))
    return out


def _fast_token_ids(model, tokenizer, prompts, order, encoded, bar, *, batch_size: int, max_new_tokens: int,
                    min_new_tokens: int, do_sample: bool, temperature: float, constrained: bool,
                    follow_plan: bool, length: int, report: list | None, cache: str,
                    merge_lora: bool = False) -> list[list[int]]:
    """:func:`generate_token_ids` with :func:`physcene.train.decode.fast_generate`: the same rows (EOS
    then padding up to the batch's longest completion, as HF ``generate`` returns them); ``bar``
    advances by each batch's prompts."""
    from physcene.train.decode import fast_generate

    attention, fuse = FAST_CACHES[cache]
    device = next(model.parameters()).device
    warpers = None
    if do_sample:
        config = copy.deepcopy(model.generation_config)
        config.update(do_sample=True, temperature=temperature)
        warpers = sampling_warpers(config) or LogitsProcessorList()
    out: list[list[int]] = [[] for _ in prompts]
    for k, enc in enumerate(encoded):
        idx = order[k * batch_size:(k + 1) * batch_size]
        rows = [prompts[i] for i in idx]
        constraint = (CTRCConstraint(tokenizer, rows, greedy=not do_sample, warpers=warpers,
                                     follow_plan=follow_plan) if constrained else None)
        result = fast_generate(model, enc["input_ids"].to(device), enc["attention_mask"].to(device),
                               max_new_tokens=max_new_tokens, min_new_tokens=min_new_tokens,
                               eos=[tokenizer.eos_token_id], pad=tokenizer.pad_token_id, sampling=do_sample,
                               warpers=warpers, constraint=constraint, length=length, attention=attention,
                               fuse=fuse, merge_lora=merge_lora)
        if report is not None:
            report.append(result)
        width = max((len(row) for row in result.tokens), default=0)
        for i, row in zip(idx, result.tokens):
            out[i] = row + [tokenizer.pad_token_id] * (width - len(row))
        bar.update(len(idx))
    return out


def generate_with(model: PreTrainedModel, tokenizer: PreTrainedTokenizerBase, prompts: Sequence[str], *,
                  chat_format: bool = False, physics: bool = False, max_new_tokens: int = 1024,
                  batch_size: int = 16, do_sample: bool = False, temperature: float = 1.0, seed: int = 0,
                  cache: str = "dynamic", constrained: bool = False, follow_plan: bool = True,
                  progress: bool = False) -> list[str]:
    """Completions (decoded, special tokens dropped) of ``prompts`` with a loaded model, in input order.

    ``cache``: the KV cache, one of :data:`CACHE_MODES` (module docstring); ``constrained``: CTRC-
    constrained decoding (:mod:`physcene.train.constrained`), whose layout follows the completion's
    plan unless ``follow_plan`` is False. ``progress``: a bar on stderr over the prompts.
    """
    ids = generate_token_ids(model, tokenizer, prompts, chat_format=chat_format, physics=physics,
                             max_new_tokens=max_new_tokens, batch_size=batch_size, do_sample=do_sample,
                             temperature=temperature, seed=seed, cache=cache, constrained=constrained,
                             follow_plan=follow_plan, progress=progress)
    return [tokenizer.decode(row, skip_special_tokens=True) for row in ids]


def generate(model_path: str | Path, prompts: Sequence[str], *, max_new_tokens: int = 1024,
             batch_size: int | None = None, do_sample: bool = False, temperature: float = 1.0, seed: int = 0,
             device: str | torch.device | None = None, dtype: str | None = None,
             cache: str = "dynamic", constrained: bool = False, follow_plan: bool = True,
             progress: bool = False, base: str | Path | None = None) -> list[str]:
    """Completions of ``prompts`` by the checkpoint at ``model_path`` (greedy unless ``do_sample``).

    ``prompts`` are CTRC prompt strings (``physcene.ctrc.build_prompt``); chat-format checkpoints get
    them wrapped in a user turn, physics-conditioned ones ask for a collision-free layout
    (:func:`input_format`). ``batch_size`` defaults to the checkpoint's ``eval_batch_size`` (its
    training config's ``eval.batch_size``; 16 for foreign checkpoints). Returns one completion
    string per prompt, in order. ``cache``: the KV cache, one of :data:`CACHE_MODES`;
    ``constrained``: CTRC-constrained decoding (:mod:`physcene.train.constrained`; ``follow_plan``: its
    layout follows the completion's own plan). ``progress``: a bar on stderr over the prompts,
    advanced as each batch is decoded (off for callers with their own bars: the ablation, analyses).
    ``base``: an adapter checkpoint's base model (:func:`adapter_base`).
    """
    check_cache(cache)
    if dtype is not None:
        torch_dtype(dtype)  # validate early
    with _loading_bar(progress):
        model, tokenizer, info = load_for_generation(model_path, device=device, dtype=dtype, base=base)
    batch_size = batch_size or int(info.get("eval_batch_size", 16))
    return generate_with(model, tokenizer, prompts, **input_format(info), max_new_tokens=max_new_tokens,
                         batch_size=batch_size, do_sample=do_sample, temperature=temperature, seed=seed,
                         cache=cache, constrained=constrained, follow_plan=follow_plan, progress=progress)


@contextmanager
def _loading_bar(shown: bool) -> Iterator[None]:
    """transformers' own "Loading weights" bar (stderr) only where ``shown``: with progress off a
    caller's stderr stays empty. The switch is transformers' global one, set back on the way out."""
    was_on = transformers_logging.is_progress_bar_enabled()
    if was_on and not shown:
        transformers_logging.disable_progress_bar()
    try:
        yield
    finally:
        if was_on and not shown:
            transformers_logging.enable_progress_bar()
