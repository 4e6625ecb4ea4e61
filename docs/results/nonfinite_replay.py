"""Replay a micro-batch saved by ``pada.nonfinite_probe`` (``nonfinite_step<N>.pt``) on the GPU: the
anchor CE's backward under each attention kernel and input layout, to find what makes it NaN.

    python docs/results/nonfinite_replay.py runs/small/sft runs/small/pada_star/nonfinite_step1.pt

The probe's micro-batch came from round 1 of PADA*, where the LoRA update is still zero, so the SFT
model alone reproduces its forward; every weight gets a gradient here (no adapter needed).
"""

from __future__ import annotations

import sys

import torch
from physcene.train.models import load_model
from torch.nn.attention import SDPBackend, sdpa_kernel


def anchor_ce(model, ids, attention, targets, loss_mask, keep):
    logits = model(input_ids=ids, attention_mask=attention, logits_to_keep=keep + 1).logits[:, :-1][:, -keep:]
    logps = torch.log_softmax(logits.float(), -1).gather(-1, targets.unsqueeze(-1)).squeeze(-1)
    m = loss_mask.float()
    return -(logps * m).sum() / m.sum().clamp(min=1)


def right_packed(d, rows):
    """[prompt tokens | anchor tokens | right padding]: no left padding, so no query row is fully masked."""
    seqs, spans = [], []
    for b in rows:
        p = d["prompt_ids"][b][d["prompt_mask"][b].bool()]
        a = d["anchor_ids"][b][d["anchor_attention_mask"][b].bool()]
        seqs.append(torch.cat([p, a]))
        spans.append((len(p), len(a)))
    width = max(len(s) for s in seqs)
    ids = torch.zeros(len(rows), width, dtype=torch.long)
    att = torch.zeros(len(rows), width, dtype=torch.long)
    for k, s in enumerate(seqs):
        ids[k, :len(s)] = s
        att[k, :len(s)] = 1
    return ids, att, spans


def main(model_dir: str, path: str) -> None:
    d = torch.load(path)
    model = load_model(model_dir, dtype="bfloat16", freeze_vision=True).cuda().train()
    for p in model.parameters():
        p.requires_grad_(True)
    rows = list(range(d["anchor_ids"].size(0)))
    W = d["anchor_ids"].size(1)
    cuda = {k: v.cuda() for k, v in d.items()}

    def check(name, fn, attention="sdpa", backend=None):
        model.set_attn_implementation(attention)
        model.zero_grad(set_to_none=True)
        try:
            with torch.autocast("cuda", dtype=torch.bfloat16):
                if backend is None:
                    loss = fn()
                else:
                    with sdpa_kernel([backend]):
                        loss = fn()
            loss.backward()
            finite = all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in model.parameters())
            print(f"{name:55s} loss={float(loss):.5f} finite_grad={finite}", flush=True)
        except Exception as e:  # a backend that refuses the inputs
            print(f"{name:55s} error: {str(e).splitlines()[0][:120]}", flush=True)

    left = lambda: anchor_ce(model, torch.cat([cuda["prompt_ids"], cuda["anchor_ids"]], 1),  # noqa: E731
                             torch.cat([cuda["prompt_mask"], cuda["anchor_attention_mask"]], 1),
                             cuda["anchor_ids"], cuda["anchor_loss_mask"], W)
    check("CE, left-padded prompt (as PADA), sdpa default", left)
    check("CE, left-padded prompt, eager", left, attention="eager")
    for backend in (SDPBackend.MATH, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.CUDNN_ATTENTION,
                    SDPBackend.FLASH_ATTENTION):
        check(f"CE, left-padded prompt, sdpa {backend.name}", left, backend=backend)
    # the same rows as GRPO sees them: prompt + completion
    C = d["completion_ids"].size(1)
    grpo = lambda: anchor_ce(model, torch.cat([cuda["prompt_ids"], cuda["completion_ids"]], 1),  # noqa: E731
                             torch.cat([cuda["prompt_mask"], cuda["completion_mask"]], 1),
                             cuda["completion_ids"], cuda["completion_mask"], C)
    check(f"NLL of the completions (GRPO's layout, width {C}), sdpa", grpo)
    # anchors right-packed after the unpadded prompt
    ids, att, spans = right_packed(d, rows)
    ids, att = ids.cuda(), att.cuda()

    def packed():
        logits = model(input_ids=ids, attention_mask=att).logits
        total, count = 0.0, 0.0
        for k, (p, a) in enumerate(spans):
            lp = torch.log_softmax(logits[k, p - 1:p + a - 1].float(), -1)
            tgt = ids[k, p:p + a]
            m = cuda["anchor_loss_mask"][k][cuda["anchor_attention_mask"][k].bool()].float()
            total = total - (lp.gather(-1, tgt.unsqueeze(-1)).squeeze(-1) * m).sum()
            count += float(m.sum())
        return total / max(count, 1.0)

    check("CE, right-packed [prompt|anchor|pad], sdpa default", packed)
    # fewer anchor pad columns: the micro-batch's own longest anchor instead of the round's
    w = int(d["anchor_attention_mask"].sum(1).max())
    trim = lambda: anchor_ce(model, torch.cat([cuda["prompt_ids"], cuda["anchor_ids"][:, :w]], 1),  # noqa: E731
                             torch.cat([cuda["prompt_mask"], cuda["anchor_attention_mask"][:, :w]], 1),
                             cuda["anchor_ids"][:, :w], cuda["anchor_loss_mask"][:, :w], w)
    check(f"CE, left-padded, anchors cut to the batch's longest ({w} of {W})", trim)
    print("prompt width", d["prompt_ids"].size(1), "real", d["prompt_mask"].sum(1).tolist(),
          "anchor width", W, "real", d["anchor_attention_mask"].sum(1).tolist(), "completion width", C)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
