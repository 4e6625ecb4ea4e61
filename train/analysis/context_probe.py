"""Does a layout model use the numbers in its context? Two teacher-forced probes on reference completions.

    python -m physcene.train.analysis.context_probe runs/small/sft data/train.jsonl --n 24 --out probe.json

``zone``: the completion's root ``bbox`` copies the prompt's ``item_placement_zone`` in the data; the
probe reports the median probability the model gives the digits of the zone's width and depth (a
model that copies: ~1; one that guesses each digit: ~0.1), and the relative change of the rest of the
completion's NLL when the zone is made 25-30 % larger in both prompt and completion (a model that
sizes its layout to the table: large).
``neighbour``: the first table-level object's box is moved onto the second one's; the NLL of what
follows it should rise for a model that places objects around what it already placed (a collision is
then written), and stays put for one that draws each position from a marginal. Records: any CTRC
JSONL with ``prompt`` and ``completion`` (``physcene data synth``; ``.gz`` read as gzip).
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
from pathlib import Path

import torch

from physcene.train.generate import load_for_generation
from physcene.train.records import load_records

_ZONE_PROMPT = re.compile(r"\*\*item_placement_zone\*\*: \[[^\]]*\]")
_ZONE_ROOT = re.compile(r'"type": "zone", "bbox": \[([^\]]*)\]')
_NEAR_BOX = re.compile(r'"relation_type": "near", [^\n]*?"relative_bbox": \[([^\]]*)\]')


class _Scorer:
    def __init__(self, model_path: str | None, device: str = "cpu", *, model=None, tokenizer=None):
        """A checkpoint directory, or (``model_path`` None) a ``model`` and ``tokenizer`` in memory."""
        self.device = device
        if model_path is None:
            self.model, self.tokenizer = model, tokenizer
        else:
            self.model, self.tokenizer, _ = load_for_generation(model_path, device=device, dtype="float32")

    def token_nll(self, prompt: str, completion: str) -> tuple[torch.Tensor, int]:
        """Per-token NLL of the completion's tokens (after the prompt's) and the prompt's length."""
        p = self.tokenizer(prompt, add_special_tokens=False)["input_ids"]
        c = self.tokenizer(completion, add_special_tokens=False)["input_ids"]
        ids = torch.tensor([p + c], device=self.device)
        with torch.no_grad():
            lp = torch.log_softmax(self.model(ids).logits[0, :-1].float(), -1).cpu()
        target = ids[0, 1:].cpu()
        return -lp[torch.arange(len(target)), target], len(p)

    def tokens_before(self, text: str) -> int:
        return len(self.tokenizer(text, add_special_tokens=False)["input_ids"])

    def nll_after(self, prompt: str, completion: str, char: int) -> float:
        """NLL of the completion from character ``char`` on (token-aligned by re-tokenizing the prefix)."""
        nll, n_prompt = self.token_nll(prompt, completion)
        return nll[n_prompt + self.tokens_before(completion[:char]) - 1:].sum().item()


def zone_probe(scorer: _Scorer, record: dict) -> dict | None:
    prompt, completion = record["prompt"], record["completion"]
    root, given = _ZONE_ROOT.search(completion), _ZONE_PROMPT.search(prompt)
    if root is None or given is None:
        return None
    nll, n_prompt = scorer.token_nll(prompt, completion)
    ids = scorer.tokenizer(completion, add_special_tokens=False)["input_ids"]
    digit_p = []
    for number in list(re.finditer(r"[\d.]+", root.group(1)))[1:4:2]:  # xmax, ymax: the zone's size
        start, end = root.start(1) + number.start(), root.start(1) + number.end()
        for k in range(scorer.tokens_before(completion[:start]), scorer.tokens_before(completion[:end])):
            if scorer.tokenizer.decode([ids[k]]).isdigit():
                digit_p.append(float(torch.exp(-nll[n_prompt + k - 1])))
    zone = [float(v) for v in root.group(1).split(",")]
    bigger = [0.0, round(zone[1] * 1.25, 1), 0.0, round(zone[3] * 1.3, 1)]
    big_root = root.group(0).replace(root.group(1), ", ".join(str(v) for v in [*bigger, 0.0, 0.0]))
    big_prompt = prompt.replace(given.group(0), "**item_placement_zone**: " + json.dumps(bigger))
    after = completion.index("\n", root.end())
    big_completion = completion.replace(root.group(0), big_root)
    big_after = big_completion.index("\n", root.start())
    rest = nll[n_prompt + scorer.tokens_before(completion[:after]) - 1:].sum().item()  # = nll_after
    return {"digit_probabilities": digit_p, "nll": rest,
            "nll_bigger_zone": scorer.nll_after(big_prompt, big_completion, big_after)}


def moved_onto_next(completion: str) -> tuple[str, int, int] | None:
    """(the completion with its first table-level box moved onto the second one's centre, where the
    moved box's line ends in the original, where it ends in the edit), or None when there are fewer than
    two table-level objects or the move would leave the zone's corner quadrant."""
    boxes = list(_NEAR_BOX.finditer(completion))
    if len(boxes) < 2:
        return None
    a, b = boxes[0], boxes[1]
    va = [float(x) for x in a.group(1).split(",")]
    vb = [float(x) for x in b.group(1).split(",")]
    cx, cy, w, d = (vb[0] + vb[1]) / 2, (vb[2] + vb[3]) / 2, va[1] - va[0], va[3] - va[2]
    numbers = (*a.group(1).split(","), *b.group(1).split(","))  # the moved box keeps the text's precision
    places = max(len(x.split(".")[1]) if "." in x else 0 for x in numbers)
    moved = [round(v, places) for v in (cx - w / 2, cx + w / 2, cy - d / 2, cy + d / 2)] + va[4:]
    if min(moved[0], moved[2]) < 0:
        return None
    edited = completion[:a.start(1)] + ", ".join(str(x) for x in moved) + completion[a.end(1):]
    return edited, completion.index("\n", a.end()), edited.index("\n", a.start(1))


def neighbour_probe(scorer: _Scorer, record: dict) -> dict | None:
    edit = moved_onto_next(record["completion"])
    if edit is None:
        return None
    edited, after, edited_after = edit
    return {"nll": scorer.nll_after(record["prompt"], record["completion"], after),
            "nll_moved_onto_next": scorer.nll_after(record["prompt"], edited, edited_after)}


def probe(scorer: _Scorer, rows: list[dict]) -> dict:
    """Both probes over ``rows``: ``{"zone": {...}, "neighbour": {...}}`` (relative NLL changes)."""
    zone = [z for r in rows if (z := zone_probe(scorer, r))]
    near = [m for r in rows if (m := neighbour_probe(scorer, r))]

    def rel(items, a, b):
        return statistics.mean((x[b] - x[a]) / x[a] for x in items)

    digits = [p for z in zone for p in z["digit_probabilities"]]
    return {
        # a vocabulary of whole numbers (docs/training.md, "Fewer tokens per object") has no digit tokens
        "zone": {"n": len(zone), "digit_probability_median": statistics.median(digits) if digits else None,
                 "nll_change_bigger_zone": rel(zone, "nll", "nll_bigger_zone")},
        "neighbour": {"n": len(near), "nll_change_moved_onto_next": rel(near, "nll", "nll_moved_onto_next"),
                      "raised": sum(m["nll_moved_onto_next"] > m["nll"] for m in near)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="checkpoint directory (physcene train sft/pada output)")
    parser.add_argument("records", help="CTRC JSONL (.gz ok) with prompt and completion")
    parser.add_argument("--n", type=int, default=24, help="records probed (the first N)")
    parser.add_argument("--out", help="write the result as JSON here")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    args = parser.parse_args()
    torch.set_num_threads(max(1, min(4, torch.get_num_threads())))
    scorer = _Scorer(args.model, args.device)
    rows = load_records(args.records)[:args.n]
    result = {"model": args.model, "records": args.records, **probe(scorer, rows)}
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
