"""``physcene demo`` end to end on a tiny benchmark (the README's main job)."""

from __future__ import annotations

import json

from physcene.cli import main


def test_demo_prints_the_before_after_table_and_writes_the_report(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--n", "3", "--quiet", "render=1", "render_size=[96,72]"])
    printed = capsys.readouterr().out
    assert rc == 0
    assert "| Reference |" in printed and "| Reference + TTO |" in printed and "QPR τ=7" in printed
    assert "0.5 cm SCR" in printed
    results = json.loads((out / "results.json").read_text())
    ref, tto = results["methods"]["Reference"], results["methods"]["Reference + TTO"]
    assert results["n"] == 3 and len(ref["scenes"]) == 3 and len(tto["scenes"]) == 3
    # TTO never makes a layout penetrate more (DESIGN: TTO contract): compare pair counts at 0.5 cm.
    assert tto["summary"]["collision"]["0.5"]["ACR"] <= ref["summary"]["collision"]["0.5"]["ACR"] + 1e-9
    for name in ("report.md", "qpr_by_level.png", "qpr_by_type_radar.png"):
        assert (out / name).stat().st_size > 0
    assert len(list((out / "renders").rglob("*.png"))) == 4  # 1 scene × 2 views × 2 methods
    report = (out / "report.md").read_text()
    assert "## Robustness to collision thresholds" in report and "## Diversity" in report


def test_demo_rejects_bad_input(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--n", "0", "--quiet"]) == 2
    assert "--n must be >= 1" in capsys.readouterr().err
