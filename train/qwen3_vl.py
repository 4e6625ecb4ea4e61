"""The paper's backbone, Qwen3-VL, built from its config at any size: the tiny checkpoint of the CPU tests
and the random-init model of Qwen3-VL-8B's exact dimensions that ``physcene bench train8b`` measures.

No checkpoint can be downloaded, so a checkpoint folder is assembled here the way a Hugging Face
Qwen3-VL release is laid out: ``Qwen3VLForConditionalGeneration`` weights and config, a byte-level BPE
tokenizer trained locally on CTRC text with Qwen's special tokens (``<|im_start|>``, ``<|im_end|>``,
the vision markers) and its ChatML chat template (:data:`CHAT_TEMPLATE`), and the processor files (the
image processor built from its class defaults; the whole ``Qwen3VLProcessor`` where its video
processor can be built, which needs torchvision). Training feeds the model text only: the tokenizer
is what :func:`physcene.train.models.load_tokenizer` reads.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import torch
from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
from transformers import PreTrainedTokenizerFast, Qwen3VLConfig, Qwen3VLForConditionalGeneration

__all__ = [
    "CHAT_TEMPLATE",
    "QWEN3_VL_8B_TEXT",
    "QWEN3_VL_8B_VISION",
    "SPECIAL_TOKENS",
    "TINY_TEXT",
    "TINY_VISION",
    "chatml_tokenizer",
    "qwen3_vl_config",
    "save_checkpoint",
    "tiny_qwen3_vl_checkpoint",
]

# Qwen's ChatML: every turn is <|im_start|>role\n...<|im_end|>\n; a generation prompt opens the
# assistant turn. Content is a string or (as processors pass it) a list of {"type": "text", ...} parts.
CHAT_TEMPLATE = (
    "{%- for message in messages %}"
    "{{- '<|im_start|>' + message['role'] + '\\n' }}"
    "{%- if message['content'] is string %}{{- message['content'] }}"
    "{%- else %}{%- for part in message['content'] %}"
    "{%- if part['type'] == 'text' %}{{- part['text'] }}{%- endif %}"
    "{%- endfor %}{%- endif %}"
    "{{- '<|im_end|>\\n' }}"
    "{%- endfor %}"
    "{%- if add_generation_prompt %}{{- '<|im_start|>assistant\\n' }}{%- endif %}"
)

# Qwen3-VL's special tokens (Qwen's ids start at 151643 behind the BPE vocabulary; here they come first).
SPECIAL_TOKENS = ("<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
                  "<|image_pad|>", "<|video_pad|>")
EOS, PAD = "<|im_end|>", "<|endoftext|>"

# Qwen3-VL-8B-Instruct's config.json (8.77 B parameters): the text model is Qwen3-8B's decoder with
# interleaved M-RoPE, the vision tower a 27-block ViT whose blocks 8, 16, 24 also feed the decoder.
QWEN3_VL_8B_TEXT = {
    "vocab_size": 151936, "hidden_size": 4096, "intermediate_size": 12288, "num_hidden_layers": 36,
    "num_attention_heads": 32, "num_key_value_heads": 8, "head_dim": 128, "hidden_act": "silu",
    "max_position_embeddings": 262144, "rms_norm_eps": 1e-6,
    "rope_parameters": {"rope_type": "default", "rope_theta": 5000000.0, "mrope_section": [24, 20, 20],
                        "mrope_interleaved": True},
}
QWEN3_VL_8B_VISION = {
    "depth": 27, "hidden_size": 1152, "intermediate_size": 4304, "num_heads": 16, "patch_size": 16,
    "spatial_merge_size": 2, "temporal_patch_size": 2, "out_hidden_size": 4096,
    "num_position_embeddings": 2304, "deepstack_visual_indexes": [8, 16, 24],
    "hidden_act": "gelu_pytorch_tanh",
}
# The CPU tests' size: the same layout (GQA, head_dim apart from hidden/heads, M-RoPE sections summing
# to head_dim / 2, deepstack taps inside the vision depth), ~0.3 M parameters.
TINY_TEXT = {
    "hidden_size": 64, "intermediate_size": 128, "num_hidden_layers": 2, "num_attention_heads": 4,
    "num_key_value_heads": 2, "head_dim": 16, "max_position_embeddings": 8192,
    "rope_parameters": {"rope_type": "default", "rope_theta": 5000000.0, "mrope_section": [4, 2, 2],
                        "mrope_interleaved": True},
}
TINY_VISION = {
    "depth": 2, "hidden_size": 32, "intermediate_size": 64, "num_heads": 2, "patch_size": 16,
    "out_hidden_size": 64, "num_position_embeddings": 64, "deepstack_visual_indexes": [0, 1],
}


def chatml_tokenizer(texts: Iterable[str], vocab_size: int = 512) -> PreTrainedTokenizerFast:
    """A byte-level BPE of at most ``vocab_size`` tokens trained on ``texts``, with Qwen's special tokens,
    EOS ``<|im_end|>`` (the end of an assistant turn), pad ``<|endoftext|>`` and :data:`CHAT_TEMPLATE`.
    Digits are single tokens, as in Qwen's own pre-tokenizer."""
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.Sequence([
        pre_tokenizers.Digits(individual_digits=True),
        pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=True),
    ])
    tok.decoder = decoders.ByteLevel()
    tok.train_from_iterator(texts, trainer=trainers.BpeTrainer(
        vocab_size=vocab_size, special_tokens=list(SPECIAL_TOKENS),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(), show_progress=False))
    return PreTrainedTokenizerFast(tokenizer_object=tok, eos_token=EOS, pad_token=PAD, bos_token=None,
                                   padding_side="left", model_max_length=1 << 20, chat_template=CHAT_TEMPLATE)


def qwen3_vl_config(tokenizer: PreTrainedTokenizerFast, text: dict, vision: dict,
                    vocab_size: int | None = None) -> Qwen3VLConfig:
    """A ``Qwen3VLConfig`` with ``text``/``vision`` sizes and ``tokenizer``'s special-token ids;
    ``vocab_size``: the embedding rows (default: the tokenizer's; the 8B size keeps Qwen's 151936)."""
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in SPECIAL_TOKENS}
    text = {**text, "vocab_size": int(vocab_size or text.get("vocab_size") or len(tokenizer)),
            "pad_token_id": ids[PAD], "eos_token_id": ids[EOS]}
    return Qwen3VLConfig(text_config=text, vision_config=dict(vision), image_token_id=ids["<|image_pad|>"],
                         video_token_id=ids["<|video_pad|>"], vision_start_token_id=ids["<|vision_start|>"],
                         vision_end_token_id=ids["<|vision_end|>"], eos_token_id=ids[EOS],
                         pad_token_id=ids[PAD], tie_word_embeddings=False)


def _image_processor(vision: dict):
    """Qwen's image processor from its class defaults, with the vision tower's patch and merge sizes
    (the PIL class: the default one needs torchvision)."""
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    return Qwen2VLImageProcessorPil(patch_size=int(vision.get("patch_size", 16)),
                                    merge_size=int(vision.get("spatial_merge_size", 2)),
                                    temporal_patch_size=int(vision.get("temporal_patch_size", 2)))


def save_checkpoint(model: Qwen3VLForConditionalGeneration, tokenizer: PreTrainedTokenizerFast,
                    out_dir: str | Path) -> Path:
    """Write ``model``, ``tokenizer`` and the processor files to ``out_dir`` as a local checkpoint.

    Where ``Qwen3VLProcessor`` cannot be built (its video processor needs torchvision), its files are
    written from the image processor: ``preprocessor_config.json``, ``video_preprocessor_config.json``
    and ``processor_config.json`` naming ``Qwen3VLProcessor``, as a release has them.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model.generation_config.eos_token_id = tokenizer.eos_token_id
    model.generation_config.pad_token_id = tokenizer.pad_token_id
    model.save_pretrained(str(out))
    tokenizer.save_pretrained(str(out))
    image_processor = _image_processor(model.config.vision_config.to_dict())
    try:
        from transformers import Qwen3VLProcessor, Qwen3VLVideoProcessor

        processor = Qwen3VLProcessor(image_processor=image_processor, tokenizer=tokenizer,
                                     video_processor=Qwen3VLVideoProcessor(), chat_template=CHAT_TEMPLATE)
        processor.save_pretrained(str(out))
    except (ImportError, AttributeError, TypeError, ValueError):  # no torchvision: no video processor
        image_processor.save_pretrained(str(out))
        video = {**image_processor.to_dict(), "video_processor_type": "Qwen3VLVideoProcessor",
                 "processor_class": "Qwen3VLProcessor"}
        video.pop("image_processor_type", None)
        (out / "video_preprocessor_config.json").write_text(json.dumps(video, indent=2))
        (out / "processor_config.json").write_text(json.dumps({"processor_class": "Qwen3VLProcessor"}))
    return out


def tiny_qwen3_vl_checkpoint(out_dir: str | Path, texts: Iterable[str], seed: int = 0,
                             vocab_size: int = 512) -> Path:
    """A random-weight Qwen3-VL of :data:`TINY_TEXT`/:data:`TINY_VISION` sizes with a tokenizer trained on
    ``texts``, saved as a local checkpoint in ``out_dir`` (fp32)."""
    tokenizer = chatml_tokenizer(texts, vocab_size=vocab_size)
    torch.manual_seed(seed)
    model = Qwen3VLForConditionalGeneration(qwen3_vl_config(tokenizer, TINY_TEXT, TINY_VISION))
    return save_checkpoint(model, tokenizer, out_dir)
