"""``physcene bench tokens``: tokens per object of the test split's references under each tokenizer kind.

    physcene bench tokens --config small                         # bpe vs ctrc, trained on data.train
    physcene bench tokens --config small --train synth:train:1000 --n 200 --json

Each kind of :data:`physcene.train.tokenizer.KINDS` is trained the way ``physcene train sft`` trains it
(:func:`physcene.train.models.tokenizer_settings` of ``--config``, on the prompts and completions of
``--train``, default the config's ``data.train``), then counts the completion tokens of every reference
of ``--split`` (:func:`physcene.data.synthesize`, the records ``physcene eval`` scores) the way TRL's
SFT feeds them: ``prompt + completion + EOS`` tokenized whole, less the tokens it shares with the
prompt tokenized alone. Every kind must give back every reference exactly (``decode(encode(text))``)
and ``--fuzz`` random strings of bytes and unicode. Nothing is timed.
"""

from __future__ import annotations

import random
import statistics

from physcene.commands.bench.timing import BenchTarget

__all__ = ["TARGET", "completion_tokens", "fuzz_texts", "round_trips", "token_counts"]


def add_arguments(parser) -> None:
    parser.add_argument("--config", default="small", help="training config whose model.tokenizer is built")
    parser.add_argument("--train", default=None,
                        help="records the tokenizers are trained on: JSONL or synth:SPLIT:N "
                             "(default: the config's data.train)")
    parser.add_argument("--split", default="test", choices=("train", "test", "ood"),
                        help="references whose completions are counted (default: test)")
    parser.add_argument("--n", type=int, default=None, help="only the first N references (default: all)")
    parser.add_argument("--kinds", nargs="+", default=None, help="tokenizer kinds (default: all, bpe first)")
    parser.add_argument("--vocab-size", type=int, default=None,
                        help="vocabulary size of every kind (default: model.tokenizer.vocab_size)")
    parser.add_argument("--fuzz", type=int, default=200, help="random strings each kind must round-trip")
    parser.add_argument("--seed", type=int, default=0)


def completion_tokens(tokenizer, prompt: str, completion: str) -> int:
    """Tokens the SFT loss sees for ``completion`` after ``prompt`` (TRL: the prompt-completion ids past
    their common prefix with the prompt's, EOS included)."""
    prompt_ids = tokenizer(prompt, add_special_tokens=False)["input_ids"]
    full = tokenizer(prompt + completion + tokenizer.eos_token, add_special_tokens=False)["input_ids"]
    shared = 0
    for a, b in zip(prompt_ids, full, strict=False):
        if a != b:
            break
        shared += 1
    return len(full) - shared


def fuzz_texts(n: int, seed: int = 0) -> list[str]:
    """``n`` random strings: bytes decoded leniently, any unicode code point, CTRC-like characters."""
    rng = random.Random(seed)
    alphabet = '0123456789.-, "[]{}:_\n abcxyz'
    out = []
    for k in range(n):
        size = rng.randint(0, 200)
        if k % 3 == 0:
            out.append(bytes(rng.randrange(256) for _ in range(size)).decode("utf-8", errors="replace"))
        elif k % 3 == 1:
            out.append("".join(chr(rng.choice((rng.randrange(0x20, 0x7F), rng.randrange(0xA0, 0xD800),
                                               rng.randrange(0xE000, 0x110000)))) for _ in range(size)))
        else:
            out.append("".join(rng.choice(alphabet) for _ in range(size)))
    return out


def round_trips(tokenizer, texts) -> list[str]:
    """The texts that do not come back from ``decode(encode(text))`` exactly (empty: all do)."""
    return [t for t in texts
            if tokenizer.decode(tokenizer(t, add_special_tokens=False)["input_ids"]) != t]


def token_counts(tokenizer, records: list[dict]) -> dict:
    """Completion tokens, characters and objects of ``records`` under ``tokenizer``."""
    tokens = [completion_tokens(tokenizer, r["prompt"], r["completion"]) for r in records]
    objects = [int(r["n_objects"]) for r in records]
    chars = sum(len(r["completion"]) for r in records)
    prompts = [len(tokenizer(r["prompt"], add_special_tokens=False)["input_ids"]) for r in records]
    by_level: dict[int, list[int]] = {}
    for r, t in zip(records, tokens, strict=True):
        by_level.setdefault(int(r["level"]), []).append(t)
    return {
        "vocab_size": len(tokenizer),
        "tokens_per_object": sum(tokens) / sum(objects),
        "chars_per_token": chars / sum(tokens),
        "completion_tokens_mean": statistics.fmean(tokens),
        "completion_tokens_max": max(tokens),
        "completion_tokens_max_by_level": {str(k): max(v) for k, v in sorted(by_level.items())},
        "prompt_tokens_mean": statistics.fmean(prompts),
    }


def run(args) -> dict:
    # transformers and the data synthesis are heavy: imported when this target runs
    from physcene.config import load_config
    from physcene.data import synthesize
    from physcene.train.models import tokenizer_settings
    from physcene.train.records import load_records
    from physcene.train.tokenizer import KINDS, build_tokenizer

    kinds = args.kinds or list(KINDS)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise ValueError(f"--kinds {' '.join(unknown)}: unknown; use {', '.join(KINDS)}")
    cfg = load_config(f"train_{args.config}", list(getattr(args, "overrides", [])))
    train_spec = args.train or str(cfg.data.train)
    train = load_records(train_spec, seed=args.seed)
    texts = [t for r in train for t in (r["prompt"], r["completion"])]
    references = list(synthesize(args.split, n=args.n, seed=args.seed))
    fuzz = fuzz_texts(args.fuzz, seed=args.seed)
    objects = sum(int(r["n_objects"]) for r in references)
    result = {
        "target": "tokens", "config": args.config, "train": train_spec, "train_records": len(train),
        "split": args.split, "references": len(references), "objects": objects,
        "chars_per_object": sum(len(r["completion"]) for r in references) / objects, "kinds": {},
    }
    for kind in kinds:
        settings = tokenizer_settings(cfg.model) | {"kind": kind}
        if args.vocab_size is not None:
            settings["vocab_size"] = args.vocab_size
        tokenizer = build_tokenizer(texts, **settings)
        figures = token_counts(tokenizer, references)
        failed = round_trips(tokenizer, [t for r in references for t in (r["prompt"], r["completion"])])
        figures["round_trip_failures"] = len(failed) + len(round_trips(tokenizer, fuzz))
        figures["round_trip_texts"] = 2 * len(references) + len(fuzz)
        result["kinds"][kind] = figures
    first = result["kinds"][kinds[0]]["tokens_per_object"]
    for figures in result["kinds"].values():
        figures["tokens_per_object_ratio"] = figures["tokens_per_object"] / first
    return result


def summary(result: dict) -> str:
    lines = [f"{result['split']} split: {result['references']} references, {result['objects']} objects, "
             f"{result['chars_per_object']:.0f} characters per object; tokenizers trained on "
             f"{result['train_records']} records of {result['train']}"]
    for kind, f in result["kinds"].items():
        lines.append(
            f"  {kind:5s} vocab {f['vocab_size']:6d}: {f['tokens_per_object']:6.1f} tokens/object "
            f"(x{f['tokens_per_object_ratio']:.2f}), {f['chars_per_token']:.2f} chars/token, completion "
            f"mean {f['completion_tokens_mean']:.0f} max {f['completion_tokens_max']}, prompt mean "
            f"{f['prompt_tokens_mean']:.0f}; round trip {f['round_trip_texts'] - f['round_trip_failures']}"
            f"/{f['round_trip_texts']} exact")
    return "\n".join(lines)


TARGET = BenchTarget(
    help="tokens per object of a split's references under each tokenizer kind (bpe, ctrc)",
    add_arguments=add_arguments, run=run, summary=summary, repeat=(1, 1))
