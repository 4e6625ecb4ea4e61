"""``physcene eval``: generators, file round trip, reports, bad input."""

from __future__ import annotations

import json

import pytest

from physcene.cli import main
from physcene.commands.eval import model_generators
from physcene.config import load_config
from physcene.ctrc import ParseError
from physcene.eval.harness import (
    EvalError,
    generate,
    load_benchmark,
    make_judge,
    method_name,
    method_names,
    save_layouts,
    score_scenes,
)
from physcene.eval.metrics import ScenePhysics, SceneResult, paired_collisions


@pytest.fixture(scope="module")
def items():
    return load_benchmark("test", n=4, progress=False)


def test_file_generator_reproduces_the_reference_scores(items, tmp_path):
    layouts = tmp_path / "layouts"
    outputs = generate(items, "reference", progress=False)
    failed = ParseError("truncated JSON at char 1")
    assert save_layouts(items, [failed, *outputs[1:]], layouts) == len(items) - 1  # a ParseError: no file
    assert not (layouts / f"{items[0].id}.json").exists()
    save_layouts(items, outputs, layouts)
    judge = make_judge("rule", [it.reference for it in items])
    ref = score_scenes(items, generate(items, "reference", progress=False), judge, progress=False)
    loaded = score_scenes(items, generate(items, f"file:{layouts}", progress=False), judge, progress=False)
    for a, b in zip(ref, loaded):
        assert a.physics.n_objects == b.physics.n_objects
        assert len(a.physics.pair_depths) == len(b.physics.pair_depths)
        assert a.judge["avg"] == pytest.approx(b.judge["avg"], abs=1e-3)


def test_heuristic_is_collision_free_and_semantics_blind(items):
    judge = make_judge("rule", [it.reference for it in items])
    ref = score_scenes(items, generate(items, "reference", progress=False), judge, progress=False)
    heur = score_scenes(items, generate(items, "heuristic", progress=False), judge, progress=False)
    assert all(r.physics.collision_free(0.5) for r in heur)  # packed with a 1 cm gap
    # No stacking or containment: the stated in/on relations are lost, so CwT drops.
    assert sum(r.judge["CwT"] for r in heur) < sum(r.judge["CwT"] for r in ref)
    # Random placement breaks the functional neighbour pairs: LCR drops too.
    assert sum(r.judge["LCR"] for r in heur) < sum(r.judge["LCR"] for r in ref)


def test_eval_command_writes_tables_plots_and_results(tmp_path, capsys):
    out = tmp_path / "ev"
    rc = main(["eval", "--split", "test", "--n", "3", "--generator", "reference,heuristic", "--out", str(out),
               "--quiet", "render=0"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "| Reference |" in printed and "| Heuristic placer |" in printed
    data = json.loads((out / "results.json").read_text())
    assert set(data["methods"]) == {"Reference", "Heuristic placer"}
    report = (out / "report.md").read_text()
    for section in ("## Main results", "## Per difficulty level", "## Per scene type",
                    "## Robustness to collision thresholds", "## Diversity"):
        assert section in report
    assert (out / "qpr_by_level.png").stat().st_size > 0


def test_eval_command_rejects_bad_input(tmp_path, capsys):
    assert main(["eval", "--n", "2", "--generator", "magic", "--out", str(tmp_path), "--quiet"]) == 2
    assert "unknown generator 'magic'" in capsys.readouterr().err
    assert main(["eval", "--n", "2", "--generator", f"file:{tmp_path}/nope", "--out", str(tmp_path),
                 "--quiet"]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert method_name("tto") == "Reference + TTO"
    assert method_name("model:runs/pada/", True) == "Model (pada) + TTO"
    # two checkpoints named alike keep a row each (one overwrote the other), labelled by their paths
    assert method_names(["model:runs/a/sft", "model:runs/b/sft/", "reference"]) == [
        "Model (runs/a/sft)", "Model (runs/b/sft)", "Reference"]
    with pytest.raises(EvalError, match="listed twice: heuristic"):
        method_names(["heuristic", "reference", "heuristic"])


def test_model_generator_feeds_ctrc_prompts_and_parses_completions(items, monkeypatch):
    """``model:PATH`` calls physcene.train.generate.generate on the benchmark's CTRC prompts; here
    the 'model' answers with the reference completions (and one garbage answer)."""
    import physcene.train.generate as train_generate
    from physcene.data import synthesize

    completions = {r["prompt"]: r["completion"] for r in synthesize("test", n=len(items))}
    seen = {}

    def fake_generate(path, prompts, **kw):
        seen["path"], seen["prompts"] = path, list(prompts)
        return [completions[p] for p in prompts[:-1]] + ["not a layout"]

    monkeypatch.setattr(train_generate, "generate", fake_generate)
    with pytest.raises(EvalError, match="no model generator"):  # the harness never loads a checkpoint itself
        generate(items, "model:runs/tiny", progress=False)
    spec = load_config("eval", ["generator=reference,model:runs/tiny"])
    outs = generate(items, "model:runs/tiny", progress=False, generators=model_generators(spec))
    assert seen["path"] == "runs/tiny" and seen["prompts"] == [it.prompt for it in items]
    for it, out in zip(items[:-1], outs[:-1]):
        assert sorted(o.instance_id for o in out.objects) == sorted(it.reference.ids())
    assert hasattr(outs[-1], "reason")
    judge = make_judge("rule", [it.reference for it in items])
    res = score_scenes(items, outs, judge, progress=False)
    assert res[-1].extra["parse_error"] and res[-1].judge["error"].startswith("unparsable output")


@pytest.mark.cuda
def test_eval_on_cuda_matches_cpu(tmp_path):
    rows = {}
    for device in ("cpu", "cuda"):
        out = tmp_path / device
        assert main(["eval", "--n", "8", "--generator", "reference,tto", "--out", str(out), "--quiet",
                     "render=0", f"device={device}"]) == 0
        rows[device] = json.loads((out / "results.json").read_text())["methods"]
    for method in ("Reference", "Reference + TTO"):
        a, b = rows["cpu"][method]["scenes"], rows["cuda"][method]["scenes"]
        for sa, sb in zip(a, b):
            da = sorted(d for _, _, d in sa["physics"]["pair_depths"])
            db = sorted(d for _, _, d in sb["physics"]["pair_depths"])
            if method == "Reference":  # the same layouts: the engine agrees (DESIGN: rel. 1e-4)
                assert len(da) == len(db) and da == pytest.approx(db, rel=1e-3, abs=1e-4)
        # TTO runs Adam in float32 on each device: the outcome agrees, not the trajectory.
        sa_, sb_ = rows["cpu"][method]["summary"], rows["cuda"][method]["summary"]
        assert abs(sa_["collision"]["0.5"]["SCR"] - sb_["collision"]["0.5"]["SCR"]) <= 0.25


def test_parse_error_kinds_group_a_models_failure_modes():
    from physcene.ctrc import parse
    from physcene.eval.metrics import parse_error_kinds

    texts = ['{"objects": [{"instance_id": "1_cup_0", "category": "cup", "parent_id": "root_zone", '
             '"relation_type": "near", "relative_bbox": [0, 10, 0, 10, 0, 12], "relative_rotation_deg": 0}',
             '{"objects": [{"instance_id": "2_mug_0", "category": "mug", "parent_id": "root_zone", '
             '"relation_type": "near", "relative_bbox": [5, 9, 1, 7, 0, 9.5], "relative_rotation_deg": 0}',
             "no layout here at all"]
    reasons = [parse(t, zone=None).reason for t in texts]
    kinds = parse_error_kinds(reasons)
    assert sum(c for _, c in kinds) == 3
    assert kinds[0][1] == 2, kinds  # the two truncations differ only in names and numbers
    assert "1_cup_0" not in kinds[0][0] and "2_mug_0" not in kinds[0][0]
    assert parse_error_kinds([]) == []


def test_score_bar_counts_every_output_parsed_or_not(items, capsys):
    """The score bar ends at the number of outputs also where some did not parse (they never reach
    the engine, and the bar used to stop short of them)."""
    judge = make_judge("rule", [it.reference for it in items])
    outputs = generate(items, "reference", progress=False)
    outputs[0] = ParseError("truncated JSON at char 1")
    score_scenes(items, outputs, judge, progress=True, desc="scoring")
    err = capsys.readouterr().err
    assert f"{len(items)}/{len(items)}" in err.replace("\r", "\n").splitlines()[-1]


def test_a_layout_file_of_another_draw_of_the_split_is_refused(tmp_path):
    """Ids are positions in a draw that depends on n: records written for the first 8 test scenes,
    scored as the first 3, are other scenes under the same ids; the file: generator names the record
    instead of scoring them. The same file read with the n it was written for scores."""
    from physcene.layout import write_layout_records
    from physcene.train.ablation import layout_records

    eight = load_benchmark("test", n=8, progress=False)
    three = load_benchmark("test", n=3, progress=False)
    assert [a.instruction for a in three] != [b.instruction for b in eight[:3]]  # the premise: other scenes
    records = layout_records(eight, [it.reference for it in eight])
    path = write_layout_records(records, tmp_path / "l.jsonl.gz")
    assert len(generate(eight, f"file:{path}", progress=False)) == 8
    with pytest.raises(EvalError, match="another draw of the split"):
        generate(three, f"file:{path}", progress=False)


def _result(scene_id: str, collides: bool | None) -> SceneResult:
    """A scored scene that collides, is collision-free, or (None) did not parse."""
    physics = ScenePhysics(3, ((0, 1, 0.8),) if collides else ())
    return SceneResult(scene_id, "desk", 1, physics, extra={"parse_error": "x"} if collides is None else {})


def test_paired_collisions_count_the_discordant_scenes_and_test_them_exactly():
    # 10 scenes: both collide on 2, the first only on 6, the second only on 1, neither on 1
    first = [_result(f"s{k}", k < 8) for k in range(10)]
    second = [_result(f"s{k}", k < 2 or k == 8) for k in range(10)]
    pair = paired_collisions(first, second)
    assert (pair["both"], pair["only_first"], pair["only_second"], pair["neither"]) == (2, 6, 1, 1)
    assert pair["scr_first"] == 0.8 and pair["scr_second"] == 0.3
    assert pair["difference"] == pytest.approx(-0.5)
    assert pair["p_value"] == pytest.approx(2 * (1 + 7) / 2 ** 7)  # binomial(7, 1/2): P(X <= 1), two-sided
    assert paired_collisions(first, first)["p_value"] == 1.0  # no discordant scene
    # unparsed on either side and unmatched ids leave the comparison; the order does not matter
    second[3] = _result("s3", None)
    shuffled = paired_collisions(first, [*reversed(second), _result("extra", True)])
    assert shuffled["scenes"] == 9 and shuffled["only_first"] == 5


def test_eval_of_several_generators_pairs_each_with_the_first(tmp_path, capsys):
    out = tmp_path / "ev"
    assert main(["eval", "--split", "test", "--n", "4", "--generator", "reference,heuristic", "--out",
                 str(out), "--quiet", "render=0"]) == 0
    printed = capsys.readouterr().out
    data = json.loads((out / "results.json").read_text())
    pair = data["methods"]["Heuristic placer"]["paired"]
    assert pair["against"] == "Reference" and pair["scenes"] == 4
    assert "paired" not in data["methods"]["Reference"]
    ref = data["methods"]["Reference"]["summary"]["collision"]["0.0"]["SCR"]
    assert pair["scr_first"] == pytest.approx(ref) and pair["scr_second"] == 0.0  # the placer packs apart
    assert pair["only_second"] == 0 and pair["only_first"] == round(4 * ref)
    assert "paired with Reference on 4 scenes" in printed
    assert "## Paired against the first method" in (out / "report.md").read_text()
