"""Benchmark data: Table 5 strata, levels, determinism, clean layouts, instructions, import, loading."""

from __future__ import annotations

import functools
import json
import re
from pathlib import Path

import numpy as np
import pytest

from physcene.data import OOD_SCENE_TYPES, SCENE_TYPES, TABLE5, level_of, plan_split, synthesize
from physcene.data.benchmark import DataConfig, build_record, write_split
from physcene.data.instructions import MAX_WORDS, check_instruction, scene_graph_text, template_instruction
from physcene.data.noise import NoiseConfig, apply_noise
from physcene.data.scene_types import SCENE_TYPE_SPECS, spec_for
from physcene.data.splits import record_rng, select_test, stratified_counts
from physcene.data.synth import synthesize_layout
from physcene.layout import load_layout
from physcene.scene import TABLE

PAPER_WORDS = ("coffee", "office", "dressing", "dining", "kitchen", "bathroom")


def test_level_of_boundaries():
    assert [level_of(n) for n in (1, 4, 5, 8, 9, 12, 13, 16, 17, 40)] == [1, 1, 2, 2, 3, 3, 4, 4, 5, 5]
    with pytest.raises(ValueError, match="n_objects=0"):
        level_of(0)


def test_test_split_matches_table5_exactly():
    plan = plan_split("test")
    assert len(plan) == 866
    counts: dict[tuple[str, int], int] = {}
    for item in plan:
        counts[(item.scene_type, item.level)] = counts.get((item.scene_type, item.level), 0) + 1
        assert level_of(item.n_objects) == item.level
    for scene_type, row in TABLE5.items():
        assert [counts.get((scene_type, lv), 0) for lv in range(1, 6)] == list(row)
    assert [sum(TABLE5[t][lv] for t in TABLE5) for lv in range(5)] == [35, 338, 324, 127, 42]
    for word, scene_type in zip(PAPER_WORDS, SCENE_TYPES):
        assert word in scene_type


def test_train_and_ood_sizes():
    assert sum(stratified_counts("train").values()) == 9429
    ood = stratified_counts("ood")
    assert sum(ood.values()) == 200
    for t in OOD_SCENE_TYPES:
        assert sum(c for (st, _), c in ood.items() if st == t) == 50
    assert not set(OOD_SCENE_TYPES) & set(SCENE_TYPES)


def test_select_test_takes_table5_counts_where_available():
    cells = [(t, lv) for t in SCENE_TYPES for lv in range(1, 6) for _ in range(3)] + [("tv stand", 2)] * 5
    chosen = select_test(cells, 866, seed=1)
    # every Table 5 cell wants >= 2 except office level 1 (3) ... all capped by the 3 available
    assert len(chosen) == sum(min(3, TABLE5[t][lv]) for t in SCENE_TYPES for lv in range(5))
    assert all(cells[k][0] != "tv stand" for k in chosen)
    assert chosen == select_test(cells, 866, seed=1)


@functools.cache
def _clean(split: str, index: int):
    item = plan_split(split, 30, seed=3)[index]
    scene = synthesize_layout(
        spec_for(item.scene_type), item.n_objects, item.level, record_rng(3, split, index)
    )
    return item, scene


def test_clean_layout_structure():
    for index in range(8):
        item, scene = _clean("test", index)
        assert len(scene) == item.n_objects
        by_id = scene.by_id()
        z = scene.zone
        for o in scene.objects:
            assert o.zmin >= -1e-9
            if o.parent == TABLE:
                assert o.zmin == pytest.approx(0.0, abs=1e-9)
                box = o.aabb()
                assert z.xmin <= box[0] and box[1] <= z.xmax and z.ymin <= box[2] and box[3] <= z.ymax
            elif o.relation == "on":
                assert o.zmin - by_id[o.parent].zmax == pytest.approx(0.001, abs=1e-9)
        for sink in scene.restricted_zones:
            for o in scene.objects:
                b = o.aabb()
                assert b[1] <= sink.xmin or b[0] >= sink.xmax or b[3] <= sink.ymin or b[2] >= sink.ymax


def test_clean_layouts_have_no_pair_deeper_than_half_a_millimetre():
    from physcene.physics import PhysicsEngine

    scenes = []
    for split in ("test", "ood"):
        for index in range(5):
            scenes.append(_clean(split, index)[1])
    score = PhysicsEngine().score(scenes)
    depth = np.asarray(score.max_depth)
    assert depth.max() <= 0.05, [
        (s.scene_type, d, p) for s, d, p in zip(scenes, depth, score.pairs) if d > 0.05
    ]


def test_noise_is_recorded_and_careless_scenes_collide():
    item, scene = _clean("test", 2)
    noisy, record = apply_noise(scene, 5, np.random.default_rng(0), NoiseConfig(careful_by_level=(0,) * 5))
    assert not record.careful and record.interpenetration
    moved = {e["moved"] for e in record.interpenetration}
    assert any(noisy.get(i).center != scene.get(i).center for i in moved)
    same, rec2 = apply_noise(scene, 1, np.random.default_rng(0), NoiseConfig(enabled=False))
    assert same is scene and rec2.as_dict()["interpenetration"] == []


def test_instructions_are_short_goal_oriented_and_varied():
    texts = set()
    for index in range(40):
        item, scene = _clean("test", index % 8)
        text = template_instruction(scene, np.random.default_rng(index))
        assert check_instruction(text) is None, text
        assert len(text.split()) < MAX_WORDS and not re.search(r"\d", text)
        texts.add(text)
    assert len(texts) >= 38
    assert check_instruction("Place the mug at 12, 30.") is not None
    assert check_instruction(" ".join(["word"] * 30)) is not None


def test_scene_graph_text_lists_stacks():
    item, scene = _clean("test", 1)
    text = scene_graph_text(scene)
    assert "Within-Stack Relationships" in text and "is at" in text


def test_records_have_the_contract_fields_and_roundtrip():
    config = DataConfig()
    item = plan_split("test", 12, seed=0)[5]
    record = build_record("test", 0, item, config)
    assert {"id", "scene_type", "level", "instruction", "prompt", "completion", "layout"} <= set(record)
    scene = load_layout(record["layout"])
    assert len(scene) == record["n_objects"] == item.n_objects and record["level"] == item.level
    assert record["instruction"] in record["prompt"] and "**Scene Layout:**" in record["completion"]
    assert all(o.parent is not None for o in scene.objects)


def test_record_decimals_set_the_completion_precision():
    """record.decimals=2: every number of the completion has at most two decimals, the text is shorter,
    and it parses to the 5-decimal record's layout within the rounding (0.005 cm a bound)."""
    from physcene.config import ConfigError
    from physcene.ctrc import parse

    item = plan_split("test", 12, seed=0)[7]
    fine = build_record("test", 0, item, DataConfig())
    coarse = build_record("test", 0, item, DataConfig.load(["record.decimals=2"]))
    def rest(record):
        return {k: v for k, v in record.items() if k != "completion"}

    assert rest(coarse) == rest(fine)
    layout = coarse["completion"].split("**Scene Layout:**")[1]
    assert max(len(m) for m in re.findall(r"\.(\d+)", layout)) == 2
    assert max(len(m) for m in re.findall(r"\.(\d+)", fine["completion"].split("**Scene Layout:**")[1])) > 2
    assert len(coarse["completion"]) < len(fine["completion"])
    zone = load_layout(fine["layout"]).zone
    a, b = (parse(r["completion"], zone=zone) for r in (fine, coarse))
    for oa, ob in zip(a.objects, b.objects):
        assert oa.category == ob.category and oa.parent == ob.parent
        assert np.abs(np.asarray(oa.center) - np.asarray(ob.center)).max() < 0.02
    with pytest.raises(ConfigError, match="record.decimals"):
        DataConfig.load(["record.decimals=-1"])
    with pytest.raises(ValueError, match="record.decimals"):  # checked in the dataclass itself
        DataConfig(decimals=99)


def test_same_seed_gives_identical_files_and_datasets_loads_them(tmp_path):
    config = DataConfig(workers=1)
    a = write_split(tmp_path / "a", "ood", 6, seed=7, config=config, progress=False, measure=False)
    b = write_split(tmp_path / "b", "ood", 6, seed=7, config=config, progress=False, measure=False)
    assert a["n"] == b["n"] == 6
    for name in ("ood.jsonl", "ood_stats.json", "ood_stats.md"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    other = write_split(tmp_path / "c", "ood", 6, seed=8, config=config, progress=False, measure=False)
    assert (
        other["n"] == 6
        and (tmp_path / "c" / "ood.jsonl").read_bytes() != (tmp_path / "a" / "ood.jsonl").read_bytes()
    )
    datasets = pytest.importorskip("datasets")
    ds = datasets.load_dataset("json", data_files=str(tmp_path / "a" / "ood.jsonl"), split="train")
    assert ds.num_rows == 6 and set(ds.column_names) >= {"prompt", "completion", "layout", "level"}


def test_synthesize_iterates_in_plan_order():
    records = list(synthesize("test", n=3, seed=1))
    assert [r["id"] for r in records] == ["test-00000", "test-00001", "test-00002"]
    assert [r["scene_type"] for r in records] == [p.scene_type for p in plan_split("test", 3, 1)]


def _fake_tree(root: Path) -> Path:
    layout_info = root / "MesaTask-10K" / "Layout_info"
    scenes = {
        "office_table/office_table_0000": [
            ("1_pen_holder_0", [20.0, 20.0, 5.0], [8.0, 8.0, 10.0]),
            ("2_pen_0", [20.0, 20.0, 7.5], [1.2, 1.2, 14.0]),
            ("3_book_0", [50.0, 30.0, 1.5], [22.0, 16.0, 3.0]),
            ("3_book_1", [50.0, 30.0, 4.5], [20.0, 15.0, 3.0]),
        ],
        "bathroom_vanity/bathroom_vanity_0003": [
            ("1_soap_dish_0", [10.0, 10.0, 1.25], [12.0, 9.0, 2.5]),
            ("2_lotion_bottle_0", [40.0, 20.0, 9.0], [6.0, 4.5, 18.0]),
        ],
    }
    for rel, objects in scenes.items():
        folder = layout_info / rel
        folder.mkdir(parents=True)
        data = {
            "item_placement_zone": [0.0, 100.0, 0.0, 60.0],
            "restricted_zone": [[60.0, 90.0, 10.0, 40.0]] if "bathroom" in rel else [],
            "objects": [
                {
                    "instance": name,
                    "position": pos,
                    "size": size,
                    "rotation": [0.0, 0.0, 0.0, 1.0],
                    "z_rotation": 0.0,
                    "retrieved_uid": f"uid{k}",
                    "description": f"a {name}",
                }
                for k, (name, pos, size) in enumerate(objects)
            ],
        }
        (folder / "layout.json").write_text(json.dumps(data))
    return layout_info.parent


def test_import_mesatask_on_a_fake_tree(tmp_path):
    from physcene.cli import main

    root = _fake_tree(tmp_path)
    out = tmp_path / "out"
    assert main(["data", "import-mesatask", str(root), "--out", str(out), "--test-size", "866"]) == 0
    records = [
        json.loads(line)
        for name in ("train.jsonl", "test.jsonl")
        for line in (out / name).read_text().splitlines()
    ]
    assert sorted(r["id"] for r in records) == [
        "bathroom_vanity/bathroom_vanity_0003",
        "office_table/office_table_0000",
    ]
    office = next(r for r in records if r["scene_type"] == "office table")
    parents = {o["instance"]: (o["parent"], o["relation"]) for o in office["layout"]["objects"]}
    assert parents["2_pen_0"] == ("1_pen_holder_0", "in") and parents["3_book_1"] == ("3_book_0", "on")
    assert "Place 2_pen_0 in 1_pen_holder_0." in office["completion"]
    assert office["level"] == 1 and check_instruction(office["instruction"]) is None
    stats = json.loads((out / "test_stats.json").read_text())
    assert stats["n"] == 2  # both cells exist in Table 5 at level 1


def test_import_mesatask_errors_name_the_input(tmp_path, capsys):
    from physcene.cli import main

    assert main(["data", "import-mesatask", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["data", "synth", "--out", str(tmp_path / "o"), "--n", "0"]) == 2
    assert main(["data", "synth", "--out", str(tmp_path / "o"), "--n", "2", "noise.bogus=1"]) == 2
    assert "bogus" in capsys.readouterr().err


def test_every_scene_type_spec_is_usable():
    for name, spec in SCENE_TYPE_SPECS.items():
        assert spec.zone_width_cm[0] < spec.zone_width_cm[1]
        rng = np.random.default_rng(0)
        scene = synthesize_layout(spec, 9, 3, rng)
        assert len(scene) == 9 and scene.scene_type == name


def test_endpoint_instructor_runs_prompts_1_and_2_over_http():
    import http.server
    import threading

    from physcene.data.instructions import EndpointInstructor

    seen: list[str] = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_POST(self):  # noqa: N802 (http.server's name)
            body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            prompt = body["messages"][0]["content"]
            seen.append(prompt)
            text = (
                "<description>A tidy desk with a pen holder at the back.<description>"
                if "Scene Graph" in prompt
                else "<instruction>Set up a tidy desk for studying with pens close at hand.<instruction>"
            )
            data = json.dumps({"choices": [{"message": {"content": text}}]}).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, *args):
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        instructor = EndpointInstructor(base_url=f"http://127.0.0.1:{server.server_port}/v1", model="m")
        item, scene = _clean("test", 1)
        description, instruction = instructor.instruct(scene)
    finally:
        server.shutdown()
    assert description.startswith("A tidy desk") and instruction.startswith("Set up a tidy desk")
    assert "## Scene Graph" in seen[0] and "less than 30 words" in seen[1] and description in seen[1]
    with pytest.raises(RuntimeError, match="127.0.0.1:9"):
        EndpointInstructor(base_url="http://127.0.0.1:9/v1", model="m", timeout_s=2).instruct(scene)
