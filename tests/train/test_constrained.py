"""CTRC-constrained decoding (train/constrained/): never blocks a valid completion, repairs the
failures a small model makes (repeated ids, broken numbers, a missing close), and plugs into HF generate."""

import random

import pytest
import torch
from omegaconf import OmegaConf
from transformers import GenerationConfig, LogitsProcessorList

from physcene.ctrc import ParseError, parse
from physcene.data import synthesize
from physcene.train.constrained import (
    CTRCConstraint,
    Rule,
    constraint_rule,
    listed_instance_ids,
    prompt_zone,
    sampling_warpers,
)
from physcene.train.constrained.grammar import may_end_anchor, planned_entries
from physcene.train.constrained.sampling import TokenIndex, vocabulary
from physcene.train.tokenizer import KINDS, build_tokenizer

PROMPT_TAIL = "**Object List**: mirror (1), tray (1), comb (2)\n\nFirst write"


@pytest.fixture(scope="module")
def records():
    return list(synthesize("train", 6, seed=3))


# every rule under each tokenizer kind; the kinds after the default run under --slow (the ctrc kind's
# constraint is also exercised end to end by tests/train/test_tokenizer_ctrc.py in every run)
@pytest.fixture(scope="module",
                params=[KINDS[0], *(pytest.param(k, marks=pytest.mark.slow) for k in KINDS[1:])])
def tokenizer(records, request):
    texts = [r["prompt"] for r in records] + [r["completion"] for r in records]
    return build_tokenizer(texts, vocab_size=600, kind=request.param)


# greedy; sampling that checks the candidates within a margin; sampling by rejection (warpers given)
MODES = {"greedy": {"greedy": True}, "candidates": {"greedy": False},
         "draw": {"greedy": False, "warpers": LogitsProcessorList()}}


def allowed(text: str, listed, candidate: str) -> bool:
    rule = constraint_rule(text, listed)
    return rule is None or rule.admits(candidate)


def test_listed_ids_follow_the_mesatask_naming(records):
    assert listed_instance_ids(PROMPT_TAIL) == ["1_mirror_0", "2_tray_0", "3_comb_0", "3_comb_1"]
    assert listed_instance_ids("no list here") is None
    for r in records:  # the data's own ids are exactly the listed ones
        scene = parse(r["completion"])
        assert sorted(listed_instance_ids(r["prompt"])) == sorted(o.instance_id for o in scene.objects)


@pytest.mark.parametrize("mode", list(MODES))
def test_reference_completions_pass_unchanged(records, tokenizer, mode):
    """Fed the true next token as the model's favourite, the processor never masks it out."""
    vocab = len(tokenizer)
    greedy = mode == "greedy"
    for r in records:
        ids = tokenizer(r["completion"], add_special_tokens=False)["input_ids"] + [tokenizer.eos_token_id]
        proc = CTRCConstraint(tokenizer, [r["prompt"]], top_k=8, **MODES[mode])
        prompt = torch.full((1, 3), tokenizer.pad_token_id)
        for k, t in enumerate(ids):
            scores = torch.randn(1, vocab)
            scores[0, t] = 50.0
            out = proc(torch.cat([prompt, torch.tensor([ids[:k]], dtype=torch.long)], 1), scores)
            assert out[0, t] == 50.0, (r["id"], repr(proc.texts[0][-60:]), repr(tokenizer.decode([t])))
        if greedy:  # the first choice was always allowed: no row was ever masked
            assert proc.stats.masked_steps == 0
        assert proc.stats.overruled == [[]]  # every token was the model's own choice


def test_repeated_instance_id_is_refused():
    listed = ["1_mirror_0", "2_tray_0", "3_comb_0"]
    text = ('**Sub-instruction:**\n1. Place 1_mirror_0 at the center.\n\n**Scene Layout:**\n{\n'
            '  "objects": [\n    {"layer": 0, "instance_id": "root_zone", "type": "zone", '
            '"bbox": [0.0, 9.0, 0.0, 9.0, 0.0, 0.0], '
            '"z_rotation": 0.0},\n    {"layer": 1, "instance_id": "1_mirror_0", "category": "mirror", '
            '"parent_id": "root_zone", "relation_type": "near", "description": "A mirror.", '
            '"relative_bbox": [1.0, 2.0, 1.0, 2.0, 0.0, 3.0], "relative_rotation_deg": 0.0},\n'
            '    {"layer": 1, "instance_id":')
    assert not allowed(text, listed, ' "1_mirror_0"')
    assert allowed(text, listed, ' "2_tray_0",') and allowed(text, listed, ' "3_co')
    assert not allowed(text, listed, ' "4_')
    # category and relation follow the id and the parent
    entry = text + ' "3_comb_0", "category":'
    assert allowed(entry, listed, ' "comb"') and not allowed(entry, listed, ' "tray"')
    parent = entry + ' "comb", "parent_id":'
    assert allowed(parent, listed, ' "1_mirror_0"') and allowed(parent, listed, ' "root_zone"')
    assert not allowed(parent, listed, ' "2_tray_0"')  # not placed yet
    assert not allowed(parent, listed, ' "3_comb_0"')  # itself
    relation = parent + ' "1_mirror_0", "relation_type":'
    assert allowed(relation, listed, ' "on"') and not allowed(relation, listed, ' "near"')
    table = parent + ' "root_zone", "relation_type":'
    assert allowed(table, listed, ' "near"') and not allowed(table, listed, ' "in"')


PLAN = ("**Sub-instruction:**\n1. Place 2_tray_0 at the center of the table.\n2. Place 3_comb_0 on 2_tray_0."
        "\n3. Place 3_comb_1 in 1_mirror_0."
        "\n4. Place 1_mirror_0 behind 2_tray_0, about 20 cm away, at the back of the table."
        '\n\n**Scene Layout:**\n{\n  "objects": [\n'
        '    {"layer": 0, "instance_id": "root_zone", "type": "zone", '
        '"bbox": [0.0, 9.0, 0.0, 9.0, 0.0, 0.0], "z_rotation": 0.0},\n    {"layer": 1, "instance_id":')
TRAY = (' "2_tray_0", "category": "tray", "parent_id": "root_zone", "relation_type": "near", "description": '
        '"A tray.", "relative_bbox": [1.0, 5.0, 1.0, 5.0, 0.0, 1.0], "relative_rotation_deg": 0.0},\n'
        '    {"layer": 2, "instance_id":')


def test_the_layout_follows_its_plan():
    """Order, parent and relation of each entry are the ones its plan step names (physcene.ctrc writes
    both in Algorithm 1's order); ``follow_plan=False`` leaves them to the model."""
    listed = ["1_mirror_0", "2_tray_0", "3_comb_0", "3_comb_1"]
    plan = planned_entries(PLAN, listed)
    assert [(e.iid, e.parent, e.relation) for e in plan] == [
        ("2_tray_0", "root_zone", "near"), ("3_comb_0", "2_tray_0", "on"),
        ("3_comb_1", None, None), ("1_mirror_0", "root_zone", "near")]  # 3's parent comes after it

    def admits(text, added, follow_plan=True):
        rule = constraint_rule(text, listed, None, follow_plan)
        return rule is None or rule.admits(added)

    assert admits(PLAN, ' "2_tray_0"') and not admits(PLAN, ' "1_mirror_0"')
    assert admits(PLAN, ' "1_mirror_0"', follow_plan=False)
    comb = PLAN + TRAY
    assert admits(comb, ' "3_comb_0"') and not admits(comb, ' "3_comb_1"')
    parent = comb + ' "3_comb_0", "category": "comb", "parent_id":'
    assert admits(parent, ' "2_tray_0"') and not admits(parent, ' "root_zone"')
    assert admits(parent, ' "root_zone"', follow_plan=False)
    relation = parent + ' "2_tray_0", "relation_type":'
    assert admits(relation, ' "on"') and not admits(relation, ' "in"')
    assert admits(relation, ' "in"', follow_plan=False)
    # a step whose parent is not placed before it leaves the parent to the model (any earlier entry)
    free = (relation + ' "on", "description": "A comb.", "relative_bbox": [1.0, 2.0, 1.0, 2.0, 0.0, 1.0], '
            '"relative_rotation_deg": 0.0},\n    {"layer": 2, "instance_id":')
    assert admits(free, ' "3_comb_1"') and not admits(free, ' "1_mirror_0"')
    free += ' "3_comb_1", "category": "comb", "parent_id":'
    assert admits(free, ' "2_tray_0"') and admits(free, ' "root_zone"') and admits(free, ' "3_comb_0"')
    # a plan that does not name every listed id once is not followed
    assert planned_entries(PLAN.replace("4. Place 1_mirror_0", "4. Place 3_comb_0"), listed) is None
    assert planned_entries(PLAN.split("**Scene")[0], listed) is None  # no layout yet


def test_a_plan_step_is_plain_words_up_to_its_full_stop():
    """A sampled plan step once ran on into `... "parent_id": "root_zone", ...`: a JSON key inside the plan
    started the layout's rules there and the layout's header was never written (no layout parsed).
    After its id a step holds no quote, brace or line break, and at most PLAN_STEP_MAX_CHARS of them."""
    listed = ["1_mirror_0", "2_tray_0"]
    step = "**Sub-instruction:**\n1. Place 2_tray_0 to the left of the table"
    assert allowed(step, listed, ", about 20 cm away.") and allowed(step, listed, " 1_mirror_0")
    for bad in (' "parent_id":', " {", "}", "\n"):
        assert not allowed(step, listed, bad), bad
    assert allowed(step, listed, " " + "x" * 200) and not allowed(step, listed, " " + "x" * 300)
    assert not allowed("**Sub-instruction:**\n1. Place", listed, " 3_comb_0 at")  # ids of the list only


def test_synthesised_completions_follow_their_plans(records):
    for r in records:
        listed = listed_instance_ids(r["prompt"])
        plan = planned_entries(r["completion"], listed)
        scene = parse(r["completion"])
        assert [e.iid for e in plan] == [o.instance_id for o in scene.objects]
        for e, o in zip(plan, scene.objects):
            assert (e.parent, e.relation) == (o.parent, o.relation if o.parent != "root_zone" else "near")


def test_numbers_and_entry_ends():
    listed = ["1_mirror_0"]
    box = '{"layer": 0, "instance_id": "root_zone", "type": "zone", "bbox":'
    assert allowed(box, listed, " [10.0")
    assert not allowed(box, listed, " [10.0.")   # 10.0.141
    assert not allowed(box, listed, " [.7")      # .7.0718
    assert not allowed(box, listed, " [1.0, , ")
    assert not allowed(box, listed, " [1.0, 2.0]")  # six numbers, not two
    rot = '"instance_id": "root_zone", "type": "zone", "z_rotation":'
    assert allowed(rot, listed, ' 0.0},\n    {"layer": 1, "instance_id":')
    assert not allowed(rot, listed, " 0.0}\n  ],")  # ids left: the array may not close
    last = rot.replace("root_zone", "1_mirror_0") + ' 0.0'
    text = '"instance_id": "root_zone", ' + last
    assert allowed(text, listed, '}\n  ],\n  "item_placement_zone":')
    assert not allowed(text, listed, "},")
    assert not allowed(text, listed, '} 1instance_1')


def test_boxes_keep_each_max_above_its_min():
    """The parser refuses a non-positive extent: a max that cannot exceed its min is refused while
    it is written, not after."""
    box = '"relation_type": "near", "description": "A mirror.", "relative_bbox": [5.0, '
    assert allowed(box, None, "5.1, ") and allowed(box, None, "5") and allowed(box, None, "5.0")
    assert allowed(box, None, "5.00001,") and allowed(box, None, "12")
    assert not allowed(box, None, "4.9") and not allowed(box, None, "5,") and not allowed(box, None, "5.0,")
    assert not allowed(box, None, "-") and not allowed(box, None, "0.")
    neg = box.replace("[5.0, ", "[1.0, 2.0, -3.0, ")
    assert allowed(neg, None, "-") and allowed(neg, None, "-2") and allowed(neg, None, "-2.9,")
    assert not allowed(neg, None, "-3") and not allowed(neg, None, "-4") and not allowed(neg, None, "-3.0,")
    z = box.replace("[5.0, ", "[1.0, 2.0, 1.0, 2.0, 3.0, ")
    assert allowed(z, None, "4.0]") and not allowed(z, None, "3.0]")
    zone = '"relative_rotation_deg": 0.0}\n  ],\n  "item_placement_zone":'
    assert allowed(zone, None, " [0.0, 150.0, 0.0, 92.7]\n}\n")
    assert not allowed(zone, None, " [0.0, 150.0, 92.7, 0.0]")
    assert not allowed(box, None, "123456.0")  # over MAX_ABS_CM
    # a max written to MAX_DECIMALS can grow no further: it must exceed its min already
    eight = box.replace("[5.0, ", "[1.06386999, ")
    assert not allowed(eight, None, "1.0638699") and not allowed(eight, None, "1.06386999")
    assert allowed(eight, None, "1.06387") and allowed(eight, None, "1.0638700,")
    start = box[:box.index(" [5.0")]  # a min no max can exceed is refused too
    assert allowed(start, None, " [9999.9999999") and not allowed(start, None, " [9999.99999999")


def test_a_box_never_reaches_a_dead_end():
    """Every prefix the rule admits has a character that continues it. At a dead end the mask gives
    up and the model's own token follows: a PADA-trained small model wrote a max of ``1.06386999`` over
    a min of ``1.06386999`` (eight decimals, no digit may follow) and 15 of 200 test layouts failed
    to parse. A random walk over the box's characters, copying the min's digits into the max most
    of the time, where that dead end lay."""
    rng = random.Random(0)
    box = '"relation_type": "near", "description": "A mirror.", "relative_bbox":'
    chars = "0123456789.-, []"
    for _ in range(120):
        written = ""
        while not written.endswith("]"):
            ok = [c for c in chars if allowed(box, None, written + c)]
            assert ok, f"dead end after {written!r}"
            parts = written[written.find("[") + 1:].split(",")
            low, high = (parts[-2].strip(), parts[-1].lstrip()) if len(parts) % 2 == 0 else ("", "")
            copy = low[len(high)] if len(high) < len(low) else None
            written += copy if copy in ok and rng.random() < 0.8 else rng.choice(ok)


def test_entry_keys_and_the_end_of_the_completion_are_fixed():
    listed = ["1_mirror_0"]
    start = '**Scene Layout:**\n{\n  "objects": [\n    {"layer": 0, "instance_id":'
    assert allowed(start, listed, ' "root_zone", "type": "zone", "bbox":')
    assert not allowed(start, listed, ' "root_zone", "category":')
    entry = (start + ' "root_zone", "type": "zone", "bbox": [0, 9, 0, 9, 0, 0], "z_rotation": 0.0},'
             '\n    {"layer": 1, "instance_id":')
    assert allowed(entry, listed, ' "1_mirror_0", "category":')
    assert not allowed(entry, listed, ' "1_mirror_0", "parent_id":')
    relation = entry + ' "1_mirror_0", "category": "mirror", "parent_id": "root_zone", "relation_type":'
    assert allowed(relation, listed, ' "near", "description": "A round \\"mirror\\".", "relative_bbox":')
    assert not allowed(relation, listed, ' "near", "relative_bbox":')  # no description
    assert not allowed(relation, listed, ' "near", "description": "A "mirror"')  # unescaped quote
    assert not allowed(relation, listed, ' "near", "description": "A mirror\n')
    end = '"item_placement_zone": [0.0, 150.0, 0.0, 92.7]\n}\n'
    rule = constraint_rule(end, listed)
    assert rule is not None and rule.pattern is None and not rule.admits(" ")  # EOS only


def test_plan_places_each_listed_object_once_then_starts_the_layout():
    listed = ["1_mirror_0", "2_tray_0"]
    text = "**Sub-instruction:**\n1. Place 1_mirror_0 at the center of the table.\n2. Place"
    assert not allowed(text, listed, " 1_mirror_0 ")
    assert allowed(text, listed, " 2_tray_0 to the left")
    done = text + " 2_tray_0 to the left of 1_mirror_0."
    assert not allowed(done, listed, "\n3. Place")
    assert allowed(done, listed, '\n\n**Scene Layout:**\n{\n  "objects": [\n    {"layer": 0, "instance_id":')
    early = "**Sub-instruction:**\n1. Place 1_mirror_0 at the center of the table."
    assert allowed(early, listed, "\n2. Place") and not allowed(early, listed, "\n\n**Scene")


def test_left_padded_batches_keep_each_rows_text(records, tokenizer):
    """Rows of different prompt lengths share one padded prompt length; each row's text is its own."""
    texts = [r["completion"][:300] for r in records[:3]]
    ids = [tokenizer(t, add_special_tokens=False)["input_ids"] for t in texts]
    n = min(len(i) for i in ids)
    proc = CTRCConstraint(tokenizer, [r["prompt"] for r in records[:3]])
    prompt = torch.full((3, 5), tokenizer.pad_token_id)
    for k in range(n + 1):
        step = torch.tensor([row[:k] for row in ids], dtype=torch.long)
        proc(torch.cat([prompt, step], 1), torch.zeros(3, len(tokenizer)))
    assert proc.texts == [tokenizer.decode(row[:n]) for row in ids]
    with pytest.raises(ValueError, match="3 prompts"):
        proc(torch.zeros(2, 9, dtype=torch.long), torch.zeros(2, len(tokenizer)))


def test_generate_runs_constrained_and_parses_a_forced_completion(records, tokenizer):
    """HF generate with the processor: a model that always prefers repeating the first entry's id
    still writes a layout with every listed id once (the processor overrules it)."""
    from physcene.config import load_config
    from physcene.train.generate import generate_token_ids
    from physcene.train.models import build_scratch_model

    cfg = load_config("train_tiny")
    model = build_scratch_model(cfg.model.arch, tokenizer, seed=0, dtype="float32").eval()
    prompts = [r["prompt"] for r in records[:2]]
    plain = generate_token_ids(model, tokenizer, prompts, max_new_tokens=12, batch_size=2)
    same = generate_token_ids(model, tokenizer, prompts, max_new_tokens=12, batch_size=2, constrained=True)
    assert plain == same  # random text never reaches an anchor: the processor leaves it alone

    # A scripted model: it prefers the text of a completion whose second object repeats the first
    # one's id (what `small` does), and otherwise the reference completion.
    r = next(r for r in records if len(listed_instance_ids(r["prompt"])) >= 2)
    first, second = listed_instance_ids(r["prompt"])[:2]
    reference = r["completion"]
    broken = reference.replace(f'"instance_id": "{second}"', f'"instance_id": "{first}"')
    assert isinstance(parse(broken), ParseError)  # the repeated id alone breaks the layout
    proc = CTRCConstraint(tokenizer, [r["prompt"]])
    vocab, text, out, changed = len(tokenizer), "", [], []
    for _ in range(2 * len(tokenizer(reference)["input_ids"])):
        scores = torch.full((1, vocab), -10.0)
        for script, bonus in ((reference, 5.0), (broken, 10.0)):  # later wins
            if not script.startswith(text):
                continue
            rest = script[len(text):]
            if not rest:
                scores[0, tokenizer.eos_token_id] = 100.0
            for t in range(vocab):
                piece = proc.token_text[t]
                if piece and rest.startswith(piece):
                    scores[0, t] = bonus + len(piece)
        favourite = int(scores.argmax())
        scores = proc(torch.tensor([[tokenizer.pad_token_id] + out], dtype=torch.long), scores)
        t = int(scores.argmax())
        if t != favourite:
            changed.append(len(out))  # the completion position of the token the constraint chose
        if t == tokenizer.eos_token_id:
            break
        out.append(t)
        text += proc.token_text[t]
    assert proc.stats.masked_steps >= 1
    assert proc.stats.overruled == [changed] and changed  # exactly the positions where it overruled the model
    scene = parse(text)
    assert not isinstance(scene, ParseError), scene
    assert sorted(o.instance_id for o in scene.objects) == sorted(listed_instance_ids(r["prompt"]))


def test_the_zone_is_copied_from_the_prompt(records):
    prompt = records[0]["prompt"]
    zone = prompt_zone(prompt)
    assert zone is not None and zone[0] < zone[1] and zone[2] < zone[3]
    assert prompt_zone("**item_placement_zone**: [0.0, 120.5, 0.0, 60.0] (cm)") == [0.0, 120.5, 0.0, 60.0]
    for bad in ("no zone", "**item_placement_zone**: [0.0, 1.0, 0.0]",
                "**item_placement_zone**: [5, 1, 0, 2]", "**item_placement_zone**: [0, nope, 0, 2]"):
        assert prompt_zone(bad) is None, bad
    listed, zone = ["1_mirror_0"], [0.0, 120.5, 0.0, 60.0]
    root = ('**Scene Layout:**\n{\n  "objects": [\n'
            '    {"layer": 0, "instance_id": "root_zone", "type": "zone", "bbox":')

    def admitted(text, added, zone):
        rule = constraint_rule(text, listed, zone)
        return rule is None or rule.admits(added)

    assert admitted(root, ' [0.0, 120.5, 0.0, 60.0, 0.0, 0.0], "z_rotation":', zone)
    assert not admitted(root, " [0.0, 137", zone)  # the model's own guess: refused
    assert admitted(root, " [0.0, 137", None)  # no zone given: the number grammar only
    end = '\n  ],\n  "item_placement_zone":'
    assert admitted(end, " [0.0, 120.5, 0.0, 60.0]\n}\n", zone)
    assert not admitted(end, " [0.0, 120.5, 0.0, 60.0]\n}\nmore", zone)  # the completion's end
    assert not admitted(end, " [0.0, 150.0", zone)
    rule = constraint_rule(end + " [0.0, 120.5, 0.0, 60.0]\n}\n", listed, zone)
    assert rule is not None and rule.pattern is None  # EOS only


def _random_logits_run(record, tokenizer, mode: str):
    """The token ids (and the processor) of a completion of ``record``'s prompt under ``mode`` by a
    model whose logits are noise (3 x N(0, 1)), forced through the reference plan: every layout token
    is a wrong guess the constraint must overrule. The same noise for the same record and mode."""
    vocab = len(tokenizer)
    greedy = mode == "greedy"
    gen = torch.Generator().manual_seed(7 + greedy)
    torch.manual_seed(7)  # the draws of the rejection mode
    plan = record["completion"].split("**Scene Layout:**")[0].rstrip("\n")
    forced = tokenizer(plan, add_special_tokens=False)["input_ids"]
    proc = CTRCConstraint(tokenizer, [record["prompt"]], **MODES[mode])
    ids: list[int] = []
    for step in range(4000):
        scores = 3.0 * torch.randn(1, vocab, generator=gen)
        if step < len(forced):
            scores[0, forced[step]] = 100.0
            scores[0, tokenizer.eos_token_id] = -1e9
        scores = proc(torch.tensor([[tokenizer.pad_token_id] + ids], dtype=torch.long), scores)
        probs = scores.softmax(-1)
        t = int(scores.argmax()) if greedy else int(torch.multinomial(probs, 1, generator=gen))
        if t == tokenizer.eos_token_id:
            break
        ids.append(t)
    return ids, proc


@pytest.mark.parametrize("mode", list(MODES))
def test_literal_rules_scan_only_the_tokens_that_fit_and_allow_the_same(records, tokenizer, mode,
                                                                        monkeypatch):
    """A vocabulary scan under a literal rule (the copied zone, ids, the layout's start) checks only
    the tokens whose text fits one of its strings: a model of noise, which needs a scan at nearly
    every such token, writes the very same completion as with every token of the vocabulary checked."""
    record = min(records, key=lambda r: len(r["completion"]))
    indexed, proc = _random_logits_run(record, tokenizer, mode)
    assert proc.stats.indexed_scans > 10 and proc.stats.indexed_scans <= proc.stats.vocabulary_scans
    monkeypatch.setattr(TokenIndex, "literal_candidates", lambda self, rule: None)
    scanned, plain = _random_logits_run(record, tokenizer, mode)
    assert plain.stats.indexed_scans == 0 and plain.stats.vocabulary_scans == proc.stats.vocabulary_scans
    assert indexed == scanned


def test_a_literal_rules_candidates_hold_every_token_it_admits(tokenizer):
    """``TokenIndex.literal_candidates`` is a superset of what the rule admits, on open and closed
    literal rules part-way through their strings, and gives up (None) where any token may fit."""
    index = vocabulary(tokenizer)
    texts = index.texts
    zone = " [0.0, 113.7, 0.0, 48.25, 0.0, 0.0], \"z_rotation\":"
    copies = [Rule(zone[:k], "", choices=(zone,)) for k in (0, 1, 5, 12, len(zone) - 3)]
    steps = (" 2_cup_0 ", " 2_cup_0.", " 2_cup_1 ", " 2_cup_1.")
    rules = [*copies, Rule(" 2_", "", choices=steps),
             Rule(" 2_cup_0", "", choices=steps),  # tokens that run past the id (" the", ". ") fit too
             Rule(" [1.5, 2", "", choices=(" [1.5, 2.5, 0.0, 1.0]\n}\n",), closed=True)]
    for rule in rules:
        candidates = set(index.literal_candidates(rule))
        admitted = {t for t, text in enumerate(texts) if text and rule.admits(text)}
        assert admitted and admitted <= candidates, rule.partial
        if rule in copies:
            assert len(candidates) < len(texts) // 20  # a handful, not the vocabulary
    assert len({t for t in index.literal_candidates(rules[-2]) if len(texts[t]) > 1}) > 10
    assert index.literal_candidates(Rule("", r"\d+")) is None  # a regex rule: scan the vocabulary
    assert index.literal_candidates(None) is None


@pytest.mark.parametrize("mode", list(MODES))
def test_a_model_of_random_logits_still_writes_layouts_that_parse(records, tokenizer, mode):
    """Everything in the layout constrained: given the reference plan, a model whose logits are noise
    (every token a wrong guess: keys broken across tokens, leading zeros, bad escapes, a max below its
    min, numbers that never end) still writes a layout the parser accepts."""
    for r in sorted(records, key=lambda r: len(r["completion"]))[:2]:
        ids, _ = _random_logits_run(r, tokenizer, mode)
        text = tokenizer.decode(ids)
        scene = parse(text)
        assert not isinstance(scene, ParseError), (scene.reason, text[-400:])
        assert sorted(o.instance_id for o in scene.objects) == sorted(listed_instance_ids(r["prompt"]))
        # the layout follows the (reference) plan: the reference's order, parents and relations
        reference = parse(r["completion"])
        assert ([(o.instance_id, o.parent, o.relation) for o in scene.objects]
                == [(o.instance_id, o.parent, o.relation) for o in reference.objects])
        # the zone is the prompt's, in the root entry and at the end, whatever the logits said
        zone = prompt_zone(r["prompt"])
        assert scene.zone.to_list() == pytest.approx(zone)
        assert f'"bbox": [{", ".join(str(v) for v in zone)}, 0.0, 0.0]' in text


def _replay(proc, tokenizer, text: str, rows: int):
    """Input ids that hand ``proc`` the completion ``text`` so far of ``rows`` identical rows at its
    next call (a first call sees the prompt alone)."""
    ids = tokenizer(text, add_special_tokens=False)["input_ids"]
    prompt = torch.full((rows, 2), tokenizer.pad_token_id)
    proc(prompt, torch.zeros(rows, len(tokenizer)))
    return torch.cat([prompt, torch.tensor([ids] * rows, dtype=torch.long)], 1)


def test_rejection_draws_sample_the_allowed_part_of_the_distribution(records, tokenizer):
    """With warpers, what ``generate`` samples after the processor is an exact sample of the model's
    (warped) distribution restricted to the allowed tokens: 4,000 rows, once where most of the
    vocabulary is allowed (a description: accepted draws) and once where two tokens are (after
    ``"relation_type":``: draws refused, then the allowed set)."""
    r = min(records, key=lambda r: len(r["completion"]))
    start = r["completion"].index('"description": "') + len('"description": "')
    for cut in (start, r["completion"].index('"relation_type":') + len('"relation_type":')):
        rows = 4000
        proc = CTRCConstraint(tokenizer, [r["prompt"]] * rows, greedy=False, warpers=sampling_warpers(
            GenerationConfig(do_sample=True, temperature=0.7, top_k=0)))
        step = _replay(proc, tokenizer, r["completion"][:cut], rows)
        gen = torch.Generator().manual_seed(0)
        logits = torch.randn(len(tokenizer), generator=gen) * 2.0
        probe = CTRCConstraint(tokenizer, [r["prompt"]])
        rule = probe._advance(_replay(probe, tokenizer, r["completion"][:cut], 1))[0]
        allowed_ids = probe.allowed_tokens(0, rule, range(len(tokenizer)))
        assert 2 <= len(allowed_ids) < len(tokenizer) - 2
        torch.manual_seed(1)
        out = proc(step, logits.repeat(rows, 1))
        picked = torch.multinomial((out / 0.7).softmax(-1), 1).flatten()  # what generate does next
        counts = torch.bincount(picked, minlength=len(tokenizer)).float()
        assert counts.sum() == counts[allowed_ids].sum()  # nothing refused comes through
        # accepted draws need no scan; where two tokens are allowed some rows exhaust their draws
        assert (proc.stats.vocabulary_scans > 0) == (len(allowed_ids) < len(tokenizer) // 2)
        assert 0 <= proc.stats.scan_seconds <= proc.stats.seconds
        p = (logits / 0.7).softmax(-1)[allowed_ids]
        p = p / p.sum()
        freq = counts[allowed_ids] / rows
        tolerance = 4 * (p * (1 - p) / rows).sqrt() + 1e-3
        assert ((freq - p).abs() <= tolerance).all(), (freq, p)


def test_only_eos_follows_the_finished_layout(records, tokenizer):
    r = records[0]
    for mode, kwargs in MODES.items():
        proc = CTRCConstraint(tokenizer, [r["prompt"]], **kwargs)
        step = _replay(proc, tokenizer, r["completion"], 1)
        scores = torch.zeros(1, len(tokenizer))
        scores[0, tokenizer.eos_token_id] = -5.0  # the model would rather go on
        torch.manual_seed(0)
        out = proc(step, scores)
        assert torch.isfinite(out[0]).nonzero().flatten().tolist() == [tokenizer.eos_token_id], mode


def test_sampling_warpers_rebuild_what_generate_applies():
    assert sampling_warpers(GenerationConfig(do_sample=False)) is None
    assert sampling_warpers(GenerationConfig(do_sample=True, typical_p=0.9)) is None  # not rebuilt
    kinds = [type(w).__name__ for w in sampling_warpers(
        GenerationConfig(do_sample=True, temperature=0.5, top_k=20, top_p=0.9, min_p=0.05))]
    assert kinds == ["TemperatureLogitsWarper", "TopKLogitsWarper", "TopPLogitsWarper", "MinPLogitsWarper"]
    assert len(sampling_warpers(GenerationConfig(do_sample=True, temperature=1.0, top_k=0))) == 0


@pytest.mark.parametrize("mode", list(MODES))
def test_the_rule_kept_between_steps_is_the_rule_of_the_whole_text(records, tokenizer, mode):
    """The processor keeps each row's anchor and skips the anchor search for tokens that cannot end one
    (a layout's decimal points) and the rule match for text its last step admitted; at every step of
    a noisy model's generation its rule equals the one found from scratch in the text so far."""
    vocab = len(tokenizer)
    gen = torch.Generator().manual_seed(11)
    torch.manual_seed(11)
    r = min(records, key=lambda r: len(r["completion"]))
    plan = r["completion"].split("**Scene Layout:**")[0].rstrip("\n")
    forced = tokenizer(plan, add_special_tokens=False)["input_ids"]
    proc = CTRCConstraint(tokenizer, [r["prompt"]], **MODES[mode])
    kept = []
    advance = proc._advance
    proc._advance = lambda input_ids: kept.append(advance(input_ids)) or kept[-1]
    ids: list[int] = []
    compared = 0
    for step in range(3000):
        scores = 4.0 * torch.randn(1, vocab, generator=gen)
        if step < len(forced):  # the reference plan, then noise: the layout is all the constraint's
            scores[0, forced[step]] = 100.0
        scores = proc(torch.tensor([[tokenizer.pad_token_id] + ids], dtype=torch.long), scores)
        if kept[-1]:
            scratch = constraint_rule(proc.texts[0], proc.listed[0], proc.zones[0])
            assert kept[-1][0] == scratch, proc.texts[0][-80:]
            compared += kept[-1][0] is not None
        probs = scores.softmax(-1)
        t = int(scores.argmax()) if mode == "greedy" else int(torch.multinomial(probs, 1, generator=gen))
        if t == tokenizer.eos_token_id:
            break
        ids.append(t)
    assert compared > 100  # the comparison ran inside rules, not only in free text
    # a decimal point inside the layout starts no anchor search; the "." that ends a plan line does
    assert not may_end_anchor('**Scene Layout:**\n{"objects": [{"bbox": [12', ".")
    assert may_end_anchor("1. Place 1_mirror_0 on the table\n2. Place 2_tray_0 near it", ".")
    assert not may_end_anchor("1. Place 1_mirror_0 on the table\n2", ".")


@pytest.mark.parametrize("kind", KINDS)
def test_the_trie_scan_allows_exactly_what_checking_every_token_does(kind):
    """A regex rule's vocabulary scan walks the vocabulary's trie and checks only the tokens under the
    prefixes its pattern can continue: at every regex-ruled position of real completions, and off them
    (a random allowed token after a true prefix, then a few more), under a 4,096-token vocabulary with
    some tokens already at -inf, it allows exactly the tokens that checking every token allows."""
    records = list(synthesize("train", 32, seed=5))
    tokenizer = build_tokenizer([r["prompt"] for r in records] + [r["completion"] for r in records],
                                vocab_size=4096, kind=kind)
    vocab = len(tokenizer)
    rng = random.Random(kind)
    gen = torch.Generator().manual_seed(0)

    def same_as_every_token(proc, rule, keep: int = 0) -> list[int]:
        scores = torch.zeros(1, vocab).masked_fill_(torch.rand(1, vocab, generator=gen) < 0.1, float("-inf"))
        scores[0, keep] = 0.0  # the true token stays finite
        every = proc.allowed_tokens(0, rule, torch.isfinite(scores[0]).nonzero().flatten().tolist())
        assert proc.allowed_in_vocabulary(0, rule, scores) == every, (rule.partial, rule.pattern)
        assert proc.stats.trie_scans == proc.stats.vocabulary_scans  # the trie did the scan
        checked.append(len(every))
        return every

    def regex(rule) -> bool:
        return rule is not None and rule.pattern is not None and not rule.choices

    checked: list[int] = []  # the allowed set's size at each position checked
    for r in sorted(records, key=lambda r: len(r["completion"]))[:2]:
        ids = tokenizer(r["completion"], add_special_tokens=False)["input_ids"]
        proc = CTRCConstraint(tokenizer, [r["prompt"]])
        rule, ruled = proc.advance_row(0, []), []
        for k, t in enumerate(ids):
            if regex(rule):
                assert t in same_as_every_token(proc, rule, keep=t)
                ruled.append(k)
            rule = proc.advance_row(0, [t])
        for k in rng.sample(ruled, 20):  # corrupted prefixes: a random allowed token, then a few more
            proc = CTRCConstraint(tokenizer, [r["prompt"]])
            rule = proc.advance_row(0, ids[:k])
            for _ in range(4):
                allowed_ids = same_as_every_token(proc, rule) if regex(rule) else []
                if not allowed_ids:  # out of the regex rules, or all it allows is at -inf
                    break
                rule = proc.advance_row(0, [rng.choice(allowed_ids)])
    assert len(checked) > 300 and min(checked) <= 2 and max(checked) > vocab // 2


def test_a_token_inside_its_rule_takes_the_short_step_to_the_same_rule(records, tokenizer):
    """``advance_within_rule`` (the fast decoder's step for a row under a rule) against the general
    step (``allowed_tokens`` + ``advance_row``), side by side on two constraints: along real completions
    and along noisy ones (a random token offered before every tenth true one), it gives the same rule
    and text wherever it takes the step (a token that may end an anchor too, through one anchor
    search), declines every token the rule refuses, and takes every other ruled step but EOS."""
    gen = random.Random(7)
    vocab = len(tokenizer)
    taken = declined = refused = across = 0
    for r in records[:3]:
        ids = tokenizer(r["completion"], add_special_tokens=False)["input_ids"]
        for noisy in (False, True):
            short, general = (CTRCConstraint(tokenizer, [r["prompt"]]) for _ in range(2))
            rule = general.advance_row(0, [])
            assert short.advance_row(0, []) == rule
            for k, true in enumerate(ids):
                offered = [gen.randrange(vocab), true] if noisy and k % 10 == 9 else [true]
                for t in offered:  # the first token the general step admits is the row's
                    if rule is None:  # free text: advance_free_text's step, not this one
                        rule = general.advance_row(0, [t])
                        short.advance_row(0, [t])
                        break
                    stepped = short.advance_within_rule(0, rule, t)
                    admitted = bool(general.allowed_tokens(0, rule, [t]))
                    if stepped is False:
                        declined += 1
                        assert not admitted or t == tokenizer.eos_token_id
                        if not admitted:
                            refused += 1
                            continue
                        rule = general.advance_row(0, [t])
                        short.advance_row(0, [t])
                        break
                    taken += 1
                    across += may_end_anchor(general.texts[0], general.token_text[t])
                    assert admitted, (general.texts[0][-60:], general.token_text[t])
                    rule = general.advance_row(0, [t])
                    assert stepped == rule and short.texts == general.texts
                    break
                assert short.texts == general.texts
    # declined: only what the general step refuses
    assert declined == refused > 10 and across > 50
    # the short step's test of a token that may end an anchor: its flag, or a text that ends "Place"
    index = vocabulary(tokenizer)
    texts = [r["completion"][:k] for r in records[:2] for k in range(0, len(r["completion"]), 37)]
    for text in texts + ["\n2. P", "\n2. Pl", "\n2. Pla", "\n2. Plac", "\n2. Place", "1. Place 1_x_0 on"]:
        for t, added in enumerate(index.texts):
            if added and may_end_anchor(text, added):
                assert index.may_end[t] or text.endswith("Place"), (text[-20:], added)


def test_overruled_stop_stops_with_a_checkpoint_once_the_mean_share_passes_its_bound():
    """OverruledStop averages constraint/overruled_frac over its last `steps` logs and, past the
    bound, stops the run and asks for a save, once; a log without the share is ignored."""
    from transformers import TrainerControl, TrainerState

    from physcene.train.constrained_rollouts import OverruledStop
    from physcene.train.pada import overruled_stop

    stop, state, control = OverruledStop(0.2, steps=3), TrainerState(), TrainerControl()
    for step, share in enumerate([0.01, 0.05, 0.5, 0.02, 0.4], start=1):  # means .19, .19, .31
        state.global_step = step
        stop.on_log(None, state, control, logs={"constraint/overruled_frac": share, "loss": 0.1})
        stop.on_log(None, state, control, logs={"loss": 0.1})
        assert control.should_training_stop == (step == 5) and stop.stopped_at == (5 if step == 5 else None)
    assert control.should_save
    with pytest.raises(ValueError, match="share of the sampled tokens in \\(0, 1\\), got 1.5"):
        OverruledStop(1.5)
    on = OmegaConf.create({"stop_overruled": 0.2, "stop_overruled_steps": 4, "constrained": True})
    assert [s.recent.maxlen for s in overruled_stop(on)] == [4]
    assert overruled_stop(OmegaConf.merge(on, {"constrained": False})) == []
    assert overruled_stop(OmegaConf.merge(on, {"stop_overruled": None})) == []


def _regex_admits(rule: Rule, added: str) -> bool:
    """:meth:`Rule.admits` by ``regex`` partial matching over the whole text since the anchor (what it
    did before the automata): the reference the automata must equal."""
    from physcene.train.constrained.grammar import _compiled, _extents_possible

    if rule.pattern is None:
        return False
    text = rule.partial + added
    if rule.choices:
        after = rule.after_choice()
        return any(c.startswith(text) or not rule.closed and text.startswith(c) and (
            after is None or _compiled(after).fullmatch(text, partial=True, pos=len(c)) is not None)
            for c in rule.choices)
    if _compiled(rule.pattern).fullmatch(text, partial=True) is None:
        return False
    return not rule.ordered or _extents_possible(text, rule.ordered)


def test_the_rules_automata_answer_what_regex_partial_matching_answers(records, tokenizer):
    """A rule's check runs on a DFA of its pattern, built lazily, its state cached by the text since
    the anchor (``train/constrained/automaton.py``). Along real completions and noisy ones (a random
    token offered at every step, kept at every seventh), every rule admits exactly the tokens that
    ``regex`` partial matching admits, and every rule's segment ends (``_Core.ends_in``) exactly where
    ``regex`` finds its whole text (``_Core.complete``); and on every prefix of the rules' segments and
    random characters after it (digits of other scripts, escapes, control characters), each pattern's
    automaton is live and accepting exactly where ``regex`` matches partially and fully."""
    import regex

    from physcene.train.constrained import grammar
    from physcene.train.constrained.automaton import automaton

    gen = random.Random(3)
    vocab = len(tokenizer)
    texts = vocabulary(tokenizer).texts
    checked = ended = 0
    segments: dict[str, set[str]] = {}  # each regex pattern -> the partials it was checked on
    for r in records[:3]:
        ids = tokenizer(r["completion"], add_special_tokens=False)["input_ids"]
        for noisy in (False, True):
            proc = CTRCConstraint(tokenizer, [r["prompt"]])
            rule = proc.advance_row(0, [])
            for k, true in enumerate(ids):
                offered = [gen.randrange(vocab) for _ in range(4)] + [true] if noisy else [true]
                if rule is not None:
                    for t in offered:
                        assert rule.admits(texts[t]) == _regex_admits(rule, texts[t]), rule.partial
                        checked += 1
                    if rule.pattern and not rule.choices:
                        segments.setdefault(rule.pattern, set()).add(rule.partial)
                found = proc.anchors[0]
                if isinstance(found, tuple) and found[1] is not None:  # the segment, then the true text
                    core = found[1]
                    true_text = r["completion"][found[0]:][:gen.randrange(400)]
                    for partial in (proc.texts[0][found[0]:], true_text):
                        assert core.ends_in(partial) == (core.complete(partial) is not None), partial
                        ended += core.ends_in(partial)
                token = offered[0] if noisy and k % 7 == 3 and rule is not None and rule.admits(
                    texts[offered[0]]) else true
                rule = proc.advance_row(0, [token])
                if proc.finished[0]:
                    break
    assert checked > 2000 and ended > 50 and len(segments) >= 4
    odd = ["\u0663", "\u00a0", "\x01", "\\", "u", "\u00e9", '"', "}", "\n", ".", "-", "0", "9", " ", ","]
    for pattern, partials in segments.items():
        for p in (pattern, grammar._then_anything(pattern)):
            machine, reference = automaton(p), regex.compile(p)
            for partial in partials:
                for text in (partial, *(partial + c for c in gen.sample(odd, 4))):
                    state = machine.advance(machine.start, text)
                    assert machine.live[state] == (reference.fullmatch(text, partial=True) is not None), text
                    assert machine.accepting[state] == (reference.fullmatch(text) is not None), text


def test_the_last_anchor_read_from_the_last_lines_is_the_last_of_the_whole_tail(records):
    """``last_anchor`` scans only the tail's last lines (``_last_match``: no anchor spans a line
    break): at every prefix of real completions and of completions with random edits (line breaks,
    quotes, full stops, keys and plan steps cut or inserted), through windows that cut a line at any
    place, it finds the very match that a scan of the whole window finds last."""
    from physcene.train.constrained import grammar

    def scanned(tail: str):
        matches = list(grammar.ANCHOR.finditer(tail))
        return matches[-1] if matches else None

    gen = random.Random(5)
    pieces = ["\n", '"', ".", ":", '"category":', '"parent_id": "', "\n3. Place", " Place", "\n12. Place x.",
              '"relation_type":', "2_tray_0", " on ", "\u0663"]
    compared = found = 0
    for r in records[:4]:
        text = r["completion"]
        noisy = "".join(c + (gen.choice(pieces) if gen.random() < 0.05 else "") for c in text)
        for full in (text, noisy):
            for end in range(1, len(full), 3):
                tail = full[max(0, end - gen.choice([grammar._TAIL, 40, 97, 333])):end]
                want, got = scanned(tail), grammar._last_match(tail)
                assert (want and (want.span(), want.groupdict())) == (got and (got.span(), got.groupdict()))
                compared += 1
                found += got is not None
    assert compared > 2000 and found > compared // 2


def test_the_short_step_of_a_literal_rule_equals_admits_and_active_rule():
    """``Rule.after`` of literal rules (one choice, several, one choice a prefix of another as
    `` 3_comb_1`` of `` 3_comb_10``, closed, with words after a plan step's id) and of regex rules
    gives what ``admits`` + ``active_rule`` give, for every prefix of every choice and the texts
    that run past them."""
    from physcene.train.constrained.grammar import _STEP_WORDS, _Core, _literal, active_rule

    cores = [_literal(' "2_tray_0", "category":'),
             _literal(' "1_mirror_0", "category":', ' "3_comb_0", "category":', ' "3_comb_1", "category":'),
             _literal(" [0.0, 113.7, 0.0, 48.25]\n}\n", then_eos=True),
             _Core(_STEP_WORDS, choices=(" 3_comb_1", " 3_comb_10", " 2_tray_0")),
             _Core(_STEP_WORDS, choices=(" 1_mirror_0", " 2_tray_0")),
             _literal(" 3_comb_1", " 3_comb_10, 11", " 2_tray_0"),  # complete inside a longer choice
             _Core(r' -?(?:0|[1-9]\d{0,3})(?:\.\d{1,8})?\}')]
    extra = ["", "x", " ", ".", " on the table.", " in 2_tray_0.", '"', ", ", "0", "1.", "9}", "\n"]
    compared = 0
    for core in cores:
        texts = {c[:n] + e for c in (core.choices or (" 12.5}",)) for n in range(len(c) + 1) for e in extra}
        for text in sorted(texts):
            for cut in range(len(text) + 1):
                rule = active_rule(text[:cut], core)
                if rule is None or rule.pattern is None:
                    continue
                added = text[cut:]
                want = active_rule(text, core, within=True) if rule.admits(added) else False
                assert rule.after(added, core) == want, (core, text[:cut], added)
                compared += 1
    assert compared > 5000


def _extents_by_reading_the_whole_array(text: str, pairs) -> bool:
    """The definition :func:`_extents_possible` answers (reading every value of the array at each call)."""
    from physcene.train.constrained.grammar import _ARRAY_START, _largest

    m = _ARRAY_START.match(text)
    if m is None:
        return True
    values = [v.strip() for v in m.group(1).split(",")]
    n_done = len(values) if m.group(2) else len(values) - 1  # the last one is still being written
    for lo, hi in pairs:
        if lo == n_done == len(values) - 1 and values[lo] and not values[lo].startswith("-"):
            if float(values[lo].rstrip(".")) >= _largest(""):
                return False
            continue
        if lo >= n_done or hi > n_done or hi >= len(values):
            continue
        low = float(values[lo])
        if hi < n_done:
            if not float(values[hi]) > low:
                return False
        elif not _largest(values[hi]) > low:
            return False
    return True


def test_the_extents_read_from_cached_finished_values_equal_reading_the_whole_array():
    """Every prefix of random boxes and zones (numbers of either sign, some maxes below their mins,
    some mins too large for any max), as the rule admits them character by character or not."""
    from physcene.train.constrained.grammar import _ORDERED, RELATIVE_BBOX, ZONE, _extents_possible

    rng = random.Random(3)

    def number() -> str:
        whole = rng.choice(["0", "5", "12", "-3", "9999", "-0"])
        return whole + rng.choice(["", ".", ".5", ".25", ".99999999"])

    checked = 0
    for key, size in ((RELATIVE_BBOX, 6), (ZONE, 4)):
        pairs = _ORDERED[key]
        for _ in range(150):
            array = " [" + ", ".join(number() for _ in range(size)) + "], \"next\": 1"
            for end in range(len(array) + 1):
                text = array[:end]
                expected = _extents_by_reading_the_whole_array(text, pairs)
                assert _extents_possible(text, pairs) == expected, text
                checked += 1
    assert checked > 5000
