"""The ablation's learning curves: SCR against RL steps, one line per variant and seed, drawn from
``ablation.json`` (:mod:`physcene.train.ablation`) as an SVG written directly (no plotting library:
the figure is text, the same rows always give the same bytes, and it diffs in review).

Each RL variant's line starts at its seed's SFT row (step 0: the base it was trained from) and goes
through its checkpoint rows (``pada@50`` ...) to its final row; the reference and SFT + TTO rows are
drawn as dashed horizontal lines.
"""

from __future__ import annotations

import json
from collections import defaultdict
from html import escape
from pathlib import Path

__all__ = ["learning_curves", "learning_curves_svg", "write_learning_curves"]

_RL = ("grpo", "pada*", "pada")
_LEVELS = ("reference", "sft+tto")
_COLOURS = {"grpo": "#1f77b4", "pada*": "#ff7f0e", "pada": "#2ca02c", "reference": "#555555",
            "sft+tto": "#9467bd"}
_DASHES = ("", "6 3", "2 2", "8 3 2 3")  # one per seed


def learning_curves(data: dict) -> dict[tuple[str, int], list[tuple[int, float]]]:
    """``{(variant, seed): [(rl_steps, scr), ...]}`` in step order: every RL variant's rows (final and
    checkpoint), starting from the seed's SFT row at step 0; ``reference`` and ``sft+tto`` as one
    point each. Rows without an SCR (nothing parsed) or skipped are left out."""
    rows = [r for r in [*data.get("rows", []), *data.get("checkpoint_rows", [])]
            if "skipped" not in r and r.get("scr") is not None]
    sft = {int(r.get("seed", 0)): float(r["scr"]) for r in rows if r["name"] == "sft"}
    curves: dict[tuple[str, int], dict[int, float]] = defaultdict(dict)
    for r in rows:
        name, seed = r["name"].split("@")[0], int(r.get("seed", 0))
        if name in _RL:
            curves[(name, seed)][int(r.get("rl_steps") or 0)] = float(r["scr"])
        elif name in _LEVELS:
            curves[(name, seed)][0] = float(r["scr"])
    for (name, seed), points in curves.items():
        if name in _RL and seed in sft:
            points.setdefault(0, sft[seed])
    return {key: sorted(points.items()) for key, points in sorted(curves.items())}


def learning_curves_svg(data: dict, *, width: int = 640, height: int = 400) -> str:
    """The curves of :func:`learning_curves` as an SVG document (SCR in %, 0 to 100)."""
    curves = learning_curves(data)
    left, right, top, bottom = 56, 150, 20, 44
    plot_w, plot_h = width - left - right, height - top - bottom
    max_step = max([s for points in curves.values() for s, _ in points] + [1])

    def x(step: float) -> float:
        return left + plot_w * step / max_step

    def y(scr: float) -> float:
        return top + plot_h * (1.0 - scr)

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="11">',
           f'<rect width="{width}" height="{height}" fill="white"/>']
    for k in range(6):  # SCR grid every 20 %
        v = k / 5
        out.append(f'<line x1="{left}" y1="{y(v):.1f}" x2="{left + plot_w}" y2="{y(v):.1f}" stroke="#ddd"/>')
        out.append(f'<text x="{left - 6}" y="{y(v) + 4:.1f}" text-anchor="end">{round(100 * v)}%</text>')
    for k in range(6):
        step = max_step * k / 5
        out.append(f'<text x="{x(step):.1f}" y="{top + plot_h + 16}" text-anchor="middle">{step:g}</text>')
    axis = top + plot_h
    out.append(f'<line x1="{left}" y1="{axis}" x2="{left + plot_w}" y2="{axis}" stroke="black"/>')
    out.append(f'<line x1="{left}" y1="{top}" x2="{left}" y2="{top + plot_h}" stroke="black"/>')
    out.append(f'<text x="{left + plot_w / 2:.1f}" y="{height - 8}" text-anchor="middle">RL steps</text>')
    out.append(f'<text transform="translate(14 {top + plot_h / 2:.1f}) rotate(-90)" text-anchor="middle">'
               'SCR (scenes with a collision)</text>')
    seeds = sorted({seed for _, seed in curves})
    for n, ((name, seed), points) in enumerate(curves.items()):
        colour = _COLOURS.get(name, "black")
        dash = _DASHES[seeds.index(seed) % len(_DASHES)]
        label = escape(f"{name} (seed {seed})" if len(seeds) > 1 else name)
        if name in _LEVELS:  # a level, not a curve
            v = points[0][1]
            out.append(f'<line x1="{left}" y1="{y(v):.1f}" x2="{left + plot_w}" y2="{y(v):.1f}" '
                       f'stroke="{colour}" stroke-dasharray="4 4"/>')
        else:
            path = " ".join(f"{x(s):.1f},{y(v):.1f}" for s, v in points)
            out.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="2"'
                       + (f' stroke-dasharray="{dash}"' if dash else "") + "/>")
            out += [f'<circle cx="{x(s):.1f}" cy="{y(v):.1f}" r="3" fill="{colour}"/>' for s, v in points]
        ly = top + 14 * n + 8
        out.append(f'<line x1="{left + plot_w + 10}" y1="{ly}" x2="{left + plot_w + 30}" y2="{ly}" '
                   f'stroke="{colour}" stroke-width="2"/>')
        out.append(f'<text x="{left + plot_w + 34}" y="{ly + 4}">{label}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def write_learning_curves(data: dict | str | Path, path: str | Path | None = None) -> Path:
    """Write the SVG of ``data`` (an ablation.json dict or its path) to ``path`` (default: the JSON's
    path with ``.svg``); returns the path."""
    if not isinstance(data, dict):
        source = Path(data)
        if not source.is_file():
            raise FileNotFoundError(f"ablation table {source} does not exist (`physcene train ablation` "
                                    "writes it)")
        data, path = json.loads(source.read_text()), path or source.with_suffix(".svg")
    if path is None:
        raise ValueError("write_learning_curves: a path is needed for an ablation dict")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(learning_curves_svg(data))
    return path
