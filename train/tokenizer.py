"""A byte-level BPE tokenizer trained locally on CTRC text, for the from-scratch ``tiny``/``small`` models.

No hub tokenizer can be downloaded, and a layout is mostly numbers, so the tokenizer is trained here
with HF ``tokenizers`` on the training prompts and completions. Numbers are split before BPE sees them:
every digit is its own token and ``.`` and ``-`` are always separate, so ``-12.75`` becomes
``- 1 2 . 7 5``. A model then learns arithmetic-like digit patterns instead of memorising thousands of
number tokens, and the PADA* numeric mask (``pada.numeric_token_mask``) has clean token boundaries.

The result is saved as a ``transformers.PreTrainedTokenizerFast`` (``tokenizer.json`` + config) so
TRL trainers, ``generate`` and ``AutoTokenizer.from_pretrained`` read it like any other.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from tokenizers import Regex, Tokenizer, decoders, models, pre_tokenizers, trainers
from transformers import PreTrainedTokenizerFast

__all__ = ["EOS_TOKEN", "PAD_TOKEN", "build_tokenizer", "train_tokenizer"]

EOS_TOKEN = "<|endoftext|>"
PAD_TOKEN = "<|pad|>"
SPECIAL_TOKENS = (EOS_TOKEN, PAD_TOKEN)


def _pre_tokenizer() -> pre_tokenizers.PreTokenizer:
    # Order matters: digits and the number punctuation are isolated first, then GPT-2 style
    # byte-level splitting handles words and whitespace (its regex would glue " 12" together).
    return pre_tokenizers.Sequence([
        pre_tokenizers.Digits(individual_digits=True),
        pre_tokenizers.Split(Regex(r"[.\-]"), behavior="isolated"),
        pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=True),
    ])


def build_tokenizer(texts: Iterable[str], vocab_size: int = 1024,
                    min_frequency: int = 2) -> PreTrainedTokenizerFast:
    """Train a byte-level BPE of at most ``vocab_size`` tokens on ``texts`` (prompts and completions).

    The 256 byte symbols are always in the alphabet, so any string (also model output never seen in
    training) round-trips exactly through encode/decode.
    """
    if vocab_size < 256 + len(SPECIAL_TOKENS):
        raise ValueError(f"vocab_size must be at least {256 + len(SPECIAL_TOKENS)} (bytes + specials), "
                         f"got {vocab_size}")
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = _pre_tokenizer()
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        min_frequency=min_frequency,
        special_tokens=list(SPECIAL_TOKENS),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(texts, trainer=trainer)
    return PreTrainedTokenizerFast(
        tokenizer_object=tok,
        eos_token=EOS_TOKEN,
        pad_token=PAD_TOKEN,
        bos_token=None,
        padding_side="left",  # decoder-only generation pads on the left
        model_max_length=1 << 20,
    )


def train_tokenizer(texts: Iterable[str], out_dir: str | Path,
                    vocab_size: int = 1024) -> PreTrainedTokenizerFast:
    """:func:`build_tokenizer` and save it to ``out_dir`` (readable by ``AutoTokenizer.from_pretrained``)."""
    tokenizer = build_tokenizer(texts, vocab_size=vocab_size)
    tokenizer.save_pretrained(str(out_dir))
    return tokenizer
