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

Decoding and scoring can run on two machines: ``--decode-only`` writes each row's completions to
``<out stem>/<row>.completions.jsonl.gz`` with the decoding's settings in ``<out stem>/decoding.json``
and scores nothing (no Warp imported: a GPU host decodes, given the assets' bake cache or Warp to bake
them, since the split's scenes are built from them), and ``--completions DIR`` scores the
completions a decode wrote (a CPU with Warp scores), on the same split, ``n`` and seed::

    python -m physcene.train.analysis.plan_following runs/medium/sft --n 866 --device cuda --cache fast \
        --batch-size 512 --rows sft+plan --decode-only --out decoded.json
    python -m physcene.train.analysis.plan_following --completions decoded --n 866 --rows sft+plan \
        --out plan_following.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from physcene.ctrc import completion_text, parse
from physcene.layout import records_by_id, row_file, write_layout_records
from physcene.scene import TABLE, Scene
from physcene.train.constrained.grammar import listed_instance_ids, planned_entries
from physcene.train.generate import generate_with, input_format, load_for_generation, sampling

__all__ = ["ROWS", "CompletionsError", "plan_agreement", "read_completions", "run", "write_completions"]

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


class CompletionsError(ValueError):
    """A decode's completions (``--completions DIR``) that do not fit the scenes asked for: a missing file
    or scene, a malformed record, another split, seed or n; or asked for with a model or --decode-only."""


def completions_file(directory: Path, row: str) -> Path:
    """Where a decode keeps ``row``'s completions: ``sft+plan`` -> ``sft_plan.completions.jsonl.gz``."""
    return Path(directory) / row_file(row, ".completions.jsonl.gz")


def write_completions(directory: Path, items, decoded: dict[str, list[str]], decoding: dict) -> Path:
    """Each row's completions as ``{"id", "completion"}`` records (``completions_file``) and the
    decoding's settings as ``decoding.json``, under ``directory``; returns ``directory``."""
    directory = Path(directory)
    for row, texts in decoded.items():
        write_layout_records([{"id": it.id, "completion": t} for it, t in zip(items, texts)],
                             completions_file(directory, row))
    (directory / "decoding.json").write_text(json.dumps(decoding, indent=1))
    return directory


def read_completions(directory: Path, items, rows, *, split: str,
                     seed: int) -> tuple[dict[str, list[str]], dict]:
    """The completions a decode of ``split`` at ``seed`` wrote (:func:`write_completions`) for ``rows``, in
    ``items``' order, and its ``decoding.json``; a :class:`CompletionsError` names a missing file, a
    decode of another split or seed, a record without an id or completion, the first scene of ``items``
    the decode did not write (it decoded fewer scenes), or a decode of more scenes (another draw)."""
    directory = Path(directory)
    meta_path = directory / "decoding.json"
    if not meta_path.is_file():
        raise CompletionsError(f"--completions {directory}: no decoding.json (write it with --decode-only)")
    decoding = json.loads(meta_path.read_text())
    if (decoding.get("split"), decoding.get("seed")) != (split, seed):
        raise CompletionsError(f"--completions {directory}: decoded on split {decoding.get('split')} seed "
                               f"{decoding.get('seed')}, asked to score split {split} seed {seed}")
    decoded = {}
    for row in rows:
        path = completions_file(directory, row)
        if not path.is_file():
            raise CompletionsError(f"--completions {directory}: no {path.name} (the decode's rows: "
                                   f"{decoding.get('rows')})")
        by_id = {}
        for key, (number, record) in records_by_id(path, error=CompletionsError).items():
            if not isinstance(record.get("completion"), str):
                raise CompletionsError(f"{path}:{number}: a record needs a 'completion' string")
            by_id[key] = record["completion"]
        missing = [it.id for it in items if it.id not in by_id]
        if missing:
            raise CompletionsError(f"{path}: no completion for scene {missing[0]!r} ({len(missing)} of "
                                   f"{len(items)} missing; the decode: split {decoding.get('split')}, "
                                   f"n {decoding.get('n')}, seed {decoding.get('seed')})")
        decoded[row] = [by_id[it.id] for it in items]
    if decoding.get("n") != len(items):  # ids are positions in a draw that depends on n: other scenes
        raise CompletionsError(f"--completions {directory}: decoded {decoding.get('n')} scenes, asked to "
                               f"score {len(items)}: a draw of another n holds other scenes under its ids")
    return decoded, decoding


def run(model_path: str | None, *, n: int, out: Path, split: str = "test", seed: int = 0,
        temperature: float = 0.0, max_new_tokens: int = 3072, batch_size: int = 32, cache: str = "dynamic",
        device: str = "cpu", rows: tuple[str, ...] = ROWS, progress: bool = True, decode_only: bool = False,
        completions: Path | None = None) -> dict:
    """The study's JSON (written to ``out``; each row's layouts to ``<out stem>/<row>.jsonl.gz``);
    ``rows``: the model's rows decoded, of :data:`ROWS` (the reference's row is always there).
    ``decode_only``: write the rows' completions (:func:`write_completions`) to ``<out stem>/`` and return
    the decoding's settings, scoring nothing; ``completions``: score the completions a decode wrote there
    instead of decoding (``model_path`` is then None)."""
    unknown = sorted(set(rows) - set(ROWS))
    if unknown or not rows:
        raise ValueError(f"rows {list(rows)}: expected one or more of {list(ROWS)}")
    if (model_path is None) == (completions is None) or (decode_only and completions is not None):
        raise CompletionsError("give a model checkpoint to decode, or --completions DIR to score a decode's "
                               "completions (not both; --decode-only only with a model)")
    from physcene.eval.harness import load_benchmark

    items = load_benchmark(split, n=n, seed=seed, progress=False)
    prompts = [it.prompt for it in items]
    wanted = [r for r in ROWS if r in rows]
    command = " ".join(["python -m physcene.train.analysis.plan_following", *sys.argv[1:]])
    if completions is not None:
        decoded, decoding = read_completions(completions, items, wanted, split=split, seed=seed)
    else:
        model, tokenizer, info = load_for_generation(model_path, device=device)
        decoded = {name: generate_with(model, tokenizer, prompts, **input_format(info),
                                       max_new_tokens=max_new_tokens, batch_size=batch_size, seed=seed,
                                       **sampling(temperature), cache=cache, constrained=True,
                                       follow_plan=name == "sft+plan")
                   for name in wanted}
        decoding = {"model": str(model_path), "split": split, "n": len(items), "seed": seed, "device": device,
                    "gpu": torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu",
                    "decoding": {"constrained": True, "temperature": temperature, "cache": cache,
                                 "max_new_tokens": max_new_tokens},
                    "rows": wanted, "commands": [command]}
        if decode_only:
            where = write_completions(out.with_suffix(""), items, decoded, decoding)
            if progress:
                print(f"completions of {wanted} for {len(items)} scenes: {where}/", file=sys.stderr)
            return decoding

    from physcene.eval.harness import generate, make_judge, score_scenes
    from physcene.physics import PhysicsEngine  # here: a decode alone needs no Warp
    from physcene.train.ablation import table_row

    judge = make_judge("rule", [it.reference for it in items])
    engine = PhysicsEngine(device=device)
    layouts = out.with_suffix("")
    table = []

    def add_row(name: str, outputs: list, texts: list[str]) -> None:
        results = score_scenes(items, outputs, judge, engine, progress=False)
        row = table_row(name, items, outputs, results, engine, seed=seed, rl_steps=0, layouts=layouts)
        row.update(plan_agreement(prompts, texts))
        table.append(row)
        if progress:
            keys = ("scr", "parse_rate", "on_table", "order_kept", "parent_kept")
            print(f"{name}: " + ", ".join(f"{k} {row[k]}" for k in keys), file=sys.stderr)

    references = [it.reference for it in items]
    add_row("reference", references, [completion_text(s) for s in references])
    for name, texts in decoded.items():
        outputs = generate(items, "model:study", progress=False,
                           generators={"model:study": lambda _items, c=texts: c})
        add_row(name, outputs, texts)
    result = {
        "what": __doc__.splitlines()[0],
        **{k: decoding[k] for k in ("model", "split", "n", "seed", "device", "gpu", "decoding")},
        "commands": [*decoding["commands"], command] if completions is not None else [command],
        "rows": table,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", nargs="?", help="checkpoint directory (SFT or merged RL model)")
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
    parser.add_argument("--decode-only", action="store_true",
                        help="write the rows' completions to <out stem>/ and score nothing (imports no Warp)")
    parser.add_argument("--completions", type=Path, default=None, metavar="DIR",
                        help="score the completions --decode-only wrote to DIR instead of decoding")
    args = parser.parse_args()
    if args.n < 1 or args.temperature < 0 or args.max_new_tokens < 1 or args.batch_size < 1:
        parser.error("--n, --max-new-tokens and --batch-size must be >= 1 and --temperature >= 0")
    try:
        run(args.model, n=args.n, out=args.out, split=args.split, seed=args.seed,
            temperature=args.temperature, max_new_tokens=args.max_new_tokens, batch_size=args.batch_size,
            cache=args.cache, device=args.device, rows=tuple(args.rows), decode_only=args.decode_only,
            completions=args.completions)
    except CompletionsError as exc:
        parser.error(str(exc))


if __name__ == "__main__":
    main()
