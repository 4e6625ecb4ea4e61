"""The software renderer draws real geometry with a z-buffer; the heuristic placer packs cleanly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from physcene.eval.render import _category_color, render_image, render_views
from physcene.layout import read_layout
from physcene.scene import Scene, SceneObject, Zone

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "office_table.layout.json"


def _two_boxes(front_first: bool = True) -> Scene:
    near = SceneObject("near_0", "cardboard_crate", center=(50.0, 10.0, 10.0), size=(30.0, 6.0, 20.0))
    far = SceneObject("far_0", "wooden_chest", center=(50.0, 40.0, 15.0), size=(40.0, 10.0, 30.0))
    return Scene(Zone(0, 100, 0, 50), (near, far) if front_first else (far, near), "office table")


def _close(pixel, rgb, tol=0.25):
    # Shading scales the base colour; compare chromaticity (colour direction), not brightness.
    p = np.asarray(pixel, float) / max(np.linalg.norm(pixel), 1e-6)
    c = np.asarray(rgb, float) / np.linalg.norm(rgb)
    return np.linalg.norm(p - c) < tol


@pytest.mark.parametrize("front_first", [True, False])
def test_nearer_object_occludes_the_farther_one(front_first):
    img = render_image(_two_boxes(front_first), "front", size=(160, 120), shadows=False)
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    # The near crate is in front of the chest's lower half: the image centre column, a little
    # below the middle, shows the crate whichever order the objects were listed in.
    h, w = img.shape[:2]
    column = img[h // 3: 2 * h // 3, w // 2]
    near_rgb, far_rgb = _category_color("cardboard_crate"), _category_color("wooden_chest")
    assert any(_close(p, near_rgb) for p in column)
    assert any(_close(p, far_rgb) for p in img[: h // 2, w // 2])  # the chest's top shows above


def test_views_differ_and_shadows_darken():
    scene = read_layout(EXAMPLE)
    front = render_image(scene, "front", size=(128, 96))
    persp = render_image(scene, "perspective", size=(128, 96))
    flat = render_image(scene, "front", size=(128, 96), shadows=False)
    assert np.abs(front.astype(int) - persp.astype(int)).mean() > 5
    assert front.sum() < flat.sum()  # the shadow map takes light away, never adds it
    background = front[0, 0].astype(int)
    assert (np.abs(front.astype(int) - background).sum(axis=2) > 30).mean() > 0.2  # the table and objects


def test_render_views_writes_pngs(tmp_path):
    paths = render_views(read_layout(EXAMPLE), tmp_path, size=(96, 72), prefix="x_")
    assert sorted(paths) == ["front", "perspective"]
    for p in paths.values():
        assert p.name.startswith("x_") and p.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="unknown view"):
        render_image(read_layout(EXAMPLE), "sideways")


def test_heuristic_placer_packs_without_overlap_or_semantics():
    from physcene.eval.baselines import heuristic_place

    ref = read_layout(EXAMPLE)
    out = heuristic_place(ref, seed=3)
    assert sorted(o.instance_id for o in out.objects) == sorted(ref.ids())
    boxes = [o.aabb() for o in out.objects]
    for k, a in enumerate(boxes):
        z = ref.zone
        assert a[0] >= z.xmin and a[1] <= z.xmax and a[2] >= z.ymin and a[3] <= z.ymax
        assert a[4] == pytest.approx(0.0)  # everything stands on the table: no stacking, no containers
        for b in boxes[k + 1:]:
            assert min(a[1], b[1]) - max(a[0], b[0]) <= 1e-6 or min(a[3], b[3]) - max(a[2], b[2]) <= 1e-6
    assert heuristic_place(ref, seed=3) == out and heuristic_place(ref, seed=4) != out
    # A zone too small for everything: objects that do not fit are dropped, never overlapped.
    tiny = ref.__class__(Zone(0, 40, 0, 30), ref.objects, ref.scene_type)
    assert 0 < len(heuristic_place(tiny)) < len(ref)


def test_labels_and_pair_depths_are_written_on_the_render():
    scene = read_layout(EXAMPLE)
    plain = render_image(scene, "perspective", size=(320, 240), shadows=False)
    labelled = render_image(scene, "perspective", size=(320, 240), shadows=False, labels=True)
    assert labelled.shape == plain.shape
    changed = np.abs(labelled.astype(int) - plain.astype(int)).sum(axis=2) > 60
    assert 0.005 < changed.mean() < 0.5  # the id tags cover some of the image, not all of it
    pair = render_image(scene, "perspective", size=(320, 240), shadows=False,
                        pairs=[("4_pen_holder_0", "9_desk_lamp_0", 1.5)])
    red = (pair[..., 0].astype(int) - pair[..., 1] > 120) & (pair[..., 0] > 180)
    plain_red = (plain[..., 0].astype(int) - plain[..., 1] > 120) & (plain[..., 0] > 180)
    assert red.sum() > 50 and not plain_red.any()


def test_the_comparison_sheet_sets_variants_side_by_side_with_their_depths():
    from physcene.eval.render import render_comparison

    scene = read_layout(EXAMPLE)
    pairs = {"reference": [("4_pen_holder_0", "5_pen_0", 0.4)], "reference + TTO": []}
    sheet = render_comparison({"reference": scene, "reference + TTO": scene}, size=(200, 150), pairs=pairs)
    assert sheet.shape[1] == 2 * 200 + 8 and sheet.shape[0] > 150
    title_h = sheet.shape[0] - 150
    left, right = sheet[title_h:, :200], sheet[title_h:, 208:]
    assert np.abs(left.astype(int) - right.astype(int)).sum() > 0  # only the left one draws a pair
    # the titles: red for the variant with a pair, green for the clean one
    is_red = lambda t: ((t[..., 0].astype(int) - t[..., 1]) > 100).any()  # noqa: E731
    assert is_red(sheet[:title_h, :200]) and not is_red(sheet[:title_h, 208:])


def test_the_report_shows_a_comparison_sheet_per_rendered_scene(tmp_path):
    from physcene.eval.report import method_slug, write_comparisons
    from physcene.layout import write_layout

    scene = read_layout(EXAMPLE)
    for name in ("Reference", "Reference + TTO"):
        write_layout(scene, tmp_path / "layouts" / method_slug(name) / "s1.json")
    assert method_slug("Reference + TTO") == "reference_tto"
    assert method_slug("Heuristic placer") == "heuristic_placer"
    assert method_slug("Layouts (docs/x/sft_plan.jsonl.gz)") == "layouts_docs_x_sft_plan.jsonl.gz"
    assert method_slug("../..") == "method"  # never a path out of the layouts folder
    sheets = write_comparisons(tmp_path, ["s1", "s2"], ["Reference", "Reference + TTO"], size=(160, 120))
    assert list(sheets) == ["s1"]  # s2 has no saved layout
    png = tmp_path / sheets["s1"]
    assert png.read_bytes()[:4] == b"\x89PNG"
