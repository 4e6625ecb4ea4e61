"""Fuzz the reward on both parse paths: random and mutated CTRC completions through
:func:`physcene.ctrc.parse` and :class:`physcene.reward.PhysicsReward` with the compiled reader
(``fast_parse``) and with the Python parser.

The completions are real ones from :func:`physcene.data.synthesize`, mutated the way a policy's
samples break: truncated, spans deleted, duplicated or swapped, random bytes, unicode lookalikes,
huge numbers, deep brackets, empty, very long. Nothing may raise; a text :func:`parse` refuses gets
-100 on both paths; the two paths agree on which texts parse, and on the rewards. A failure prints
the seed, the mutation and the text. 2,400 completions here, 24,000 under ``--slow``.
"""

from __future__ import annotations

import random
import re
import time

import numpy as np
import pytest

from physcene.assets import AssetLibrary
from physcene.ctrc import ParseError, parse
from physcene.data import synthesize
from physcene.physics import PhysicsEngine
from physcene.reward import PhysicsReward, RewardConfig
from physcene.scene import Scene

SEED = 31
BATCH = 200
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
UNICODE = ["\u00a0", "\u200b", "\u202e", "\ufeff", "１", "−", "，", "：", "［", "｝", "é", "ß", "文", "🙂",
           "\ud800", "\udfff", "\x00", "\x7f", "\u2028", "\\u0041", "\\ud83d"]
HUGE = ["1e309", "-1e309", "9" * 400, "1" + "0" * 5000, "1e-400", "-0", "NaN", "Infinity", "-Infinity",
        "1e5", "100000.0001", "0.0000000000000000000001", "1" * 30 + ".5", "0x10", "1_000", "+5", ".5", "5.",
        "00012"]
# Numbers at the grammar's edges (4 integer digits, 8 decimals, |x| <= 1e5 cm) and past them.
EDGE = ["9999.99999999", "-9999.99999999", "99999.99999999", "100000", "100000.00000001", "-100000",
        "0.00000001", "0.000000001", "1.123456789", "-0", "-0.0", "0.0", "0", "1e-5", "9999", "10000"]
ALPHABET = '{}[]":,.-0123456789eE \n"objects" "relative_bbox" instance_id parent_id **Scene Layout:**'
# JSON that Python reads one way and a hand-written scanner may read another: a key given twice, a
# string spelled with escapes, whitespace where the canonical text has none.
KEY = re.compile(r'"(relative_bbox|relative_rotation_deg|parent_id|relation_type|instance_id|category)": ')


@pytest.fixture(scope="module")
def rewards():
    """The reward with the compiled reader and with the Python parser, on one small engine."""
    library = AssetLibrary(resolution=24, n_points=256)
    library.add_primitives()
    engine = PhysicsEngine(library)
    return (PhysicsReward(RewardConfig(), engine=engine),
            PhysicsReward(RewardConfig(fast_parse=False), engine=engine))


def _bases() -> list[str]:
    return [r["completion"] for r in synthesize("train", n=12, seed=SEED)]


def _span(rng: random.Random, text: str) -> tuple[int, int]:
    a = rng.randrange(len(text) + 1)
    return a, min(len(text), a + rng.choice([1, 2, 5, 20, 100, 1000]))


def _mutate_once(rng: random.Random, text: str, bases: list[str]) -> tuple[str, str]:
    """One mutation of ``text``: (its name, the new text)."""
    kind = rng.choice(["truncate", "delete", "duplicate", "swap", "bytes", "unicode", "number", "huge",
                       "brackets", "splice", "digits", "json", "json", "edge", "edge"])
    if not text and kind not in ("bytes", "unicode", "brackets"):
        kind = "bytes"
    if kind == "truncate":
        return kind, text[:rng.randrange(len(text))]
    if kind == "delete":
        a, b = _span(rng, text)
        return kind, text[:a] + text[b:]
    if kind == "duplicate":
        a, b = _span(rng, text)
        at = rng.randrange(len(text) + 1)
        return kind, text[:at] + text[a:b] * rng.choice([1, 2, 10]) + text[at:]
    if kind == "swap":
        a, b = sorted(_span(rng, text))
        c, d = _span(rng, text)
        if c < b:
            return "delete", text[:a] + text[b:]
        return kind, text[:a] + text[c:d] + text[b:c] + text[a:b] + text[d:]
    if kind == "bytes":
        junk = bytes(rng.randrange(256) for _ in range(rng.choice([1, 4, 32, 256])))
        junk = junk.decode("utf-8", rng.choice(["replace", "surrogateescape", "ignore"]))
        at = rng.randrange(len(text) + 1)
        return kind, text[:at] + junk + text[at:]
    if kind == "unicode":
        at = rng.randrange(len(text) + 1)
        junk = "".join(rng.choices(UNICODE, k=rng.randint(1, 3)))
        return kind, text[:at] + junk + text[at + rng.randint(0, 1):]
    keys = list(KEY.finditer(text))
    if kind == "json" and keys:
        m = rng.choice(keys)
        style = rng.randrange(3)
        if style == 0:  # the key twice, another value first: Python's json keeps the last one
            end = text.find(", \"", m.end())
            if end < 0:
                return "json-twice", text
            pair = text[m.start():end]
            first = NUMBER.sub(lambda _: str(round(rng.uniform(-50, 150), 2)), pair)
            if first == pair:  # a string value
                first = m.group(0) + rng.choice(['"on"', '"root_zone"', '"vase"', '"x_0"', '""'])
            return "json-twice", text[:m.start()] + first + ", " + text[m.start():]
        if style == 1:  # a character of the key or of the string after it as a \uXXXX escape
            k = rng.randrange(m.start() + 1, min(len(text), m.end() + 12))
            if text[k] in '"\\':
                return "json-escape", text
            return "json-escape", text[:k] + f"\\u{ord(text[k]):04x}" + text[k + 1:]
        return "json-space", text[:m.end() - 1] + rng.choice(["\n", "\t", "   ", "\r\n"]) + text[m.end() - 1:]
    numbers = list(NUMBER.finditer(text))
    if kind in ("number", "huge", "digits", "edge") and numbers:
        m = rng.choice(numbers)
        if kind == "huge":
            new = rng.choice(HUGE)
        elif kind == "edge":
            new = rng.choice(EDGE)
        elif kind == "digits":  # another plausible value: the layout may stay valid
            new = str(round(rng.uniform(-200, 200), rng.randrange(6)))
        else:
            new = rng.choice(["0", "-1", "1e9", "-0.0", "3", "1e-9", '"1"', "null", "true", "[]"])
        return kind, text[:m.start()] + new + text[m.end():]
    if kind == "brackets":
        at = rng.randrange(len(text) + 1)
        opener = rng.choice(["[", "{", '{"a":', "[[{"])
        return kind, text[:at] + opener * rng.choice([10, 1000, 30_000]) + text[at:]
    other = rng.choice(bases)  # splice: the head of one completion, the tail of another
    return "splice", text[:rng.randrange(len(text) + 1)] + other[rng.randrange(len(other) + 1):]


def corpus(n: int, seed: int = SEED) -> list[tuple[str, str]]:
    """``n`` (label, text) pairs: the real completions, a few fixed extremes, then mutations."""
    rng = random.Random(seed)
    bases = _bases()
    out = [("real", t) for t in bases]
    out += [("empty", ""), ("empty", " \n\t"), ("empty", "**Scene Layout:**"), ("empty", "{}"),
            ("long", bases[0] * 60), ("long", bases[1] + " " * 250_000), ("long", "[" * 300_000),
            ("long", bases[2].replace("Tall", "x" * 100_000, 1)), ("random", "\x00" * 5000)]
    while len(out) < n:
        r = rng.random()
        if r < 0.08:  # random text over the grammar's characters
            out.append(("random", "".join(rng.choice(ALPHABET) for _ in range(rng.randrange(400)))))
            continue
        text, labels = rng.choice(bases), []
        for _ in range(rng.choice([1, 1, 1, 2, 3])):
            label, text = _mutate_once(rng, text, bases)
            labels.append(label)
        out.append((f"seed {seed} case {len(out)}: " + "+".join(labels), text))
    return out[:n]


def _show(label: str, text: str) -> str:
    shown = text if len(text) <= 3000 else text[:1500] + f"... [{len(text)} chars] ..." + text[-1500:]
    return f"{label}: {shown!r}"


def _check(rewards, cases: list[tuple[str, str]]) -> dict:
    fast, slow = rewards
    counts = {"parsed": 0, "refused": 0}
    for start in range(0, len(cases), BATCH):
        chunk = cases[start:start + BATCH]
        texts = [t for _, t in chunk]
        parsed = []
        for label, text in chunk:
            try:
                parsed.append(parse(text))
            except Exception as exc:  # noqa: BLE001 - the finding is any exception at all
                pytest.fail(f"parse raised {exc!r} on {_show(label, text)}")
        try:
            got_fast, got_slow = fast.score(texts), slow.score(texts)
        except Exception:  # noqa: BLE001 - find the text that raised, then report it
            for label, text in chunk:
                for path, reward in (("fast", fast), ("python", slow)):
                    try:
                        reward.score([text])
                    except Exception as exc:  # noqa: BLE001
                        pytest.fail(f"the reward ({path} path) raised {exc!r} on {_show(label, text)}")
            raise
        for k, ((label, text), p) in enumerate(zip(chunk, parsed)):
            assert isinstance(p, (Scene, ParseError)), _show(label, text)
            f, s = got_fast.rewards[k], got_slow.rewards[k]
            if isinstance(p, ParseError):
                assert f == -100.0 and s == -100.0, f"{p.reason}: fast {f}, python {s}; {_show(label, text)}"
                assert p.reason.strip(), _show(label, text)
            assert (got_fast.parse_errors[k] is None) == (got_slow.parse_errors[k] is None), (
                f"fast: {got_fast.parse_errors[k]}, python: {got_slow.parse_errors[k]}; {_show(label, text)}")
            assert np.isfinite(f) and f == pytest.approx(s, abs=1e-6, rel=1e-6), (
                f"fast {f}, python {s}; {_show(label, text)}")
            counts["parsed" if got_fast.parse_errors[k] is None else "refused"] += 1
    return counts


def test_fuzz_reward_both_paths(rewards):
    t0 = time.perf_counter()
    cases = corpus(2_400)
    counts = _check(rewards, cases)
    print(f"reward fuzz: {len(cases)} completions in {time.perf_counter() - t0:.1f} s {counts}")
    assert len(cases) >= 2_000
    assert counts["parsed"] >= 100 and counts["refused"] >= 1_000  # both outcomes are exercised


@pytest.mark.slow
def test_fuzz_reward_both_paths_long(rewards):
    cases = corpus(24_000, seed=SEED + 1)
    counts = _check(rewards, cases)
    assert len(cases) >= 20_000 and counts["parsed"] and counts["refused"]
