"""RuleJudge: each criterion moves the right way; metrics follow the paper's formulas."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from physcene.eval.judges import EvalCase, LayoutStats, RuleJudge, layout_features
from physcene.eval.metrics import (
    ScenePhysics,
    SceneResult,
    breakdown,
    collision_rates,
    diversity,
    level_of,
    out_of_zone,
    qpr,
    summarize,
)
from physcene.layout import read_layout
from physcene.scene import TABLE, SceneObject

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "office_table.layout.json"


@pytest.fixture(scope="module")
def scene():
    return read_layout(EXAMPLE)


@pytest.fixture(scope="module")
def judge(scene):
    # Reference distribution: the example plus small deterministic jitters of it.
    rng = np.random.default_rng(0)
    refs = [scene]
    for _ in range(8):
        p = scene.poses()
        p[:, :2] += rng.normal(0, 2.0, size=(len(scene), 2))
        refs.append(scene.with_poses(p))
    return RuleJudge(LayoutStats.fit(refs))


def _clean(scene) -> ScenePhysics:
    return ScenePhysics(len(scene), out_of_zone=out_of_zone(scene))


def test_reference_scores_high(scene, judge):
    s = judge.score(scene, EvalCase.from_reference(scene), _clean(scene))
    assert set(s) == {"CwT", "OSR", "PPI", "LCR", "OV", "avg"}
    assert s["CwT"] == 10.0 and s["PPI"] == 10.0
    assert s["avg"] > 8.5, s


def test_cwt_falls_when_a_requested_object_is_dropped(scene, judge):
    case = EvalCase.from_reference(scene)
    assert case.relations, "the example has in/on relations"
    fewer = scene.with_objects(o for o in scene.objects if o.category != "mouse")
    assert judge.consistency_with_task(fewer, case) < judge.consistency_with_task(scene, case)
    # Breaking a stated relation (the pen leaves its holder) also costs.
    pen = scene.get("5_pen_0")
    moved = scene.with_objects(o.moved(center=(60.0, 50.0, 0.6), size=(14.0, 1.2, 1.2), parent=None,
                                       relation=None) if o is pen else o.moved(parent=None, relation=None)
                               for o in scene.objects)
    assert judge.consistency_with_task(moved, case) < judge.consistency_with_task(scene, case)


def test_osr_falls_for_a_mug_scaled_five_times(scene, judge):
    big = scene.with_objects(o.moved(size=tuple(5 * v for v in o.size)) if o.category == "mug" else o
                             for o in scene.objects)
    before, after = judge.object_size_reasonableness(scene), judge.object_size_reasonableness(big)
    assert after < before - 3.0, (before, after)


def test_ppi_falls_for_floating_penetrating_or_out_of_zone_objects(scene, judge):
    clean = judge.placement_plausibility(scene, _clean(scene))
    floating = judge.placement_plausibility(scene, ScenePhysics(len(scene), floating=(7,)))
    pen = judge.placement_plausibility(scene, ScenePhysics(len(scene), pair_depths=((0, 1, 2.0),)))
    out = judge.placement_plausibility(scene, ScenePhysics(len(scene), out_of_zone=(0, 3)))
    assert clean == 10.0 and floating < clean and pen < clean and out < clean


def test_ppi_uses_the_engines_floating_detection(scene, judge):
    physics = pytest.importorskip("physcene.physics")
    from physcene.eval.metrics import physics_from_score

    engine = physics.PhysicsEngine()
    lifted = scene.with_objects(o.moved(center=(o.center[0], o.center[1], o.center[2] + 15.0))
                                if o.category == "mouse" else o for o in scene.objects)
    ph = physics_from_score([scene, lifted], engine.score([scene, lifted]))
    mouse = lifted.ids().index("8_mouse_0")
    assert mouse in ph[1].floating and mouse not in ph[0].floating
    case = EvalCase.from_reference(scene)
    assert judge.score(lifted, case, ph[1])["PPI"] < judge.score(scene, case, ph[0])["PPI"]


def test_lcr_falls_when_objects_are_pushed_to_the_zone_edges(scene, judge):
    z = scene.zone
    objs, k = [], 0
    by_id = scene.by_id()
    for o in scene.objects:  # table-level objects to alternating corners/edges; children follow
        if o.parent not in (None, TABLE) and o.parent in by_id:
            continue
        hw, hd = 0.5 * o.size[0], 0.5 * o.size[1]
        xs = (z.xmin + hw, z.xmax - hw, z.xmin + hw, z.xmax - hw, z.center[0])[k % 5]
        ys = (z.ymin + hd, z.ymax - hd, z.ymax - hd, z.ymin + hd, z.ymax - hd)[k % 5]
        dx, dy = xs - o.center[0], ys - o.center[1]
        objs.append(o.moved(center=(xs, ys, o.center[2])))
        for c in scene.objects:
            if c.parent == o.instance_id:
                objs.append(c.moved(center=(c.center[0] + dx, c.center[1] + dy, c.center[2])))
        k += 1
    edges = scene.with_objects(objs)
    assert layout_features(edges)["edge_fraction"] > layout_features(scene)["edge_fraction"]
    before, after = judge.layout_coherence(scene), judge.layout_coherence(edges)
    assert after < before - 2.0, (before, after)


def test_ov_falls_for_a_pen_hidden_in_a_closed_box(scene, judge):
    box = SceneObject("10_box_0", "box", center=(70.0, 52.0, 3.0), size=(18.0, 6.0, 6.0))
    pen = SceneObject("11_pen_1", "pen", center=(70.0, 52.0, 1.0), size=(14.0, 1.2, 1.2))
    hidden = scene.with_objects([*scene.objects, box, pen])
    visible = scene.with_objects([*scene.objects, box, pen.moved(center=(40.0, 55.0, 0.6))])
    assert judge.object_visibility(hidden) < judge.object_visibility(visible) - 2.0
    # A pen in an (open) pen holder stays visible.
    assert judge.object_visibility(scene) > 9.0


def test_collision_rates_follow_the_paper_formulas():
    scenes = [ScenePhysics(4, ((0, 1, 0.3), (1, 2, 1.2))), ScenePhysics(3), ScenePhysics(1)]
    r = collision_rates(scenes)
    assert r[0.0]["SCR"] == pytest.approx(1 / 3)
    assert r[0.0]["ACR"] == pytest.approx((2 / 6) / 3)  # 2 of 6 pairs in scene 1, 0, 0
    assert r[0.5]["ACR"] == pytest.approx((1 / 6) / 3)
    assert r[1.0]["SCR"] == pytest.approx(1 / 3) and collision_rates(scenes, (1.5,))[1.5]["SCR"] == 0.0
    q = qpr([9.5, 7.5, float("nan")], scenes, taus=(7, 8, 9))
    assert q == {7.0: pytest.approx(1 / 3), 8.0: 0.0, 9.0: 0.0}


def test_summary_breakdown_and_diversity(scene):
    judge = {"CwT": 8, "OSR": 9, "PPI": 9, "LCR": 8, "OV": 9, "avg": 8.6}
    results = [SceneResult(f"s{k}", t, level_of(n), ScenePhysics(n, ((0, 1, 0.2),) if k % 2 else ()),
                           judge, {"stable": k % 3 == 0})
               for k, (t, n) in enumerate([("office", 3), ("office", 10), ("dining", 17), ("dining", 6)])]
    row = summarize(results)
    assert row["QPR"][7.0] == 0.5 and row["QPR"][9.0] == 0.0
    assert row["collision"][0.0]["SCR"] == 0.5 and math.isclose(row["stability_rate"], 0.5)
    assert set(breakdown(results, "scene_type")) == {"office", "dining"}
    assert [level_of(n) for n in (1, 4, 5, 8, 9, 12, 13, 16, 17, 40)] == [1, 1, 2, 2, 3, 3, 4, 4, 5, 5]
    d = diversity([scene])
    assert d["asset_types"] == len({o.category for o in scene.objects})
    assert d["pos_std_x"] == pytest.approx(np.std([o.center[0] for o in scene.objects]))
    assert SceneResult.from_dict(results[1].to_dict()).to_dict() == results[1].to_dict()


def test_relation_preservation_rate(scene):
    from physcene.eval.metrics import relation_preservation_rate

    same = relation_preservation_rate([scene], [scene])
    assert same["in_on_kept"] == 1.0
    pen = scene.get("5_pen_0")
    out = scene.with_objects(o.moved(center=(60.0, 55.0, 0.6), size=(14.0, 1.2, 1.2)) if o is pen else o
                             for o in scene.objects)
    assert relation_preservation_rate([scene], [out])["in_on_kept"] < 1.0
