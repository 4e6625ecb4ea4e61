"""Tokenizers trained locally on CTRC text, for the from-scratch ``tiny``/``small`` models.

No hub tokenizer can be downloaded, and a layout is mostly numbers, so the tokenizer is trained here
with HF ``tokenizers`` on the training prompts and completions. Two kinds (``model.tokenizer.kind``):

- ``bpe``: a byte-level BPE whose numbers are split before BPE sees them: every digit is its own token
  and ``.`` and ``-`` are always separate, so ``-12.75`` becomes ``- 1 2 . 7 5``. A model learns
  digit patterns instead of memorising number tokens, at ~140 tokens per object of a completion.
- ``ctrc``: a byte-level BPE whose pre-tokenizer cuts the text into the units of the CTRC format
  (:func:`ctrc_units_pattern`, derived from :mod:`physcene.ctrc.grammar`): the writer's fixed runs
  (``**Sub-instruction:**\\n``, ``},\\n    {"layer": ``), each key with its quotes, colon, space and
  the quotes or bracket around it (``", "relative_bbox": [``), runs of words and names
  (``lotion_bottle``, `` of the table``), and numbers as an integer part with its separator
  (``, -12``), the point with up to three fraction digits (``.006``) and the digits left (``37``).
  BPE then learns each frequent unit as one token, so ``, 40.00637`` is three tokens instead of ten.
  The text is the same; only its cut into tokens changes.

Both keep the 256 byte symbols in the alphabet, so any string (model output never seen in training,
any unicode) round-trips exactly through encode/decode, and both are saved as a
``transformers.PreTrainedTokenizerFast`` (``tokenizer.json`` + config) so TRL trainers, ``generate``,
the CTRC constraint's vocabulary index and ``AutoTokenizer.from_pretrained`` read them like any other.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from tokenizers import Regex, Tokenizer, decoders, models, pre_tokenizers, trainers
from transformers import PreTrainedTokenizerFast

from physcene.ctrc.grammar import (
    ENTRY_KEYS,
    ENTRY_SEPARATOR,
    ITEM_SEPARATOR,
    KEY_SEPARATOR,
    LAYER,
    LAYOUT_CLOSE,
    LAYOUT_OPEN,
    OBJECTS_CLOSE,
    PLACE,
    PLAN_OPEN,
    STEP_END,
    STEP_NUMBER_END,
    STEP_SEPARATOR,
    VALUE_SPACE,
    ZONE_ENTRY_KEYS,
    key_text,
    quoted,
)

__all__ = ["EOS_TOKEN", "KINDS", "PAD_TOKEN", "build_tokenizer", "ctrc_units_pattern", "train_tokenizer"]

EOS_TOKEN = "<|endoftext|>"
PAD_TOKEN = "<|pad|>"
SPECIAL_TOKENS = (EOS_TOKEN, PAD_TOKEN)
KINDS = ("bpe", "ctrc")
"""``model.tokenizer.kind``: digit-level BPE, or BPE over the CTRC format's units."""

# JSON's own delimiters around a value: a string's quotes, a list's brackets, an object's braces.
_STRING, _LIST_OPEN, _LIST_CLOSE, _ENTRY_OPEN, _ENTRY_CLOSE = '"', "[", "]", "{", "}"
# Fraction digits that stay with the point (1,000 tokens ``.000``-``.999``); the rest follow as digits.
_FRACTION_HEAD = 3


def _literal(text: str) -> str:
    """``text`` as an Oniguruma regex matching it literally (punctuation and whitespace as code points)."""
    return "".join(c if c.isalnum() or c == " " else f"\\x{{{ord(c):x}}}" for c in text)


def _optional(*chars: str) -> str:
    return "(?:" + "|".join(_literal(c) for c in chars) + ")?"


def ctrc_units_pattern() -> str:
    """The regex whose matches (and the text between them) are the pre-tokens of the ``ctrc`` kind.

    Alternatives in order, the first that matches at a position wins:

    1. the writer's fixed runs, longest first, each with the JSON delimiters that always touch it: the
       plan's header, a step's ``.\\n`` and ``. Place ``, the layout's opening up to the first entry's
       first key, the run between entries, the objects' close up to the zone's ``[``, the end;
    2. every entry key as written after a value (``", "category": "``), with the previous value's
       closing quote or bracket and its own value's opening one;
    3. a number's integer part with the item separator or space before it (``, -12``);
    4. the point with up to three fraction digits (``.006``);
    5. a run of words and names, each with the space or underscore before it and an underscore after
       it (``_comb_`` of ``4_comb_0``, `` at the left front of the table``, ``picture_frame``): BPE
       merges the plan's and descriptions' frequent phrases (67 -> 57 tokens per object).

    Everything else (other punctuation, newlines, non-letters) is cut between the matches.
    """
    first_key = _ENTRY_OPEN + quoted(LAYER) + KEY_SEPARATOR
    fixed = [
        PLAN_OPEN,
        STEP_END + STEP_SEPARATOR,
        STEP_NUMBER_END + PLACE + " ",
        STEP_END + LAYOUT_OPEN + first_key,
        _ENTRY_CLOSE + ENTRY_SEPARATOR + first_key,
        _ENTRY_CLOSE + OBJECTS_CLOSE + VALUE_SPACE + _LIST_OPEN,
        _LIST_CLOSE + LAYOUT_CLOSE,
    ]
    keys = dict.fromkeys(k for k in (*ENTRY_KEYS, *ZONE_ENTRY_KEYS) if k != LAYER)
    key_runs = [_optional(_STRING, _LIST_CLOSE) + _literal(key_text(k) + VALUE_SPACE)
                + _optional(_STRING, _LIST_OPEN) for k in keys]
    units = [_literal(t) for t in sorted(fixed, key=len, reverse=True)] + key_runs + [
        _optional(ITEM_SEPARATOR, VALUE_SPACE) + r"-?\d+",
        r"\." + rf"\d{{1,{_FRACTION_HEAD}}}",
        r"(?:[ _]?\p{L}+(?:_\p{L}+)*_?)+",
    ]
    return "|".join(units)


def _pre_tokenizer(kind: str) -> pre_tokenizers.PreTokenizer:
    if kind == "ctrc":
        return pre_tokenizers.Sequence([
            pre_tokenizers.Split(Regex(ctrc_units_pattern()), behavior="isolated"),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ])
    # Order matters: digits and the number punctuation are isolated first, then GPT-2 style
    # byte-level splitting handles words and whitespace (its regex would glue " 12" together).
    return pre_tokenizers.Sequence([
        pre_tokenizers.Digits(individual_digits=True),
        pre_tokenizers.Split(Regex(r"[.\-]"), behavior="isolated"),
        pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=True),
    ])


def build_tokenizer(texts: Iterable[str], vocab_size: int = 1024, min_frequency: int = 2,
                    kind: str = "bpe") -> PreTrainedTokenizerFast:
    """Train a byte-level BPE of at most ``vocab_size`` tokens on ``texts`` (prompts and completions),
    cutting the text the way ``kind`` (:data:`KINDS`) says.

    The 256 byte symbols are always in the alphabet, so any string (also model output never seen in
    training) round-trips exactly through encode/decode.
    """
    if kind not in KINDS:
        raise ValueError(f"model.tokenizer.kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if vocab_size < 256 + len(SPECIAL_TOKENS):
        raise ValueError(f"vocab_size must be at least {256 + len(SPECIAL_TOKENS)} (bytes + specials), "
                         f"got {vocab_size}")
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = _pre_tokenizer(kind)
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


def train_tokenizer(texts: Iterable[str], out_dir: str | Path, vocab_size: int = 1024,
                    kind: str = "bpe") -> PreTrainedTokenizerFast:
    """:func:`build_tokenizer` and save it to ``out_dir`` (readable by ``AutoTokenizer.from_pretrained``)."""
    tokenizer = build_tokenizer(texts, vocab_size=vocab_size, kind=kind)
    tokenizer.save_pretrained(str(out_dir))
    return tokenizer
