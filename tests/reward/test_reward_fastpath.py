"""The compiled CTRC reader (kernels/ctrc_reader/, reward.text_batch.TextPacker) against the Python parser.

The fast path must give the batch ``pack([parse(t)])`` gives and the rewards, metrics and parse
errors of the pure-Python reward, on real completions, on the fuzz corpus of test_ctrc_fuzz.py
and on hypothesis layouts; whatever the scanner cannot read goes to the Python parser.
"""

from __future__ import annotations

import json
import math
import random
import weakref

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from test_ctrc import layouts
from test_ctrc_fuzz import ALPHABET, _base_completions, _mutate, _random_json, _split

from physcene.assets import AssetLibrary
from physcene.commands.bench import bench_scenes
from physcene.ctrc import ParseError, completion_text, parse
from physcene.data import synthesize
from physcene.graph import build_hierarchy
from physcene.kernels.ctrc_reader import MAX_ENTRIES, category_hash
from physcene.layout import load_layout
from physcene.physics import PhysicsEngine
from physcene.reward import PhysicsReward, RewardConfig, TextPacker
from physcene.scene import Scene, SceneObject, Zone

MARK = "**Scene Layout:**"
_PACKERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def pack_texts(engine, texts):
    """The engine's texts through one TextPacker per engine (its category table kept between calls)."""
    if engine not in _PACKERS:
        _PACKERS[engine] = TextPacker(engine)
    return _PACKERS[engine].pack(texts)


@pytest.fixture(scope="module")
def engine():
    library = AssetLibrary(resolution=24, n_points=256)
    library.add_primitives()
    return PhysicsEngine(library)


def _stack_scene() -> Scene:
    """Rotated, nested on/in hierarchy three levels deep, zone not at the origin."""
    return Scene(Zone(-20.0, 70.0, 5.0, 60.0), (
        SceneObject("1_tray_0", "tray", (30.0, 30.0, 2.0), (30.0, 24.0, 4.0), yaw=0.7),
        SceneObject("2_box_0", "box", (31.0, 30.5, 7.0), (14.0, 10.0, 6.0), yaw=-1.2),
        SceneObject("3_book_0", "book", (31.2, 30.6, 11.0), (8.0, 6.0, 2.0), yaw=2.9),
        SceneObject("4_bowl_0", "bowl", (0.0, 20.0, 3.0), (14.0, 14.0, 6.0), yaw=-3.1),
        SceneObject("5_spoon_0", "spoon", (0.5, 20.2, 3.5), (2.0, 7.0, 5.0), yaw=0.2),
        SceneObject("6_mug_0", "mug", (55.0, 45.0, 5.0), (8.0, 8.0, 10.0), yaw=math.pi - 1e-9),
    ))


def _real_texts() -> list[str]:
    texts = [r["completion"] for r in synthesize("train", n=24)]
    texts += [completion_text(s) for s in bench_scenes(6, 5, seed=3)]
    texts += [completion_text(_stack_scene()), completion_text(bench_scenes(1, 1, seed=1)[0])]
    return texts


def _yaw_diff(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a - b + math.pi, 2 * math.pi) - math.pi


def assert_batches_equal(fast, slow, pos_tol=1e-4, yaw_tol=1e-5):
    assert fast.poses.shape == slow.poses.shape
    assert torch.equal(fast.count, slow.count) and torch.equal(fast.pair_start, slow.pair_start)
    assert fast.n_pairs == slow.n_pairs and torch.equal(fast.mask, slow.mask)
    assert torch.equal(fast.asset_index, slow.asset_index)
    assert (fast.poses[..., :3] - slow.poses[..., :3]).abs().max() <= pos_tol
    assert _yaw_diff(fast.poses[..., 3], slow.poses[..., 3]).abs().max() <= yaw_tol
    assert (fast.sizes - slow.sizes).abs().max() <= pos_tol
    assert [list(r) for r in fast.ids] == slow.ids


def _python_pack(engine, texts):
    parsed = [parse(t) for t in texts]
    return engine.pack([p for p in parsed if isinstance(p, Scene)]), parsed


def _rewards_both(engine, texts, **config):
    fast = PhysicsReward(RewardConfig(**config), engine=engine)
    slow = PhysicsReward(RewardConfig(fast_parse=False, **config), engine=engine)
    fast_batch, slow_batch = fast.score(texts), slow.score(texts)
    got, want = fast_batch.rewards.tolist(), slow_batch.rewards.tolist()
    assert [r == -100.0 for r in got] == [r == -100.0 for r in want]
    assert got == pytest.approx(want, abs=1e-6, rel=1e-6)
    assert fast_batch.parse_errors == slow_batch.parse_errors
    assert dict(fast_batch.metrics) == pytest.approx(dict(slow_batch.metrics), abs=1e-6, rel=1e-6)
    return got


def test_real_completions_take_the_fast_path_and_match_the_python_batch(engine):
    texts = _real_texts()
    pack = pack_texts(engine, texts)
    assert pack.fast.all(), pack.status
    assert pack.status.tolist() == [len(parse(t).objects) for t in texts]
    slow, _ = _python_pack(engine, texts)
    assert_batches_equal(pack.batch, slow)
    assert pack.row.tolist() == list(range(len(texts))) and pack.errors == [None] * len(texts)


@pytest.mark.parametrize("n", [1, 3])
def test_batch_of_one_and_few(engine, n):
    texts = [completion_text(_stack_scene())] * n
    pack = pack_texts(engine, texts)
    assert pack.fast.all()
    assert_batches_equal(pack.batch, _python_pack(engine, texts)[0])


def test_rewards_identical_to_the_python_path(engine):
    texts = _real_texts() + ["I cannot do that.", "", _real_texts()[0][:500]]
    rewards = _rewards_both(engine, texts)
    assert rewards[-3:] == [-100.0] * 3
    _rewards_both(engine, texts, tolerance_mm=1.0, table_term=True)


def _variants(text: str) -> dict[str, str]:
    """Texts ctrc.parse reads (mostly to a Scene) that the scanner must hand to it."""
    head, data = _split(text)
    entries = [e for e in data["objects"] if e.get("instance_id") != "root_zone"]
    e = entries[-1]
    iid = entries[0]["instance_id"]
    escaped = f"\\u{ord(iid[0]):04x}{iid[1:]}"  # the same id, its first letter as a \u escape

    def dump(d):
        return head + json.dumps(d)

    def edit(fn):
        d = json.loads(json.dumps(data))
        fn(d, [x for x in d["objects"] if x.get("instance_id") != "root_zone"])
        return dump(d)

    body = text.split(MARK)[1]
    return {
        "exponent": dump(data).replace(str(e["relative_bbox"][1]) + ",", f"{e['relative_bbox'][1]:.6e},", 1),
        "escape in id": dump(data).replace(f'"instance_id": "{iid}"', f'"instance_id": "{escaped}"', 1),
        "alias relation": edit(lambda d, es: es[0].update(relation_type="on_table")),
        "unknown key": edit(lambda d, es: es[0].update(colour="red")),
        "asset id": edit(lambda d, es: es[0].update(asset_id="box")),
        "no category": edit(lambda d, es: es[0].pop("category")),
        "relation key": edit(lambda d, es: es[0].update(relation=es[0].pop("relation_type"))),
        "float layer": edit(lambda d, es: es[0].update(layer=1.0)),
        "code fence": "```json\n" + body + "\n```",
        "json tokens": "<json>" + body + "<json>",
        "trailing comma": text.replace("]\n}", "],\n}"),
        "no marker": body,
        "nested layout": head + json.dumps({"layout": data}),
        "marker in description": edit(lambda d, es: es[0].update(description="Scene Layout {x}")),
        "null zone": edit(lambda d, es: d.update(item_placement_zone=None)),
        "too many digits": dump(data).replace(str(e["relative_bbox"][1]) + ",",
                                              str(e["relative_bbox"][1]) + "000000000000001,", 1),
    }


def test_unreadable_completions_go_to_the_python_parser(engine):
    base = completion_text(_stack_scene())
    variants = _variants(base)
    texts = list(variants.values())
    pack = pack_texts(engine, texts)
    for name, status in zip(variants, pack.status.tolist()):
        assert status < 0, name
    parsed = [parse(t) for t in texts]
    assert sum(isinstance(p, Scene) for p in parsed) >= len(texts) - 1  # the float layer is refused
    rewards = _rewards_both(engine, texts)
    assert sum(r != -100.0 for r in rewards) == sum(isinstance(p, Scene) for p in parsed)
    slow, _ = _python_pack(engine, texts)
    assert_batches_equal(pack.batch, slow)


def test_key_order_whitespace_and_zone_entry(engine):
    base = completion_text(_stack_scene())
    head, data = _split(base)
    rng = random.Random(5)
    shuffled = {k: v for k, v in reversed(list(data.items()))}
    shuffled["objects"] = [dict(rng.sample(list(e.items()), len(e))) for e in data["objects"]]
    no_zone = json.loads(json.dumps(data))
    zone = no_zone.pop("item_placement_zone")  # the root entry's bbox stands in
    no_zone["objects"][0]["bbox"] = zone + [0.0, 0.0]
    minimal = json.loads(json.dumps(data))
    for entry in minimal["objects"]:
        if entry.get("parent_id") == "root_zone":
            entry.pop("parent_id")
            entry.pop("relation_type")
        entry.pop("layer")
        entry.pop("description", None)
    texts = [head + json.dumps(shuffled, indent=3), head + json.dumps(no_zone, separators=(",", ":")),
             head + json.dumps(minimal) + "\nDone. Trailing words after the JSON are ignored.",
             base + "</s>", "<s>" + base]
    pack = pack_texts(engine, texts)
    assert pack.fast.all(), pack.status
    assert_batches_equal(pack.batch, _python_pack(engine, texts)[0])


def test_too_many_entries_and_non_ascii_text(engine):
    objs = tuple(SceneObject(f"{k}_box_{k}", "box", (5.0 + 3 * (k % 30), 5.0 + 5 * (k // 30), 1.0),
                             (2.0, 2.0, 2.0)) for k in range(MAX_ENTRIES))
    many = completion_text(Scene(Zone(0, 100, 0, 100), objs))
    uni = completion_text(Scene(Zone(0, 60, 0, 40), (
        SceneObject("1_tasse_0", "tasse", (20.0, 20.0, 4.0), (8.0, 8.0, 8.0), description="Über 10° — ☕"),
        SceneObject("2_plätzchen_0", "plätzchen", (30.0, 20.0, 1.0), (5.0, 5.0, 2.0)))))
    texts = [many, uni]
    pack = pack_texts(engine, texts)
    assert pack.status[0] == -7 and pack.status[1] == 2
    assert_batches_equal(pack.batch, _python_pack(engine, texts)[0])
    _rewards_both(engine, texts)


def test_non_string_items_send_the_batch_to_the_python_parser():
    library = AssetLibrary(resolution=16, n_points=64)
    library.add_primitives()
    engine = PhysicsEngine(library)  # fresh: no scan has run yet
    text = completion_text(_stack_scene())
    pack = pack_texts(engine, [text, 5, None])
    assert pack.status.tolist() == [-2, -2, -2] and pack.row.tolist() == [0, -1, -1]
    assert "string" in pack.errors[1] and pack.errors[0] is None
    assert_batches_equal(pack.batch, engine.pack([parse(text)]))


def test_new_categories_are_learned_and_hash_collisions_fall_back():
    library = AssetLibrary(resolution=16, n_points=64)
    library.add_primitives()
    engine = PhysicsEngine(library)
    text = completion_text(_stack_scene())
    first = pack_texts(engine, [text])
    assert first.fast.all()  # unknown categories resolved on the host, then rescanned
    packer = _PACKERS[engine]
    learned = {name for _, _, name in packer._categories.values()}
    assert learned == {o.category for o in _stack_scene().objects}
    # a foreign name posing under mug's hash: mug's own occurrences no longer check out
    key, check = category_hash(b"mug")
    packer._categories[key] = (check + 1, 0, "not-a-mug")
    packer._table = packer._upload_table()
    second = pack_texts(engine, [text])
    assert second.status.tolist() == [-9]
    assert_batches_equal(second.batch, first.batch)


def _fuzz_corpus(n_trunc=150, n_mut=400, n_junk=300, n_random=60) -> list[str]:
    """A sample of test_ctrc_fuzz's corpus (its generators) plus the clean bases."""
    rng = random.Random(4242)
    bases = [(text, *_split(text)) for text in _base_completions()]
    texts = [b[0] for b in bases]
    for _ in range(n_trunc):
        text, _, _ = rng.choice(bases)
        texts.append(text[: rng.randrange(len(text))])
    for _ in range(n_mut):
        _, head, data = rng.choice(bases)
        texts.append(_mutate(rng, head, data))
    for _ in range(n_junk):
        text, *_ = rng.choice(bases)
        for _ in range(rng.randint(1, 4)):
            k = rng.randrange(len(text) + 1)
            junk = rng.choice(["}", "{", "]", ",", '"', "NaN", "<json>", "```", "\\", "\x00", "null", "1e999",
                               " ", "\n", "0", "-", ".5", "Scene Layout"])
            text = text[:k] + junk + text[k:]
        texts.append(text)
    for _ in range(n_random):
        texts.append("".join(rng.choice(ALPHABET) for _ in range(rng.randrange(200))) or " ")
        texts.append(json.dumps(_random_json(rng)))
    texts += ["", " ", "{}", '{"objects": null}', '{"objects": [null]}', "\ud800", MARK + "\ud800{}"]
    return texts


def test_fuzz_corpus_rewards_identical(engine):
    texts = _fuzz_corpus()
    pack = pack_texts(engine, texts)
    parsed = [parse(t) for t in texts]
    # the scanner never accepts what Python refuses, and agrees on what both read
    for k, (status, p) in enumerate(zip(pack.status.tolist(), parsed)):
        if status >= 0:
            assert isinstance(p, Scene) and len(p.objects) == status, (k, texts[k][:200])
        assert (pack.row[k] >= 0) == isinstance(p, Scene)
        assert pack.errors[k] == (p.reason if isinstance(p, ParseError) else None)
    assert pack.fast.sum() >= 20  # junk in descriptions or whitespace leaves some canonical
    assert_batches_equal(pack.batch, engine.pack([p for p in parsed if isinstance(p, Scene)]))
    _rewards_both(engine, texts)


def _number(rng: random.Random, v: float) -> str:
    """v written as JSON the way a model might: int, trailing zeros, many decimals, -0."""
    style = rng.randrange(5)
    if style == 0 and float(v).is_integer():
        return str(int(v)) if v != 0 or rng.random() < 0.5 else "-0"
    if style == 1:
        return f"{v:.7f}"
    if style == 2:
        return f"{v:.3f}"
    if style == 3:
        return repr(float(v))  # up to 17 significant digits: beyond 15 the scanner defers
    return f"{v:.5f}"


def _rewrite(rng: random.Random, head: str, data: dict) -> str:
    """The same layout re-serialised with random key order, whitespace and number formats."""
    ws = ["", " ", "\n", "\t", "\r\n  "]

    def value(v) -> str:
        if isinstance(v, (bool, int)) or v is None:  # ints stay ints: "layer" must be one
            return json.dumps(v)
        if isinstance(v, float):
            return _number(rng, v)
        if isinstance(v, list):
            return "[" + ",".join(rng.choice(ws) + value(x) for x in v) + rng.choice(ws) + "]"
        if isinstance(v, dict):
            items = list(v.items())
            rng.shuffle(items)
            pairs = [f"{rng.choice(ws)}{json.dumps(k)}{rng.choice(ws)}:{rng.choice(ws)}{value(x)}"
                     for k, x in items]
            return "{" + ",".join(pairs) + rng.choice(ws) + "}"
        return json.dumps(v, ensure_ascii=rng.random() < 0.5)

    return head + value(data) + rng.choice(["", "\n", "\nThat is the layout."])


def test_reserialised_layouts_match_the_python_parser(engine):
    """Acceptance side of the fuzzing: valid layouts in many spellings (both paths must agree)."""
    rng = random.Random(77)
    bases = [_split(t) for t in _real_texts()[:12] + [completion_text(_stack_scene())]]
    descriptions = ['say "hi"', "tab\there", "Über 10° ☕", "back\\slash", "{[,]}"]
    for _, data in bases:
        for e in data["objects"]:
            if rng.random() < 0.3:
                e["description"] = rng.choice(descriptions)
    texts = [_rewrite(rng, *rng.choice(bases)) for _ in range(120)]
    pack = pack_texts(engine, texts)
    assert pack.fast.mean() > 0.5, pack.status
    slow, parsed = _python_pack(engine, texts)
    assert all(isinstance(p, Scene) for p in parsed)
    assert_batches_equal(pack.batch, slow)
    _rewards_both(engine, texts)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(layouts())
def test_hypothesis_round_trip_layouts(engine, case):
    data, _ = case
    scene = build_hierarchy(load_layout(json.loads(json.dumps(data))))
    text = completion_text(scene)
    pack = pack_texts(engine, [text])
    slow, parsed = _python_pack(engine, [text])
    assert isinstance(parsed[0], Scene)
    descriptions = " ".join(o.description for o in scene.objects)
    if "<json>" not in descriptions and "Scene Layout" not in descriptions:
        assert pack.fast.all(), pack.status
    assert_batches_equal(pack.batch, slow)


@pytest.mark.cuda
def test_cuda_fast_path_matches_cpu_and_python():
    library = AssetLibrary(resolution=24, n_points=256)
    library.add_primitives()
    cpu, cuda = PhysicsEngine(library, "cpu"), PhysicsEngine(library, "cuda")
    texts = _real_texts() + _fuzz_corpus(40, 100, 80, 10)
    on_gpu, on_cpu = pack_texts(cuda, texts), pack_texts(cpu, texts)
    assert np.array_equal(on_gpu.status, on_cpu.status) and on_gpu.errors == on_cpu.errors
    slow, _ = _python_pack(cpu, texts)
    gpu_batch = on_gpu.batch
    for name in ("poses", "sizes", "asset_index", "count", "pair_start", "mask"):
        setattr(gpu_batch, name, getattr(gpu_batch, name).cpu())
    assert_batches_equal(gpu_batch, slow)
    _rewards_both(cuda, texts)
