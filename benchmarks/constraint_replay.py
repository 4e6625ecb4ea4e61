"""The CTRC constraint's host work in PADA's rollouts, recorded once and replayed: old against new.

    python benchmarks/constraint_replay.py record --model small-sft-physics \
        --records artifacts/rl-anchors/anchors.jsonl.gz --n 128 --max-new-tokens 2304 --out trace.pt
    python benchmarks/constraint_replay.py replay trace.pt --against 21621c8 --rounds 5 --json out.json

Under the constraint the fast decoder's host checks step t's tokens while the GPU runs step t + 1
(:class:`~physcene.train.decode.OverlappedConstraint`); when the check takes longer than a step, it is
the rollout's critical path (the RL study's rounds: ``time/decode_host_check_s`` 3.9 of 4.8 s of
generation). ``record`` samples a round as PADA does (the fast decoder, temperature 1, one row per
prompt, the checkpoint's prompt format) and keeps every call of the check: the step's tokens, the
candidates copied with them, the rows skipped, the random state, the logits of each row the check
read, and what it returned. ``replay`` feeds those calls to a fresh constraint and times the checks
alone; each call must return what it returned when recorded, and the round must end with the same
tokens and counters, so a faster check is also an equal one. ``--against REV`` replays the same
trace with the code of each git revision (a worktree of its own, in a subprocess), round by round
interleaved with the working tree's, so load that changes during the run hits every version alike.
The trace depends on the tokenizer and prompts only (no model is loaded by ``replay``). ``score``
gives the physics reward's figures of the rollouts a trace holds (collision-free and invalid shares,
the validity terms': what a round of that sampling gives RL to learn from). ``profile`` replays a trace
once under cProfile (after an untimed round) and lists the functions that hold the check's time, with
the share spent inside regular-expression matching: where a faster check must save. ``streams`` (a GPU's
measure) samples the same round with the logits the check reads on a stream of their own
(``FastDecoder.reads_stream``, the default) and on the decoding stream, where they wait for the step
launched before the check, and reports each one's seconds a round and host-check seconds.

    python benchmarks/constraint_replay.py streams --model small-sft-physics \
        --records artifacts/rl-anchors/anchors.jsonl.gz --n 128 --rounds 3 --json out.json
    python benchmarks/constraint_replay.py profile trace.pt --top 15 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _round_inputs(args: argparse.Namespace):
    """The model, tokenizer, run info and the ``--n`` prompts of ``args`` (levels ``--levels``), in the
    order generate_token_ids batches them (by rendered length; a stable sort): the constraint's rows."""
    from physcene.artifacts import resolve_model
    from physcene.train.generate import input_format, load_for_generation, render_prompt
    from physcene.train.records import load_records

    model_path = resolve_model(args.model)
    records = [r for r in load_records(args.records) if not args.levels or r.get("level") in args.levels]
    prompts = [r["prompt"] for r in records[:args.n]]
    if len(prompts) < args.n:
        raise SystemExit(f"{args.records} has {len(prompts)} prompts of levels {args.levels}, "
                         f"{args.n} asked for")
    model, tokenizer, info = load_for_generation(model_path, device=args.device)
    rendered = {p: len(render_prompt(tokenizer, p, **input_format(info))) for p in prompts}
    prompts.sort(key=rendered.__getitem__)
    return model_path, model, tokenizer, info, prompts


def record(args: argparse.Namespace) -> None:
    from physcene.train import decode
    from physcene.train.generate import generate_token_ids, input_format

    model_path, model, tokenizer, info, prompts = _round_inputs(args)
    calls: list[dict] = []
    seeds: list = []

    class Recording(decode.OverlappedConstraint):
        def check(self, tokens, candidates, skip, logits_row):
            read: dict[int, torch.Tensor] = {}

            def reading(b: int) -> torch.Tensor:
                read[b] = logits_row(b).float().cpu().clone()
                return logits_row(b)

            rng = torch.get_rng_state()
            seeds.append(getattr(self, "seed", None))
            corrections = super().check(tokens, candidates, skip, reading)
            calls.append({"tokens": list(tokens), "candidates": [list(c) for c in candidates],
                          "skip": sorted(skip), "rng": rng, "logits": read, "corrections": dict(corrections)})
            return corrections

    decode.OverlappedConstraint = Recording  # fast_generate builds its check from the package
    report: list = []
    start = time.perf_counter()
    generate_token_ids(model, tokenizer, prompts, **input_format(info), max_new_tokens=args.max_new_tokens,
                       batch_size=len(prompts), do_sample=True, temperature=args.temperature, seed=args.seed,
                       cache=args.cache, constrained=True, report=report)
    result = report[0]
    trace = {"model": str(Path(model_path).resolve()), "prompts": prompts,
             "max_new_tokens": args.max_new_tokens,
             "temperature": args.temperature, "eos": [tokenizer.eos_token_id], "calls": calls,
             "tokens": result.tokens, "steps": result.steps, "seed": seeds[0] if seeds else None,
             "repairs": result.repairs,
             "host_check_s": result.seconds["host_check"], "device": str(model.device),
             "command": " ".join(sys.argv)}
    torch.save(trace, args.out)
    print(f"recorded {len(prompts)} rows x {result.steps} steps ({result.repairs} repairs) in "
          f"{time.perf_counter() - start:.1f} s; host check {result.seconds['host_check']:.2f} s "
          f"-> {args.out}")


def replay_once(trace: dict, tokenizer, workers: int = 0, profiler=None) -> dict:
    """One round: a fresh constraint fed the recorded calls (``workers``: checked by that many worker
    processes); the seconds in its checks, and whether each call and the round's end agree with the
    recording. ``profiler`` (a ``cProfile.Profile``) runs during the checks alone."""
    import inspect

    from transformers import GenerationConfig, LogitsProcessorList

    from physcene.train.constrained import CTRCConstraint, sampling_warpers
    from physcene.train.decode import OverlappedConstraint

    # the warpers generate_token_ids sampled the round with: the checkpoint's generation config at the
    # round's temperature
    config = GenerationConfig.from_pretrained(trace["model"])
    config.update(do_sample=True, temperature=trace["temperature"])
    warpers = sampling_warpers(config) or LogitsProcessorList()
    constraint = CTRCConstraint(tokenizer, trace["prompts"], greedy=False, warpers=warpers)
    kwargs = dict(max_new_tokens=trace["max_new_tokens"], eos=trace["eos"], warpers=warpers)
    if "seed" in inspect.signature(OverlappedConstraint).parameters:  # a refused draw's seeded redraw
        kwargs["seed"] = trace.get("seed") or 0
    if workers:
        from physcene.train.decode import ShardedConstraint, constraint_pool

        check = ShardedConstraint(constraint, pool=constraint_pool(tokenizer, workers), **kwargs)
    else:
        check = OverlappedConstraint(constraint, **kwargs)
    seconds, differing, unread = 0.0, 0, 0
    for call in trace["calls"]:

        def logits_row(b: int, logits: dict = call["logits"]) -> torch.Tensor:
            nonlocal unread
            if b not in logits:  # the check reads a row it did not read when recorded: counted, unequal
                unread += 1
                return torch.full((len(tokenizer),), float("-inf"))
            return logits[b]

        torch.set_rng_state(call["rng"])
        if profiler is not None:
            profiler.enable()
        start = time.perf_counter()
        corrections = check.check(call["tokens"], call["candidates"], set(call["skip"]), logits_row)
        seconds += time.perf_counter() - start
        if profiler is not None:
            profiler.disable()
        differing += corrections != call["corrections"]
    return {"seconds": seconds, "calls": len(trace["calls"]), "differing_calls": differing,
            "logits_not_recorded": unread, "same_tokens": check.tokens() == trace["tokens"]}


def _equal(result: dict) -> bool:
    """Whether a replayed round decided as recorded: every call, the round's tokens, no unrecorded read."""
    return result["differing_calls"] == 0 and result["same_tokens"] and not result["logits_not_recorded"]


def load_trace(path: str) -> dict:
    """A recorded trace, its model folder made absolute (a trace recorded with a relative path is read
    from the repository's root, where another revision's worktree replays it too)."""
    trace = torch.load(path, weights_only=False)
    model = Path(trace["model"])
    if not model.is_absolute() and (ROOT / model).is_dir():
        trace["model"] = str(ROOT / model)
    return trace


def replay_rounds(trace_path: str, rounds: int, workers: int = 0) -> list[dict]:
    """``rounds`` replays after one untimed (the rule patterns compiled, the vocabulary's index built:
    what a PADA run has from its second round on)."""
    from physcene.train.models import load_tokenizer

    trace = load_trace(trace_path)
    tokenizer = load_tokenizer(trace["model"])
    replay_once(trace, tokenizer, workers)
    return [replay_once(trace, tokenizer, workers) for _ in range(rounds)]


def worktree(rev: str, folder: Path) -> Path:
    """A checkout of ``rev`` (detached) under ``folder``."""
    path = folder / rev
    subprocess.run(["git", "worktree", "add", "--detach", "-f", str(path), rev], cwd=ROOT, check=True,
                   capture_output=True)
    return path


def rounds_at(checkout: Path, trace: str, rounds: int, workers: int = 0) -> list[dict]:
    """``rounds`` replays with the code of ``checkout`` (its physcene first on the path)."""
    # the checkout's code first, then whatever the caller's path holds (wheels installed beside the tree)
    path = [str(checkout), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path))
    code = (f"import json, sys; sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); "
            "import constraint_replay as c; "
            f"print(json.dumps(c.replay_rounds({trace!r}, {rounds}, {workers})))")
    out = subprocess.run([sys.executable, "-c", code], cwd=checkout, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"replay with the code of {checkout} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def replay(args: argparse.Namespace) -> None:
    args.trace = str(Path(args.trace).resolve())
    trace = load_trace(args.trace)
    steps, rows = len(trace["calls"]), len(trace["prompts"])
    versions = {"working tree": (ROOT, 0)}
    versions.update({f"working tree, {k} workers": (ROOT, k) for k in args.workers})
    with tempfile.TemporaryDirectory() as folder:
        try:
            for rev in args.against:
                versions[rev] = (worktree(rev, Path(folder)), 0)
            results: dict[str, list[dict]] = {name: [] for name in versions}
            for _ in range(args.rounds):  # interleaved: one round of each version in turn
                for name, (checkout, workers) in versions.items():
                    results[name] += rounds_at(checkout, args.trace, 1, workers)
        finally:
            for rev in args.against:
                subprocess.run(["git", "worktree", "remove", "--force", str(Path(folder) / rev)], cwd=ROOT,
                               capture_output=True)
    summary = {"trace": args.trace, "rows": rows, "steps": steps, "recorded_on": trace["device"],
               "recorded_host_check_s": trace["host_check_s"], "record_command": trace["command"],
               "rounds": args.rounds, "cpu": _cpu_name(), "versions": {}}
    for name, runs in results.items():
        times = [r["seconds"] for r in runs]
        equal = all(_equal(r) for r in runs)
        summary["versions"][name] = {"median_s": statistics.median(times), "min_s": min(times),
                                     "ms_per_step": 1e3 * statistics.median(times) / steps,
                                     "us_per_row_step": 1e6 * statistics.median(times) / steps / rows,
                                     "equal_to_recording": equal, "rounds": runs}
        print(f"{name:>26}: {1e3 * statistics.median(times) / steps:6.3f} ms per step of {rows} rows "
              f"(median of {len(times)}; min {min(times):.3f} s, median {statistics.median(times):.3f} s "
              f"for {steps} steps); equal to the recording: {equal}")
    # each interleaved round's working-tree time over the other version's: a slow drift of the machine's
    # speed hits both rounds of a pair alike, so their spread says whether a difference is beyond the noise
    ours = [r["seconds"] for r in results["working tree"]]
    for name, version in summary["versions"].items():
        if name == "working tree":
            continue
        paired = [a / b["seconds"] for a, b in zip(ours, version["rounds"])]
        medians = summary["versions"]["working tree"]["median_s"] / version["median_s"]
        version["working_tree_over_this"] = {"median_of_medians": medians, "per_round": paired,
                                             "per_round_median": statistics.median(paired)}
        print(f"working tree / {name}: {medians:.3f} of the time "
              f"(medians); per interleaved round {statistics.median(paired):.3f}, "
              f"{min(paired):.3f}-{max(paired):.3f} over {len(paired)} rounds")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")


def profile(args: argparse.Namespace) -> dict:
    """One replay of the trace with cProfile on during the checks, after an untimed one: the ``--top``
    functions by their own time (calls, own and cumulative seconds, own share of all the checks' profiled
    time), the share inside the regex engines' matching methods, and the replay's equality with the
    recording."""
    import cProfile
    import pstats

    from physcene.train.models import load_tokenizer

    trace = load_trace(args.trace)
    tokenizer = load_tokenizer(trace["model"])
    replay_once(trace, tokenizer)
    profiler = cProfile.Profile()
    result = replay_once(trace, tokenizer, profiler=profiler)
    stats = pstats.Stats(profiler).stats  # (file, line, name) -> (calls, primitive, own, cumulative, callers)
    total = sum(own for _, _, own, _, _ in stats.values())
    functions = sorted(({"function": f"{Path(file).name}:{line}({name})" if line else name, "calls": calls,
                         "own_s": own, "cumulative_s": cumulative, "own_share": own / total}
                        for (file, line, name), (_, calls, own, cumulative, _) in stats.items()),
                       key=lambda f: -f["own_s"])
    methods = [f"'{m}' of '{kind}" for m in ("match", "fullmatch", "search", "findall")
               for kind in ("_regex.Pattern", "re.Pattern")]
    matching = sum(f["own_s"] for f in functions if any(m in f["function"] for m in methods))
    steps, rows = len(trace["calls"]), len(trace["prompts"])
    equal = _equal(result)
    summary = {"trace": str(args.trace), "rows": rows, "steps": steps, "profiled_check_s": result["seconds"],
               "regex_matching_share": matching / total, "equal_to_recording": equal, "cpu": _cpu_name(),
               "record_command": trace["command"], "command": " ".join(sys.argv),
               "functions": functions[:args.top]}
    print(f"{rows} rows x {steps} steps: {result['seconds']:.3f} s in the checks under the profiler; "
          f"{100 * summary['regex_matching_share']:.1f} % of it inside regex matching; "
          f"equal to the recording: {summary['equal_to_recording']}")
    for f in summary["functions"]:
        print(f"{100 * f['own_share']:6.1f} %  {f['own_s']:7.3f} s own  {f['cumulative_s']:7.3f} s cum  "
              f"{f['calls']:>8} calls  {f['function']}")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def streams(args: argparse.Namespace) -> dict:
    """The same round sampled with the check's logits reads on a stream of their own
    (``FastDecoder.reads_stream``, the default) and on the decoding stream, behind the step launched
    before the check: rounds interleaved after a warm-up of each; the median seconds of a round and of
    its host check, and whether the two wrote the same tokens (the same kernels run either way)."""
    from physcene.train.decode import FastDecoder
    from physcene.train.generate import generate_token_ids, input_format

    model_path, model, tokenizer, info, prompts = _round_inputs(args)
    cuda = model.device.type == "cuda"

    def one_round(own_stream: bool) -> tuple[dict, list]:
        FastDecoder.reads_stream = own_stream
        report: list = []
        if cuda:
            torch.cuda.synchronize(model.device)
        start = time.perf_counter()
        ids = generate_token_ids(model, tokenizer, prompts, **input_format(info),
                                 max_new_tokens=args.max_new_tokens, batch_size=len(prompts),
                                 do_sample=args.temperature > 0, temperature=args.temperature or 1.0,
                                 seed=args.seed, cache=args.cache, constrained=True, report=report)
        if cuda:
            torch.cuda.synchronize(model.device)
        result = report[0]
        return {"seconds": time.perf_counter() - start, "host_check_s": result.seconds["host_check"],
                "steps": result.steps, "repairs": result.repairs, "graphs": result.graphs}, ids

    settings = {"own stream": True, "decoding stream": False}
    rounds: dict[str, list[dict]] = {name: [] for name in settings}
    tokens: dict[str, list] = {}
    try:
        for name, own in settings.items():  # warm-up: graphs captured, layers compiled
            tokens[name] = one_round(own)[1]
        for _ in range(args.rounds):
            for name, own in settings.items():
                figures, ids = one_round(own)
                rounds[name].append(figures)
                if ids != tokens[name]:
                    raise SystemExit(f"streams: a seeded round with the reads on the {name} wrote other "
                                     f"tokens than its warm-up")
    finally:
        FastDecoder.reads_stream = True
    median = {name: {k: statistics.median(r[k] for r in rows) for k in ("seconds", "host_check_s")}
              for name, rows in rounds.items()}
    summary = {"device": torch.cuda.get_device_name(model.device) if cuda else _cpu_name(),
               "model": str(model_path), "rows": len(prompts), "max_new_tokens": args.max_new_tokens,
               "temperature": args.temperature, "cache": args.cache, "seed": args.seed,
               "command": " ".join(sys.argv), "rounds": rounds, "median": median,
               "same_tokens": tokens["own stream"] == tokens["decoding stream"]}
    for name, m in median.items():
        print(f"reads on the {name}: {m['seconds']:.2f} s a round (host check {m['host_check_s']:.2f} s), "
              f"median of {args.rounds}")
    print(f"same tokens: {summary['same_tokens']}")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def score(args: argparse.Namespace) -> None:
    from physcene.reward import PhysicsReward, RewardConfig
    from physcene.train.models import load_tokenizer

    reward = PhysicsReward(RewardConfig.load(list(args.set)))
    rows = {}
    for path in args.traces:
        trace = load_trace(path)
        tokenizer = load_tokenizer(trace["model"])
        texts = [tokenizer.decode(row, skip_special_tokens=True) for row in trace["tokens"]]
        metrics = {k: float(v) for k, v in reward.score(texts).metrics.items()}
        rows[path] = {"rollouts": len(texts), "temperature": trace["temperature"], "model": trace["model"],
                      "record_command": trace["command"], **metrics}
        invalid = metrics.get("invalid_rate", float("nan"))
        print(f"{path}: {len(texts)} rollouts at temperature {trace['temperature']}: collision-free "
              f"{metrics['collision_free_rate']:.1%}, invalid {invalid:.1%}, "
              f"parse failures {metrics['parse_failure_rate']:.1%}")
    if args.json:
        Path(args.json).write_text(json.dumps({"reward_overrides": list(args.set), "traces": rows}, indent=1)
                                   + "\n")


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() + f" ({os.cpu_count()} logical CPUs)"
    except OSError:
        pass
    return f"{os.cpu_count()} logical CPUs"


def _round_arguments(parser: argparse.ArgumentParser, cache: str) -> None:
    """The options of a sampled round (``record``, ``streams``): model, prompts, length, sampling."""
    parser.add_argument("--model", required=True, help="a checkpoint folder or an artifact name")
    parser.add_argument("--records", required=True, help="JSONL (.gz ok) with a prompt column (and level)")
    parser.add_argument("--levels", type=int, nargs="*", default=[], help="only prompts of these levels")
    parser.add_argument("--n", type=int, default=128, help="rows (PADA: the global batch of completions)")
    parser.add_argument("--max-new-tokens", type=int, default=2304)
    parser.add_argument("--temperature", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", default=cache, help="a fast decoder setting (train.decode.FAST_CACHES)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="sample one round under the constraint and keep its checks")
    _round_arguments(rec, cache="fast")
    rec.add_argument("--out", required=True)
    stm = sub.add_parser("streams", help="sample a round with the check's logits reads on a stream of their "
                                         "own and on the decoding stream (a GPU's A/B)")
    _round_arguments(stm, cache="fast+fused+cudnn")
    stm.add_argument("--rounds", type=int, default=3)
    stm.add_argument("--json", help="write the figures here")
    rep = sub.add_parser("replay", help="time the recorded checks, with this tree and --against revisions")
    rep.add_argument("trace")
    rep.add_argument("--against", nargs="*", default=[],
                     help="git revisions replayed beside the working tree")
    rep.add_argument("--workers", type=int, nargs="*", default=[],
                     help="also replay the working tree with the check spread over this many worker "
                          "processes (physcene.train.decode.shards), e.g. --workers 2 4")
    rep.add_argument("--rounds", type=int, default=5)
    rep.add_argument("--json", help="write the figures here")
    pro = sub.add_parser("profile", help="where the recorded checks' time goes, by function (cProfile)")
    pro.add_argument("trace")
    pro.add_argument("--top", type=int, default=20, help="functions listed, by their own time")
    pro.add_argument("--json", help="write the figures here")
    sco = sub.add_parser("score", help="the physics reward's figures of the rollouts recorded in traces")
    sco.add_argument("traces", nargs="+")
    sco.add_argument("--set", nargs="*", default=["valid_terms=[floating,shrunk,out_of_zone]"],
                     help="configs/reward.yaml overrides (default: the RL study's validity terms)")
    sco.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    verbs = {"record": record, "replay": replay, "profile": profile, "streams": streams, "score": score}
    verbs[args.command](args)


if __name__ == "__main__":
    main()
