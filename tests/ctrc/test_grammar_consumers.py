"""The consumers of the CTRC grammar agree (physcene/ctrc/grammar.py is the one description of the
format): the writer and the parser round-trip, the Python parser and the compiled (Warp) reader accept
and refuse the same fuzzed texts, every prefix the decoding constraint admits continues to a text the
parser accepts, and a key name or a limit changed in grammar.py reaches every consumer."""

import json
import os
import random
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from physcene.ctrc import ParseError, completion_text, grammar, parse, spans
from physcene.data import synthesize
from physcene.layout import load_layout
from physcene.physics import PhysicsEngine
from physcene.reward.text_batch import TextPacker
from physcene.train.constrained import CTRCConstraint, constraint_rule, listed_instance_ids, prompt_zone
from physcene.train.constrained import grammar as constraint_grammar
from physcene.train.tokenizer import build_tokenizer

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def records():
    return list(synthesize("test", 24, seed=5))


def fast_path_reads(texts: list[str]) -> np.ndarray:
    """Per text, whether the compiled reader of the reward's fast path reads it by itself (no Python
    fallback: the fallback here refuses everything)."""
    pack = TextPacker(PhysicsEngine(device="cpu")).pack(texts, lambda text: ParseError("left to the parser"))
    return np.asarray(pack.row) >= 0


def test_the_compiled_reader_compares_against_the_grammar_s_words():
    """The reader's keyword table is built from the grammar's names, in the reader's role order."""
    from physcene.kernels.ctrc_reader.codes import ENTRY_ROLES, TOP_ROLES, WORD_ROLES
    from physcene.reward import text_batch

    assert text_batch.ENTRY_KEYS == ENTRY_ROLES and text_batch.TOP_KEYS == TOP_ROLES
    assert (*text_batch.ZONE_WORDS, *text_batch.RELATIONS) == WORD_ROLES


# (a) writer -> parser ---------------------------------------------------------------------------
def test_writer_and_parser_round_trip_the_benchmark_scenes(records):
    for r in records:
        truth = load_layout(r["layout"]).by_id()
        scene = parse(r["completion"])
        assert not isinstance(scene, ParseError), scene.reason
        again = parse(completion_text(scene)).by_id()  # and once more through the writer
        assert sorted(truth) == sorted(again) == sorted(o.instance_id for o in scene.objects)
        for o in scene.objects:
            t, back = truth[o.instance_id], again[o.instance_id]
            assert o.center == pytest.approx(t.center, abs=1e-4) and o.size == pytest.approx(t.size, abs=1e-4)
            assert back.center == pytest.approx(o.center, abs=1e-4)
            assert back.size == pytest.approx(o.size, abs=1e-4)
            assert (back.parent, back.relation) == (o.parent, o.relation)


# (b) Python parser <-> compiled reader ------------------------------------------------------------
_LINE = re.compile(r"^    \{.*\}$", re.M)  # one object entry of the writer's layout


def _entry_lines(text: str) -> list[re.Match]:
    return [m for m in _LINE.finditer(text) if grammar.quoted(grammar.RELATIVE_BBOX) in m.group(0)]


def _replace_line(text: str, m: re.Match, entry: dict) -> str:
    line = json.dumps(entry, separators=(grammar.ITEM_SEPARATOR, grammar.KEY_SEPARATOR))
    return text[:m.start()] + "    " + line + text[m.end():]


def _mutations(kind: str, texts: list[str], rng: random.Random) -> list[str]:
    out = []
    for text in texts:
        layout = text.index(grammar.LAYOUT_HEADER)
        k = rng.randrange(layout, len(text))
        m = rng.choice(_entry_lines(text))
        entry = json.loads(m.group(0).strip())
        if kind == "deleted_character":
            out.append(text[:k] + text[k + 1:])
        elif kind == "duplicated_character":
            out.append(text[:k] + text[k] + text[k:])
        elif kind == "swapped_key_order":  # valid JSON, keys out of the writer's order
            keys = list(entry)
            i, j = rng.sample(range(len(keys)), 2)
            keys[i], keys[j] = keys[j], keys[i]
            out.append(_replace_line(text, m, {key: entry[key] for key in keys}))
        elif kind == "swapped_key_names":  # two values under each other's key
            a, b = rng.sample(list(grammar.ENTRY_KEYS[1:]), 2)
            entry[a], entry[b] = entry[b], entry[a]
            out.append(_replace_line(text, m, entry))
        elif kind == "number_over_limit":
            entry[grammar.RELATIVE_BBOX][rng.randrange(grammar.BOX_LENGTH)] = rng.choice(
                [1.5 * grammar.MAX_ABS_CM, -2.0 * grammar.MAX_ABS_CM])
            out.append(_replace_line(text, m, entry))
        elif kind == "too_many_decimals":  # more than the constraint lets a model write: still a layout
            entry[grammar.RELATIVE_ROTATION] = float(f"{entry[grammar.RELATIVE_ROTATION]:.0f}.123456789")
            out.append(_replace_line(text, m, entry))
        elif kind == "text_over_limit":
            out.append(text + " " * (grammar.MAX_CHARS - len(text) + 1))
        elif kind == "too_many_objects":
            copies = []
            for n in range(grammar.MAX_OBJECTS + 1 - len(_entry_lines(text))):
                copy = dict(entry, **{grammar.INSTANCE_ID: f"copy_{n}", grammar.PARENT_ID: grammar.TABLE,
                                      grammar.RELATION_TYPE: grammar.TABLE_RELATION, grammar.LAYER: 1})
                copies.append(json.dumps(copy))
            out.append(text[:m.end()] + grammar.ENTRY_SEPARATOR + grammar.ENTRY_SEPARATOR.join(copies)
                       + text[m.end():])
        else:
            raise ValueError(kind)
    return out


KINDS = ["deleted_character", "duplicated_character", "swapped_key_order", "swapped_key_names",
         "number_over_limit", "too_many_decimals", "text_over_limit", "too_many_objects"]


@pytest.mark.parametrize("kind", KINDS)
def test_parser_and_compiled_reader_accept_and_refuse_the_same_texts(records, kind):
    rng = random.Random(f"consumers-{kind}")
    texts = [r["completion"] for r in records]
    if kind in ("text_over_limit", "too_many_objects"):
        texts = texts[:3]  # large texts: a few suffice
    mutated = _mutations(kind, texts, rng)
    parsed = [parse(t) for t in mutated]
    python_ok = np.array([not isinstance(p, ParseError) for p in parsed])
    fast_ok = fast_path_reads(mutated)
    assert fast_path_reads(texts).all()  # the writer's own texts are the fast path's
    # the compiled reader never accepts what the parser refuses; what it leaves to the parser is read
    # there (the reward's pack), so both paths give the same verdict per text
    refused_by_python_only = [(k, parsed[k].reason) for k in np.nonzero(fast_ok & ~python_ok)[0]]
    assert not refused_by_python_only
    for k in np.nonzero(fast_ok)[0]:
        scene = parsed[k]
        assert scene is not None and not isinstance(scene, ParseError)


# (c) decoding constraint -> parser ----------------------------------------------------------------
def test_the_constraint_admits_every_character_of_real_completions(records):
    """Char by char: wherever a rule is in force, it admits the completion's next character."""
    for r in sorted(records, key=lambda r: len(r["completion"]))[:2]:
        text, listed, zone = r["completion"], listed_instance_ids(r["prompt"]), prompt_zone(r["prompt"])
        ruled = 0
        for i in range(len(text)):
            rule = constraint_rule(text[:i], listed, zone)
            if rule is not None:
                ruled += 1
                assert rule.admits(text[i]), (i, text[max(0, i - 60):i + 1])
        assert constraint_rule(text, listed, zone).pattern is None  # the end: only EOS may follow
        assert ruled > len(text) // 3


@pytest.mark.parametrize("greedy", [True, False])
def test_every_prefix_the_constraint_admits_continues_to_a_text_the_parser_accepts(records, greedy):
    """A tiny model of random logits decoded under the constraint: every prefix the constraint let it
    write continues to a finished text the parser accepts. The plan's wording is free text (the
    model's, not the format's), so the model is given the reference plan; the layout is its own."""
    # a vocabulary size no other test uses: the constraint caches its token index per tokenizer class,
    # name and size, and these unnamed tokenizers differ from the ones of tests/train/test_constrained.py
    tokenizer = build_tokenizer([r["prompt"] for r in records] + [r["completion"] for r in records],
                                vocab_size=640)
    gen = torch.Generator().manual_seed(3 + greedy)
    torch.manual_seed(3)
    model = torch.nn.Embedding(len(tokenizer), len(tokenizer))  # next-token logits of the last token
    torch.nn.init.normal_(model.weight, std=3.0, generator=gen)
    for r in sorted(records, key=lambda r: len(r["completion"]))[:1]:
        plan = r["completion"].split(grammar.LAYOUT_HEADER)[0].rstrip("\n")
        forced = tokenizer(plan, add_special_tokens=False)["input_ids"]
        proc = CTRCConstraint(tokenizer, [r["prompt"]], greedy=greedy)
        ids: list[int] = []
        for step in range(6000):
            last = ids[-1] if ids else tokenizer.pad_token_id
            scores = model(torch.tensor([last])).detach()
            if step < len(forced):
                scores[0, forced[step]] = 100.0
                scores[0, tokenizer.eos_token_id] = -1e9
            scores = proc(torch.tensor([[tokenizer.pad_token_id] + ids]), scores)
            t = (int(scores.argmax()) if greedy
                 else int(torch.multinomial(scores.softmax(-1), 1, generator=gen)))
            if t == tokenizer.eos_token_id:
                break
            ids.append(t)
        else:
            pytest.fail("no EOS")
        scene = parse(tokenizer.decode(ids))
        assert not isinstance(scene, ParseError), scene.reason
        assert sorted(o.instance_id for o in scene.objects) == sorted(listed_instance_ids(r["prompt"]))


# (d) one edit -----------------------------------------------------------------------------------
def test_the_constraint_and_spans_are_built_from_the_grammar():
    keys = constraint_grammar.ANCHOR.pattern
    for key in (grammar.INSTANCE_ID, grammar.RELATIVE_BBOX, grammar.RELATIVE_ROTATION, grammar.ZONE):
        assert key in keys
    assert spans.GEOMETRY_KEYS == (grammar.RELATIVE_BBOX, grammar.RELATIVE_ROTATION)
    rule = constraint_rule('{"layer": 1, "relative_rotation_deg":', None)
    assert grammar.NUMBER_PATTERN in rule.pattern
    decimals, digits = grammar.MAX_DECIMALS, grammar.INTEGER_DIGITS
    assert rule.admits(" 1." + "1" * decimals) and not rule.admits(" 1." + "1" * (decimals + 1))
    assert rule.admits(" " + "9" * digits) and not rule.admits(" " + "9" * (digits + 1))


_EDITED = """
import sys
from physcene.ctrc import completion_text, parse, ParseError
from physcene.ctrc.spans import numeric_spans, object_text_spans
from physcene.data import synthesize
from physcene.layout import load_layout
from physcene.train.constrained import constraint_rule, listed_instance_ids, prompt_zone

r = next(iter(synthesize("test", 1, seed=5)))

text = completion_text(parse(r["completion"]))
assert '"yaw_deg"' in text and "relative_rotation_deg" not in text, "writer"
assert "Put " in text and "Place" not in text, "writer: plan steps"
assert not isinstance(parse(text), ParseError), "parser"
start = text.index('"yaw_deg":')
assert any(a > start for a, _ in numeric_spans(text)), "spans: geometry numbers"
assert all(len(s) == 2 for s in object_text_spans(text)), "spans: plan steps found"
listed, zone = listed_instance_ids(r["prompt"]), prompt_zone(r["prompt"])
for i in range(len(text)):
    rule = constraint_rule(text[:i], listed, zone)
    assert rule is None or rule.admits(text[i]), ("constraint", i, text[max(0, i - 40):i + 1])
rule = constraint_rule(text[:start + len('"yaw_deg":')], listed, zone)
assert rule.admits(" 1.123") and not rule.admits(" 1.1234"), "constraint: MAX_DECIMALS"
print("followed")
"""


def test_a_key_a_verb_and_a_limit_changed_in_grammar_reach_every_consumer(tmp_path):
    """In a copy of the package, one edit each in grammar.py (the rotation key renamed, the plan's
    verb changed, MAX_DECIMALS lowered): the writer writes it, the parser reads it, the span finders
    and the constraint follow it."""
    copy = tmp_path / "repo"
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    for name in files.split():
        if not name.startswith(("docs/", "tests/", "benchmarks/")):
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(ROOT / name, copy / name)
    path = copy / "physcene" / "ctrc" / "grammar.py"
    source = path.read_text()
    for old, new in (('RELATIVE_ROTATION = "relative_rotation_deg"', 'RELATIVE_ROTATION = "yaw_deg"'),
                     ('PLACE = "Place"', 'PLACE = "Put"'), ("MAX_DECIMALS = 8", "MAX_DECIMALS = 3"),
                     ("DECIMALS = 5", "DECIMALS = 3")):
        assert source.count(old) == 1, old
        source = source.replace(old, new)
    path.write_text(source)
    done = subprocess.run([sys.executable, "-c", _EDITED], cwd=copy, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(copy), "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0 and "followed" in done.stdout, done.stderr[-2000:]
