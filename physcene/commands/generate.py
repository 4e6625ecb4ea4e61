"""``physcene generate``: a text instruction in, tabletop layouts out (docs/generate.md).

    physcene generate "a desk with a laptop, two mugs and a pen in the pen holder" -o out
    physcene generate "a dining table set for two, with plates, glasses, a vase and a bowl of fruit" \\
        -o out --n 4 --repair --export mjcf
    physcene generate "..." --generator endpoint:http://127.0.0.1:8000/v1 --endpoint-model qwen3
    physcene generate "..." --generator model:runs/tiny/pada --json

Per sample ``out/sample_<k>/`` holds the CTRC completion, ``layout.json`` (MesaTask), ``check.json``
(pairs by id, floating ids, table penetration), front and perspective renders, with ``--repair`` the
TTO-repaired layout and its report, with ``--export`` the simulator files; ``out/generate.json`` sums
it up. Exit 0 when every sample produced a layout, 1 when some did not, 2 on a bad request (an
unknown generator, an unreachable endpoint, a missing model).
"""

from __future__ import annotations

import json
import sys

from physcene.artifacts import resolve_generators
from physcene.commands import add_quiet

NAME = "generate"
HELP = "Generate tabletop layouts from a text instruction (procedural, endpoint:URL or model:PATH)"


def add_arguments(parser) -> None:
    parser.add_argument("instruction", help="what the table should hold, e.g. 'a desk with a laptop and "
                                            "a pen in the pen holder'")
    parser.add_argument("--generator", default="procedural",
                        help="procedural (default, offline), endpoint:URL (OpenAI-compatible chat server, "
                             "key in $PHYSCENE_GENERATOR_API_KEY) or model:PATH (a checkpoint of "
                             "physcene train, or an artifact's name: docs/training.md)")
    parser.add_argument("--n", type=int, default=1, help="number of samples (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--repair", action="store_true", help="also repair every sample by TTO")
    parser.add_argument("-o", "--output", default="physcene-generate", metavar="DIR",
                        help="output folder (default: physcene-generate)")
    parser.add_argument("--export", choices=("mjcf", "urdf", "glb"), action="append", default=[],
                        help="also write simulator files in this format (repeatable)")
    parser.add_argument("--scene-type", help="table type, when the instruction does not name it")
    parser.add_argument("--endpoint-model", default="default", help="model name sent to an endpoint")
    parser.add_argument("--max-new-tokens", type=int, default=4096,
                        help="model:PATH: the longest completion, in tokens (default 4096)")
    parser.add_argument("--device", default="cpu", help="physics/TTO/model device: cpu (default), cuda")
    parser.add_argument("--no-render", action="store_true", help="skip the PNG renders")
    parser.add_argument("--json", action="store_true", help="print generate.json's content")
    add_quiet(parser)


def _line(sample) -> str:
    if sample.error:
        return f"sample {sample.index}: ERROR {sample.error}"
    c = sample.check
    text = (f"sample {sample.index}: {c['objects']} objects, {len(c['pairs'])} penetrating pair(s), "
            f"max depth {c['max_depth_cm']:.2f} cm, floating: {', '.join(c['floating']) or 'none'}")
    if sample.repair_report is not None:
        r = sample.repair_report["check"]
        text += (f"; repaired: {len(r['pairs'])} pair(s), max depth {r['max_depth_cm']:.2f} cm, "
                 f"floating: {', '.join(r['floating']) or 'none'}")
    return text


def run(args) -> int:
    from physcene.generation import generate

    if args.n < 1:
        raise ValueError(f"--n must be >= 1, got {args.n}")
    generator = resolve_generators(args.generator)  # model:NAME of an artifact -> its restored folder
    result = generate(args.instruction, generator=generator, n=args.n, seed=args.seed,
                      repair=args.repair, out=args.output, export=args.export, render=not args.no_render,
                      scene_type=args.scene_type, device=args.device, endpoint_model=args.endpoint_model,
                      max_new_tokens=args.max_new_tokens, progress=not args.quiet)
    reading = result.instruction
    if args.json:
        print(json.dumps(result.summary(), indent=1))
    else:
        named = ", ".join(f"{m.count or ''} {m.word}".strip() for m in reading.mentions) or "nothing named"
        print(f"{reading.scene_type}: {named}")
        for r in reading.relations:
            print(f"  {reading.mentions[r.child].word} {r.relation} the {reading.mentions[r.parent].word}")
        for sample in result:
            print(_line(sample))
        print(f"written: {result.out}/ (generate.json)")
    if reading.unknown:
        print(f"physcene generate: not understood (ignored): {', '.join(reading.unknown)}", file=sys.stderr)
    return 0 if all(s.scene is not None for s in result) else 1
