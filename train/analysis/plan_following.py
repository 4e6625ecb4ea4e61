"""Does a layout model's layout follow its own plan, and what changes when the constraint makes it?

    python -m physcene.train.analysis.plan_following runs/cpu/sft --n 96 --out plan_following.json

The first ``n`` scenes of the test split are decoded twice by one checkpoint under the CTRC constraint
(greedy, or sampled at ``--temperature``): row ``sft`` with the layout's order and parents left to the
model (``follow_plan=False``), row ``sft+plan`` with them taken from the completion's own plan
(:func:`~physcene.train.constrained.grammar.planned_entries`). Both, and the split's reference layouts,
are scored as the ablation scores its rows (SCR, ACR, QPR, rule judge, parse rate and the shares of
floating, shrunk and out-of-zone objects; :func:`physcene.train.ablation.table_row`), with each row's
layouts kept beside the JSON. Each row also says how its layouts relate to their plans:

- ``on_table``: the share of objects whose parent is the table;
- ``order_kept``: the share of parsed scenes whose layout lists the objects in the plan's order;
- ``parent_kept``: of the plan steps that name where an object goes (``Place X in|on Y.`` or a
  table-level step), the share whose layout entry has that parent and relation.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from physcene.ctrc import completion_text, parse
from physcene.scene import TABLE, Scene
from physcene.train.ablation import table_row
from physcene.train.constrained.grammar import listed_instance_ids, planned_entries
from physcene.train.generate import generate_with, load_for_generation, sampling

__all__ = ["ROWS", "plan_agreement", "run"]

ROWS = ("sft", "sft+plan")
"""The model's rows: its layouts with the order and parents free, and taken from its own plan."""


def plan_agreement(prompts: list[str], completions: list[str]) -> dict:
    """``on_table``, ``order_kept`` and ``parent_kept`` (module docstring) of the completions of
    ``prompts``; a figure is None when nothing counts towards it."""
    objects = table = scenes = ordered = steps = kept = 0
    for prompt, text in zip(prompts, completions):
        scene = parse(text)
        if not isinstance(scene, Scene):
            continue
        objects += len(scene.objects)
        table += sum(o.parent == TABLE for o in scene.objects)
        plan = planned_entries(text, listed_instance_ids(prompt))
        if plan is None:
            continue
        scenes += 1
        ordered += [e.iid for e in plan] == [o.instance_id for o in scene.objects]
        placed = {o.instance_id: o for o in scene.objects}
        for e in plan:
            if e.parent is None or e.iid not in placed:
                continue
            steps += 1
            o = placed[e.iid]
            kept += o.parent == e.parent and (e.parent == TABLE or o.relation == e.relation)
    share = (lambda k, n: k / n if n else None)  # noqa: E731
    return {"on_table": share(table, objects), "order_kept": share(ordered, scenes),
            "parent_kept": share(kept, steps), "scenes_with_plan": scenes}


def run(model_path: str, *, n: int, out: Path, split: str = "test", seed: int = 0, temperature: float = 0.0,
        max_new_tokens: int = 3072, batch_size: int = 32, cache: str = "dynamic", device: str = "cpu",
        rows: tuple[str, ...] = ROWS, progress: bool = True) -> dict:
    """The study's JSON (written to ``out``; each row's layouts to ``<out stem>/<row>.jsonl.gz``);
    ``rows``: the model's rows decoded, of :data:`ROWS` (the reference's row is always there)."""
    unknown = sorted(set(rows) - set(ROWS))
    if unknown or not rows:
        raise ValueError(f"rows {list(rows)}: expected one or more of {list(ROWS)}")
    from physcene.eval.harness import generate, load_benchmark, make_judge, score_scenes
    from physcene.physics import PhysicsEngine

    items = load_benchmark(split, n=n, seed=seed, progress=False)
    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine(device=device)
    layouts = out.with_suffix("")
    model, tokenizer, info = load_for_generation(model_path, device=device)
    prompts = [it.prompt for it in items]
    table = []

    def add_row(name: str, outputs: list, completions: list[str]) -> None:
        results = score_scenes(items, outputs, judge, engine, progress=False)
        row = table_row(name, items, outputs, results, engine, seed=seed, rl_steps=0, layouts=layouts)
        row.update(plan_agreement(prompts, completions))
        table.append(row)
        if progress:
            keys = ("scr", "parse_rate", "on_table", "order_kept", "parent_kept")
            print(f"{name}: " + ", ".join(f"{k} {row[k]}" for k in keys), file=sys.stderr)

    references = [it.reference for it in items]
    add_row("reference", references, [completion_text(s) for s in references])
    for name in (r for r in ROWS if r in rows):
        follow = name == "sft+plan"
        completions = generate_with(model, tokenizer, prompts,
                                    chat_format=bool(info.get("chat_format", False)),
                                    max_new_tokens=max_new_tokens, batch_size=batch_size,
                                    seed=seed, **sampling(temperature),
                                    cache=cache, constrained=True, follow_plan=follow)
        outputs = generate(items, "model:study", progress=False,
                           generators={"model:study": lambda _items, c=completions: c})
        add_row(name, outputs, completions)
    result = {
        "what": __doc__.splitlines()[0],
        "model": str(model_path), "split": split, "n": len(items), "seed": seed, "device": device,
        "gpu": torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu",
        "decoding": {"constrained": True, "temperature": temperature, "cache": cache,
                     "max_new_tokens": max_new_tokens},
        "commands": [" ".join(["python -m physcene.train.analysis.plan_following", *sys.argv[1:]])],
        "rows": table,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="checkpoint directory (SFT or merged RL model)")
    parser.add_argument("--n", type=int, default=96, help="first N scenes of the split (default 96)")
    parser.add_argument("--split", default="test", choices=["test", "ood", "train"])
    parser.add_argument("--seed", type=int, default=0, help="the split's and the sampling's seed")
    parser.add_argument("--temperature", type=float, default=0.0, help="0: greedy (default); else sampled")
    parser.add_argument("--max-new-tokens", type=int, default=3072)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--cache", default="dynamic", help="KV cache of generation (docs/training.md)")
    parser.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N (generation and physics)")
    parser.add_argument("--out", type=Path, default=Path("plan_following.json"))
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS),
                        help="the model's rows: sft (plan free), sft+plan (default: both)")
    args = parser.parse_args()
    if args.n < 1 or args.temperature < 0 or args.max_new_tokens < 1 or args.batch_size < 1:
        parser.error("--n, --max-new-tokens and --batch-size must be >= 1 and --temperature >= 0")
    run(args.model, n=args.n, out=args.out, split=args.split, seed=args.seed, temperature=args.temperature,
        max_new_tokens=args.max_new_tokens, batch_size=args.batch_size, cache=args.cache, device=args.device,
        rows=tuple(args.rows))


if __name__ == "__main__":
    main()
