"""One model from several checkpoints of an RL run: the mean of their merged weights.

A LoRA checkpoint ``k`` changes each adapted projection of the base by ``ΔW_k = scaling · B_k A_k``.
The mean model has ``W + (1/n) Σ ΔW_k`` there (and the base's weights elsewhere, which LoRA does not
train): the mean of the merged models, not of the ``A`` and ``B`` factors, whose product would be
another matrix. The result is a full checkpoint (config, weights in float32, tokenizer and the run info
of the checkpoints' base, so generation reads its prompts as the base's), which ``physcene eval
--generator model:OUT`` and ``physcene generate --generator model:OUT`` load like any other:

    python -m physcene.train.analysis.adapter_average artifacts/small-sft-physics \\
        artifacts/rl-phys-credit-s0-pada-585/checkpoint-{200,300,400,500} --out runs/average/s0
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch

__all__ = ["average_checkpoints"]

_INPUT_FORMAT = ("chat_format", "physics_conditioned", "config", "eval_batch_size")


def average_checkpoints(base: str | Path, checkpoints: list[str | Path], out: str | Path) -> Path:
    """Write the mean of the merged ``checkpoints`` (LoRA adapters of ``base``, each checked against the
    base digest its run recorded) to ``out``; returns ``out``."""
    from physcene.train.generate import load_for_generation
    from physcene.train.models import read_run_info, write_run_info

    if not checkpoints:
        raise ValueError("adapter_average: no checkpoints to average")
    missing = [str(c) for c in checkpoints if not (Path(c) / "adapter_config.json").is_file()]
    if missing:
        raise ValueError(f"adapter_average: not LoRA checkpoints (no adapter_config.json): {missing}")
    total: dict[str, torch.Tensor] = {}
    model = tokenizer = None
    for ckpt in checkpoints:
        model, tokenizer, _ = load_for_generation(ckpt, device="cpu", dtype="float32", base=base)
        for name, value in model.state_dict().items():
            if value.is_floating_point():
                total[name] = total[name] + value if name in total else value.clone()
    state = model.state_dict()
    for name, value in total.items():
        state[name].copy_(value / len(checkpoints))
    out = Path(out)
    model.save_pretrained(out)
    tokenizer.save_pretrained(out)
    # how the checkpoints read their prompts (their base's input format), not the base's training record
    info = {k: v for k, v in read_run_info(base).items() if k in _INPUT_FORMAT}
    write_run_info(out, **info, stage="adapter_average", base_model=str(base),
                   averaged=[str(c) for c in checkpoints])
    return out


def main(argv=None) -> int:
    prog = "python -m physcene.train.analysis.adapter_average"
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("base", help="the base model folder the adapters were trained on")
    parser.add_argument("checkpoints", nargs="+", help="LoRA checkpoint folders of that base")
    parser.add_argument("--out", required=True, help="the averaged model's folder")
    args = parser.parse_args(argv)
    try:
        out = average_checkpoints(args.base, args.checkpoints, args.out)
    except ValueError as exc:
        parser.error(str(exc))
    print(f"{out}: the mean of {len(args.checkpoints)} merged checkpoints "
          f"(python -m physcene.train.analysis.adapter_average {shlex.join(argv or sys.argv[1:])})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
