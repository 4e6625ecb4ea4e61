"""Models for the training configs: Qwen3 built from a config (``tiny``, ``small``) or a local checkpoint.

- ``scratch``: a ``transformers.Qwen3ForCausalLM`` built from ``Qwen3Config`` with the sizes in the
  config's ``model.arch`` and a tokenizer trained locally (:mod:`physcene.train.tokenizer`, of the kind
  ``model.tokenizer.kind`` names: ``bpe`` or ``ctrc``). The same
  architecture as the paper's backbone family, small enough for CPU tests (``tiny``, 0.24 M parameters)
  or one GPU (``small``, ~27 M parameters, a 55 MB bf16 checkpoint).
- ``pretrained``: any local Hugging Face checkpoint, e.g. Qwen3-VL-8B-Instruct. Vision-language
  checkpoints load with ``AutoModelForImageTextToText`` and are fed text only; their vision tower is
  frozen (``requires_grad=False``) so neither the optimizer nor ZeRO-2 keeps states for it, and LoRA
  targets the language model's modules only (:func:`language_model_targets`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from transformers import (
    AutoConfig,
    AutoModelForCausalLM,
    AutoModelForImageTextToText,
    AutoTokenizer,
    PreTrainedModel,
    PreTrainedTokenizerBase,
    Qwen3Config,
    Qwen3ForCausalLM,
)
from transformers.models.auto.modeling_auto import MODEL_FOR_IMAGE_TEXT_TO_TEXT_MAPPING_NAMES

from physcene.artifacts import checkpoint_digest
from physcene.files import replace_dir, write_atomic
from physcene.train.checkpoints import weights_problem
from physcene.train.tokenizer import build_tokenizer, train_tokenizer

__all__ = [
    "RUN_INFO",
    "TrainingSetupError",
    "base_checked",
    "begin_final_save",
    "build_scratch_model",
    "count_parameters",
    "freeze_vision_tower",
    "language_model_targets",
    "load_model",
    "load_tokenizer",
    "prepare_model_and_tokenizer",
    "read_run_info",
    "recorded_base_digest",
    "save_train_log",
    "set_attention_kernels",
    "tokenizer_settings",
    "torch_dtype",
    "write_run_info",
]

# Written next to every checkpoint this package saves: how to feed the model (chat template or plain
# text) so that anchors, PADA and eval need no extra flags.
RUN_INFO = "physcene_run.json"


class TrainingSetupError(ValueError):
    """A training config, model path or data file was wrong."""


def torch_dtype(name: str) -> torch.dtype:
    """``"bfloat16"``/``"bf16"``/``"float16"``/``"fp16"``/``"float32"`` -> torch dtype."""
    table = {"bfloat16": torch.bfloat16, "bf16": torch.bfloat16, "float16": torch.float16,
             "fp16": torch.float16, "float32": torch.float32, "fp32": torch.float32}
    if name not in table:
        raise TrainingSetupError(f"unknown dtype {name!r}; use one of {sorted(table)}")
    return table[name]


def count_parameters(model: torch.nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters (tied embeddings counted once)."""
    seen: set[int] = set()
    total = 0
    for p in model.parameters():
        if id(p) in seen or (trainable_only and not p.requires_grad):
            continue
        seen.add(id(p))
        total += p.numel()
    return total


def build_scratch_model(arch: DictConfig | dict, tokenizer: PreTrainedTokenizerBase, seed: int = 0,
                        dtype: str = "float32") -> Qwen3ForCausalLM:
    """A randomly initialised Qwen3 causal LM with the sizes in ``arch`` and ``tokenizer``'s vocabulary."""
    arch = OmegaConf.to_container(arch, resolve=True) if isinstance(arch, DictConfig) else dict(arch)
    torch.manual_seed(seed)
    config = Qwen3Config(
        vocab_size=len(tokenizer),
        eos_token_id=tokenizer.eos_token_id,
        pad_token_id=tokenizer.pad_token_id,
        bos_token_id=None,
        tie_word_embeddings=True,
        **arch,
    )
    model = Qwen3ForCausalLM(config)
    model.generation_config.eos_token_id = tokenizer.eos_token_id
    model.generation_config.pad_token_id = tokenizer.pad_token_id
    return model.to(torch_dtype(dtype))


def _is_image_text_checkpoint(path: str | Path) -> bool:
    config = AutoConfig.from_pretrained(str(path))
    return config.model_type in MODEL_FOR_IMAGE_TEXT_TO_TEXT_MAPPING_NAMES


# Where a vision tower's modules sit in the image-text-to-text classes (Qwen3-VL: model.visual;
# LLaVA-style: vision_tower / vision_model). Qwen2.5-VL's vision blocks have gate/up/down_proj too.
VISION_TOWER_NAMES = ("visual", "vision_tower", "vision_model")


def language_model_targets(names: Iterable[str]) -> str:
    """A peft ``target_modules`` regex for the modules named ``names`` (``q_proj`` ...) outside any
    vision tower: LoRA on the language model only, for causal LMs and vision-language models alike.

    peft matches a string ``target_modules`` against each module's full name with ``re.fullmatch``;
    a list would match by suffix and also wrap a vision block's layer of the same name.
    """
    names = [str(n) for n in names]
    if not names or any(not re.fullmatch(r"[A-Za-z0-9_]+", n) for n in names):
        raise TrainingSetupError(f"lora.target_modules must be module names such as q_proj, got {names}")
    tower = "|".join(VISION_TOWER_NAMES)
    return rf"(?!(?:.*\.)?(?:{tower})\.).*\.(?:{'|'.join(names)})"


def freeze_vision_tower(model: torch.nn.Module) -> int:
    """Freeze every parameter of a vision tower (names containing ``visual``/``vision``); returns how many."""
    frozen = 0
    for name, p in model.named_parameters():
        if ".visual." in f".{name}" or "vision_tower" in name or "vision_model" in name:
            p.requires_grad_(False)
            frozen += p.numel()
    return frozen


def load_model(path: str | Path, dtype: str = "bfloat16", freeze_vision: bool = True) -> PreTrainedModel:
    """A local checkpoint (causal LM or image-text-to-text, used text-only), vision tower frozen."""
    path = Path(path)
    if not (path / "config.json").is_file():
        raise TrainingSetupError(f"model path {str(path)!r} has no config.json "
                                 "(a local Hugging Face checkpoint is needed)")
    loader = AutoModelForImageTextToText if _is_image_text_checkpoint(path) else AutoModelForCausalLM
    model = loader.from_pretrained(str(path), dtype=torch_dtype(dtype))
    if freeze_vision:
        freeze_vision_tower(model)
    return model


def load_tokenizer(path: str | Path) -> PreTrainedTokenizerBase:
    """The tokenizer saved with a checkpoint, left-padded for generation, with a pad token."""
    tokenizer = AutoTokenizer.from_pretrained(str(path))
    if tokenizer.chat_template is None:
        # Vision-language checkpoints may keep the template with the processor files only.
        for name in ("chat_template.jinja", "chat_template.json"):
            f = Path(path) / name
            if f.is_file():
                text = f.read_text()
                is_json = name.endswith(".json")
                tokenizer.chat_template = json.loads(text)["chat_template"] if is_json else text
                break
    if tokenizer.pad_token is None:
        tokenizer.pad_token = tokenizer.eos_token
    tokenizer.padding_side = "left"
    return tokenizer


def set_attention_kernels(model_cfg: DictConfig | dict) -> bool:
    """Allow or forbid torch's cuDNN kernel for ``scaled_dot_product_attention`` in this process, as
    ``model.cudnn_attention`` says (default: forbid); returns whether it is allowed.

    A training process, not the model: the flag is torch's global one. Why off: on H100/H200 under
    torch 2.11 the cuDNN backward writes NaN into the query gradient when a query row attends to
    nothing (the left padding of a batch of prompts: its logsumexp is -inf) and the sequence length
    is 64 past a multiple of 128 (pytorch/pytorch#196678). PADA's anchor forward, [left-padded prompt |
    anchor], met it at 346 + 1894 = 2240 tokens: every LoRA gradient NaN for a whole generation round,
    with finite losses (``pada.nonfinite_probe``; the replay ``docs/results/nonfinite_replay.py``:
    cuDNN NaN, memory-efficient, math and eager attention finite on the same micro-batch). SDPA then
    picks the memory-efficient kernel. Set ``model.cudnn_attention=true`` on a torch without the bug.
    """
    allowed = bool((model_cfg or {}).get("cudnn_attention", False))
    torch.backends.cuda.enable_cudnn_sdp(allowed)
    return allowed


def tokenizer_settings(model_cfg: DictConfig | dict) -> dict:
    """``model.tokenizer`` as :func:`~physcene.train.tokenizer.build_tokenizer`'s keywords: ``vocab_size``
    and ``kind`` (``bpe`` when the config has none)."""
    t = model_cfg["tokenizer"]
    return {"vocab_size": int(t["vocab_size"]), "kind": str(t.get("kind") or "bpe")}


def prepare_model_and_tokenizer(cfg: DictConfig, texts: Iterable[str] | None = None,
                                out_dir: str | Path | None = None):
    """The stage-1 starting point of ``cfg.model``: (model, tokenizer).

    ``scratch`` trains a tokenizer on ``texts`` (saved to ``out_dir/tokenizer`` when given) and builds
    a random Qwen3, or with ``model.init_from`` starts from an earlier scratch checkpoint (fp32);
    ``pretrained`` loads ``cfg.model.path``.
    """
    m = cfg.model
    if m.source == "scratch" and m.get("init_from"):
        # Continue an earlier from-scratch run on new data: its weights and vocabulary, trained in fp32
        # like a fresh scratch model and saved in model.dtype.
        if not Path(m.init_from).is_dir():
            raise TrainingSetupError(f"model.init_from={m.init_from!r} is not a checkpoint directory")
        return load_model(m.init_from, dtype="float32", freeze_vision=False), load_tokenizer(m.init_from)
    if m.source == "scratch":
        if texts is None:
            raise TrainingSetupError("a scratch model needs training texts to build its tokenizer")
        tok_dir = Path(out_dir) / "tokenizer" if out_dir is not None else None
        if tok_dir is not None and (tok_dir / "tokenizer.json").is_file():
            tokenizer = load_tokenizer(tok_dir)  # resume: the vocabulary must not change under a checkpoint
        elif tok_dir is not None:
            with replace_dir(tok_dir) as tmp:  # a resume must never find half a vocabulary
                train_tokenizer(texts, tmp, **tokenizer_settings(m))
            tokenizer = load_tokenizer(tok_dir)
        else:
            tokenizer = build_tokenizer(texts, **tokenizer_settings(m))
        # Train from scratch in fp32 (bf16 autocast on GPU); model.dtype is the dtype it is saved in.
        model = build_scratch_model(m.arch, tokenizer, seed=int(cfg.seed), dtype="float32")
        return model, tokenizer
    if m.source == "pretrained":
        if not m.path:
            raise TrainingSetupError("model.source=pretrained needs model.path (a local checkpoint dir)")
        model = load_model(m.path, dtype=str(m.dtype), freeze_vision=bool(m.freeze_vision))
        return model, load_tokenizer(m.path)
    raise TrainingSetupError(f"model.source must be 'scratch' or 'pretrained', got {m.source!r}")


def write_run_info(out_dir: str | Path, **info) -> None:
    """Record how a checkpoint expects its input (``chat_format``, ``stage``, ``base_model`` ...).

    Written last, after the model, tokenizer and log: a run folder with :data:`RUN_INFO` is a
    finished one (:func:`begin_final_save` removes it before the final model is written)."""
    write_atomic(Path(out_dir) / RUN_INFO, json.dumps(info, indent=2, sort_keys=True))


def begin_final_save(trainer, out_dir: str | Path) -> None:
    """Remove the :data:`RUN_INFO` of an earlier run before ``trainer`` writes the final model into
    ``out_dir``: interrupted while it writes, the folder no longer claims to hold a finished model."""
    if trainer.is_world_process_zero():
        (Path(out_dir) / RUN_INFO).unlink(missing_ok=True)


def save_train_log(trainer, out_dir: str | Path) -> None:
    """The trainer's log history as ``out_dir/train_log.json`` (renamed into place when complete)."""
    write_atomic(Path(out_dir) / "train_log.json", json.dumps(trainer.state.log_history, indent=1))


def read_run_info(model_dir: str | Path) -> dict:
    """The :data:`RUN_INFO` of a checkpoint, or ``{}`` for a foreign checkpoint.

    A training folder (``checkpoint-*`` inside) without it, or with one marked ``complete: false``, whose
    top-level weights are missing or cut short is a run that has not finished (stopped before or during
    its final save): an error saying so, rather than a crash in the model loader."""
    path = Path(model_dir) / RUN_INFO
    info = json.loads(path.read_text()) if path.is_file() else None
    if info is not None and info.get("complete") is not False:
        return info
    folder = Path(model_dir)
    # an RL run records its base at the start (``complete: false``) and its model at the end
    if folder.is_dir() and (info is not None or any(folder.glob("checkpoint-*"))):
        problem = weights_problem(folder)
        if problem:
            raise TrainingSetupError(f"{str(folder)!r} is a training run that has not finished ({problem}); "
                                     "run its training command again to resume it")
    return info or {}


def recorded_base_digest(run_dir: str | Path) -> str | None:
    """The base digest (``base_sha256``) an RL run at ``run_dir`` recorded, or None: read raw, since an
    unfinished run's info (``complete: false``) records it too."""
    info_path = Path(run_dir) / RUN_INFO
    return json.loads(info_path.read_text()).get("base_sha256") if info_path.is_file() else None


def base_checked(out_dir: str | Path, base_dir: str | Path, **info) -> str:
    """The digest of the base checkpoint an RL run at ``out_dir`` starts from
    (:func:`physcene.artifacts.checkpoint_digest`: weights, config, tokenizer), checked against the one
    its run info recorded: resuming an adapter on another base trains it on weights it was not made
    for. A new run records it (``base_sha256``, ``complete: false`` until the run saves its model)."""
    digest = checkpoint_digest(base_dir)
    recorded = recorded_base_digest(out_dir)
    if recorded is not None and recorded != digest:
        raise TrainingSetupError(f"{out_dir} was trained from a base with sha256 {recorded}; {base_dir} has "
                                 f"sha256 {digest}: restore the base it was trained on, or start a new "
                                 "output_dir")
    if not (Path(out_dir) / RUN_INFO).is_file():
        write_run_info(out_dir, **info, base_sha256=digest, complete=False)
    return digest
