"""Reports in the paper's format: markdown tables (main results, per level, per type, threshold
robustness, diversity), plots (QPR vs difficulty level, per-type radar) and the report folder.

``methods`` everywhere is an ordered mapping method name -> the dict of
:func:`physcene.eval.harness.method_report` (``summary``, ``by_level``, ``by_type``,
``diversity``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

from physcene.eval.metrics import CRITERIA, DIFFICULTY_LEVELS, QPR_TAUS, THRESHOLDS_CM
from physcene.eval.render import png_bytes, render_comparison
from physcene.files import open_atomic, write_atomic
from physcene.layout import read_layout

__all__ = ["diversity_table", "failure_lines", "level_table", "main_table", "method_slug", "paired_table",
           "plot_qpr_by_level", "plot_type_radar", "threshold_table", "type_table", "write_comparisons",
           "write_report"]


def _pct(x, digits: int = 1) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.{digits}f}%"


def _num(x, digits: int = 2) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _get(d: Mapping, *keys):
    """d[k0][k1]... accepting float keys written as strings (after a JSON round trip)."""
    for k in keys:
        if k in d:
            d = d[k]
        elif str(k) in d:
            d = d[str(k)]
        else:
            return float("nan")
    return d


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + [":-:"] * (len(header) - 1)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def main_table(methods: Mapping[str, Mapping]) -> str:
    """The paper's main-results table: QPR τ=7/8/9, the five criteria and their average, SCR and
    ACR at 0 cm; plus floating rate and, when measured, stability and relation preservation."""
    extra_cols = [c for c in ("stability_rate", "relation_preservation")
                  if any(c in m["summary"] for m in methods.values())]
    labels = {"stability_rate": "Stable ↑", "relation_preservation": "Rel. kept ↑"}
    header = ["Model", *[f"QPR τ={t}" for t in QPR_TAUS], *CRITERIA, "Avg.", "SCR ↓", "ACR ↓", "Floating ↓",
              *[labels[c] for c in extra_cols]]
    rows = []
    for name, m in methods.items():
        s = m["summary"]
        row = [name, *[_pct(_get(s, "QPR", float(t))) for t in QPR_TAUS],
               *[_num(_get(s, "judge", c)) for c in (*CRITERIA, "avg")],
               _pct(_get(s, "collision", 0.0, "SCR")), _pct(_get(s, "collision", 0.0, "ACR"), 2),
               _pct(_get(s, "floating", "objects"), 2)]
        row += [_pct(s.get(c)) for c in extra_cols]
        rows.append(row)
    return _table(header, rows)


def failure_lines(methods: Mapping[str, Mapping]) -> list[str]:
    """One line per method where a scene went unscored: generations that failed (an endpoint
    request with no answer), outputs that did not parse, judgements that gave no scores. Each of
    those scenes fails QPR; the physics columns are over the parsed layouts only."""
    lines = []
    for name, m in methods.items():
        s = m["summary"]
        n = int(s.get("n", 0))
        gen, unparsed, judge = (int(s.get(k, 0)) for k in ("generation_failures", "parse_errors",
                                                             "judge_failures"))
        parts = []
        if gen:
            parts.append(f"{gen} of {n} generations failed (no answer from the endpoint)")
        if unparsed:
            parts.append(f"{unparsed} of {n} outputs did not parse")
        if judge:
            parts.append(f"{judge} of {n - gen - unparsed} judgements gave no scores")
        if parts:
            lines.append(f"{name}: " + "; ".join(parts))
    return lines


def paired_table(methods: Mapping[str, Mapping]) -> str:
    """Each method against the first, scene by scene (``paired`` of :func:`physcene.eval.harness.
    run_evaluation`): SCR of both on the scenes both parsed, the scenes that collide in one only, the
    exact McNemar p-value; empty when fewer than two methods."""
    rows = []
    for name, m in methods.items():
        pair = m.get("paired")
        if pair:
            rows.append([name, pair["against"], str(pair["scenes"]), _pct(pair["scr_first"]),
                         _pct(pair["scr_second"]), f"{100 * pair['difference']:+.1f}",
                         f"{pair['only_first']} / {pair['only_second']}", f"{pair['p_value']:.2g}"])
    if not rows:
        return ""
    return _table(["method", "against", "scenes", "SCR against", "SCR method", "difference (points)",
                   "collide in the first only / the method only", "McNemar p"], rows)


def threshold_table(methods: Mapping[str, Mapping]) -> str:
    """SCR (and ACR) under penetration thresholds 0 / 0.5 / 1.0 cm (appendix "Robustness")."""
    header = ["Collision threshold", *methods]
    rows = []
    for t in THRESHOLDS_CM:
        rows.append([f"{t:.1f} cm SCR", *[_pct(_get(m["summary"], "collision", float(t), "SCR"))
                                          for m in methods.values()]])
    for t in THRESHOLDS_CM:
        rows.append([f"{t:.1f} cm ACR", *[_pct(_get(m["summary"], "collision", float(t), "ACR"), 2)
                                          for m in methods.values()]])
    return _table(header, rows)


def diversity_table(methods: Mapping[str, Mapping]) -> str:
    """Distinct asset types and position std x / y (appendix "Generative Diversity")."""
    rows = [[name, str(m["diversity"]["asset_types"]),
             f"{_num(m['diversity']['pos_std_x'])} / {_num(m['diversity']['pos_std_y'])}"]
            for name, m in methods.items()]
    return _table(["Model", "Asset types", "Pos Std X / Y (cm)"], rows)


def _group_table(methods: Mapping[str, Mapping], key: str, label: str, groups: list) -> str:
    header = [label, "n", *[f"{name} QPR τ=7" for name in methods], *[f"{name} SCR" for name in methods],
              *[f"{name} Avg." for name in methods]]
    rows = []
    for g in groups:
        first = next(iter(methods.values()))[key]
        n = _get(first, g, "n")
        rows.append([str(g), str(n if not isinstance(n, float) else 0),
                     *[_pct(_get(m[key], g, "QPR", 7.0)) for m in methods.values()],
                     *[_pct(_get(m[key], g, "collision", 0.0, "SCR")) for m in methods.values()],
                     *[_num(_get(m[key], g, "judge", "avg")) for m in methods.values()]])
    return _table(header, rows)


def level_table(methods: Mapping[str, Mapping]) -> str:
    """QPR(τ=7), SCR and judge average per difficulty level."""
    present = sorted({int(k) for m in methods.values() for k in m["by_level"]})
    return _group_table(methods, "by_level", "Level", [lv for lv in DIFFICULTY_LEVELS if lv in present])


def type_table(methods: Mapping[str, Mapping]) -> str:
    """QPR(τ=7), SCR and judge average per scene type."""
    types = sorted({k for m in methods.values() for k in m["by_type"]})
    return _group_table(methods, "by_type", "Scene type", types)


def _save_figure(fig, path) -> None:
    """``fig`` as ``path`` (format from its suffix), renamed into place when complete."""
    with open_atomic(path, "wb") as fh:
        fig.savefig(fh, format=Path(path).suffix.lstrip(".") or "png")


def plot_qpr_by_level(methods: Mapping[str, Mapping], path: Path) -> Path:
    """Line plot of QPR(τ=7) against difficulty level, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.0, 3.4), dpi=120)
    for name, m in methods.items():
        levels = sorted(int(k) for k in m["by_level"])
        ax.plot(levels, [100 * _get(m["by_level"], lv, "QPR", 7.0) for lv in levels], marker="o", label=name)
    ax.set_xlabel("difficulty level (objects: 1-4, 5-8, 9-12, 13-16, 17+)")
    ax.set_ylabel("QPR (τ = 7), %")
    ax.set_xticks(list(DIFFICULTY_LEVELS))
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save_figure(fig, path)
    plt.close(fig)
    return path


def plot_type_radar(methods: Mapping[str, Mapping], path: Path) -> Path:
    """Radar chart of QPR(τ=7) per scene type, one polygon per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    types = sorted({k for m in methods.values() for k in m["by_type"]})
    fig = plt.figure(figsize=(5.0, 5.0), dpi=120)
    ax = fig.add_subplot(polar=True)
    if types:
        angles = np.linspace(0, 2 * np.pi, len(types), endpoint=False).tolist()
        for name, m in methods.items():
            vals = [100 * float(np.nan_to_num(_get(m["by_type"], t, "QPR", 7.0))) for t in types]
            ax.plot(angles + angles[:1], vals + vals[:1], marker="o", label=name)
            ax.fill(angles + angles[:1], vals + vals[:1], alpha=0.12)
        ax.set_xticks(angles)
        ax.set_xticklabels(types, fontsize=8)
        ax.set_ylim(0, 100)
    ax.set_title("QPR (τ = 7) per scene type, %", fontsize=9)
    ax.legend(fontsize=7, loc="lower right", bbox_to_anchor=(1.15, -0.1))
    fig.tight_layout()
    _save_figure(fig, path)
    plt.close(fig)
    return path


def method_slug(name: str) -> str:
    """The folder name of a method's layouts and renders (``Reference + TTO`` -> ``reference_tto``): one
    path component, whatever the name holds (``Layouts (docs/x/sft.jsonl.gz)`` ->
    ``layouts_docs_x_sft.jsonl.gz``)."""
    return re.sub(r"[^a-z0-9._-]+", "_", name.lower().replace(" + ", "_")).strip("_.") or "method"


def write_comparisons(out_dir, scene_ids: Sequence[str], method_names: Sequence[str], *, labels: bool = False,
                      size: tuple[int, int] = (800, 600), view: str = "perspective") -> dict[str, str]:
    """``renders/compare/<id>.png``: the methods' layouts of each scene side by side with their
    penetrating pairs' depths (:func:`physcene.eval.render.render_comparison`), read from
    ``layouts/<method>/<id>.json`` (``save_layouts``). Returns id -> path relative to ``out_dir``;
    scenes without saved layouts are left out."""
    out = Path(out_dir)
    sheets = {}
    for scene_id in scene_ids:
        found = {name: out / "layouts" / method_slug(name) / f"{scene_id}.json" for name in method_names}
        scenes = {name: read_layout(p) for name, p in found.items() if p.is_file()}
        if not scenes:
            continue
        path = out / "renders" / "compare" / f"{scene_id}.png"
        write_atomic(path, png_bytes(render_comparison(scenes, view, size=size, labels=labels)))
        sheets[scene_id] = str(path.relative_to(out))
    return sheets


def write_report(out_dir, methods: Mapping[str, Mapping], *, title: str, command: str = "",
                 renders: Mapping[str, Mapping[str, str]] | None = None, labels: bool = False,
                 comparison_size: tuple[int, int] = (800, 600)) -> Path:
    """report.md (all tables, plots, renders) + qpr_by_level.png + qpr_by_type_radar.png.

    With ``renders`` and the methods' saved layouts, each rendered scene also gets a comparison
    sheet (:func:`write_comparisons`, panels of ``comparison_size`` px, object ids with ``labels``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plot_qpr_by_level(methods, out / "qpr_by_level.png")
    plot_type_radar(methods, out / "qpr_by_type_radar.png")
    n = next(iter(methods.values()))["summary"]["n"] if methods else 0
    parts = [f"# {title}", ""]
    if command:
        parts += ["Produced by:", "", "```bash", command, "```", ""]
    parts += [f"{n} scenes per method. QPR(τ) = share of scenes with judge average ≥ τ and no pair "
              "penetrating deeper than 0 cm; SCR/ACR at 0 cm (paper appendix).", "",
              "## Main results", "", main_table(methods), ""]
    failures = failure_lines(methods)
    if failures:
        parts += ["**Not every scene was scored** (each such scene fails QPR; the physics columns are "
                  "over the parsed layouts):", "", *[f"- {line}" for line in failures], ""]
    paired = paired_table(methods)
    if paired:
        parts += ["## Paired against the first method", "",
                  "The same scenes, scene by scene (those both parsed): SCR of each, the scenes that "
                  "collide in one only, and the exact two-sided McNemar p-value of the difference.", "",
                  paired, ""]
    parts += ["## Per difficulty level", "", level_table(methods), "",
              "![QPR by level](qpr_by_level.png)", "",
              "## Per scene type", "", type_table(methods), "", "![QPR by type](qpr_by_type_radar.png)", "",
              "## Robustness to collision thresholds", "", threshold_table(methods), "",
              "## Diversity", "", diversity_table(methods), ""]
    if renders:
        parts += ["## Renders", ""]
        sheets = write_comparisons(out, list(renders), list(methods), labels=labels, size=comparison_size)
        if sheets:
            parts += ["Each method's layout of a scene side by side; red: penetrating pairs with their "
                      "depth (cm).", ""]
        for scene_id, views in renders.items():
            parts.append(f"**{scene_id}**  ")
            if scene_id in sheets:
                parts += [f"![{scene_id}: methods side by side]({sheets[scene_id]})", ""]
            parts.append(" ".join(f"![{label}]({p})" for label, p in views.items()))
            parts.append("")
    return write_atomic(out / "report.md", "\n".join(parts))
