"""The non-finite gradient probe (``pada.nonfinite_probe``; not in the paper, off by default).

A micro-batch whose backward leaves a NaN or inf gradient is taken apart once per step, up to
``nonfinite_probe`` times a run: which loss term, which rows, which attention kernel
(:meth:`NonfiniteProbe.probe`). The report goes to the log and ``<output_dir>/nonfinite_probe.jsonl``,
the micro-batch's tensors to ``<output_dir>/nonfinite_step<N>.pt``;
:class:`~physcene.train.sft.SkipNonFiniteSteps` still drops the step.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch
from trl import GRPOTrainer

from physcene.train.extension import PADAExtension
from physcene.train.sft import nonfinite_gradients
from physcene.train.targets import ANCHOR_ROW_KEYS

__all__ = ["NonfiniteProbe"]

logger = logging.getLogger(__name__)


class NonfiniteProbe(PADAExtension):
    """Probes up to ``probes`` micro-batches whose backward left a non-finite gradient (module docstring)."""

    def __init__(self, probes: int):
        self.probes_left = int(probes)
        self._probed_step = -1
        self._micro_batch_inputs = None

    def extra_loss(self, trainer, model, inputs: dict):
        # adds nothing: keeps the micro-batch TRL's loss sees, for a probe after its backward
        if self.probes_left > 0:
            self._micro_batch_inputs = inputs
        return None

    def after_backward(self, trainer, model) -> None:
        if self.probes_left > 0 and self._probed_step != trainer.state.global_step:
            if nonfinite_gradients(model)[0]:
                self.probes_left -= 1
                self._probed_step = trainer.state.global_step  # later micro-batches carry the same NaN
                self.probe(trainer, model, self._micro_batch_inputs)

    def probe(self, trainer, model, inputs) -> dict:
        """Take apart a micro-batch whose backward left a non-finite gradient (``pada.nonfinite_probe``).

        Runs each loss term's backward alone (the GRPO loss; the anchor CE under the model's own
        attention and under eager attention) and the anchor CE of each row alone, and notes which
        leave every gradient finite, with each row's prompt padding and anchor length. The report
        goes to the log and ``<output_dir>/nonfinite_probe.jsonl``, the micro-batch's tensors to
        ``<output_dir>/nonfinite_step<N>.pt`` for a replay. The gradients are put back as they were,
        so :class:`~physcene.train.sft.SkipNonFiniteSteps` still drops the step. (The probe's GRPO
        forward logs its metrics, KL and entropy, a second time for that step.)
        """
        params = [q for q in model.parameters() if q.requires_grad]
        saved = [q.grad for q in params]

        def finite_backward(term) -> tuple[float, bool]:
            for q in params:
                q.grad = None
            with trainer.compute_loss_context_manager():
                value = term()
            with trainer.accelerator.no_sync(model):  # this rank's own diagnosis: no gradient all-reduce
                value.backward()
            return float(value.detach()), not nonfinite_gradients(model)[0]

        step = trainer.state.global_step + 1

        def anchor_ce(batch=inputs):
            return trainer.anchor_cross_entropy(model, batch)

        grpo_loss = finite_backward(lambda: GRPOTrainer._compute_loss(trainer, model, inputs))
        report: dict = {"step": step, "grpo_loss": grpo_loss}
        if "anchor_ids" in inputs and inputs["anchor_loss_mask"].sum() > 0:
            report["anchor_ce"] = finite_backward(anchor_ce)
            base = trainer.accelerator.unwrap_model(model)
            attention = base.config._attn_implementation
            if attention != "eager":
                base.set_attn_implementation("eager")
                try:
                    report["anchor_ce_eager"] = finite_backward(anchor_ce)
                finally:
                    base.set_attn_implementation(attention)
            rows = []
            for b in range(inputs["anchor_ids"].size(0)):
                if inputs["anchor_loss_mask"][b].sum() == 0:
                    continue
                one = {k: inputs[k][b:b + 1] for k in ANCHOR_ROW_KEYS}
                value, finite = finite_backward(lambda one=one: anchor_ce(one))
                rows.append({"row": b, "ce": value, "finite": finite,
                             "prompt_tokens": int(one["prompt_mask"].sum()),
                             "prompt_width": one["prompt_ids"].size(1),
                             "anchor_tokens": int(one["anchor_attention_mask"].sum()),
                             "anchor_width": one["anchor_ids"].size(1)})
            report["anchor_rows"] = rows
        for q, g in zip(params, saved):
            q.grad = g
        broken = [r["row"] for r in report.get("anchor_rows", ()) if not r["finite"]]
        logger.warning("step %d: non-finite gradient probe (value, finite backward): %s", step,
                       {k: v for k, v in report.items() if k != "anchor_rows"}
                       | {"rows_with_nonfinite_ce": broken})
        if trainer.is_world_process_zero():
            out = Path(trainer.args.output_dir)
            out.mkdir(parents=True, exist_ok=True)
            with open(out / "nonfinite_probe.jsonl", "a") as f:
                f.write(json.dumps(report) + "\n")
            torch.save({k: v.detach().cpu() for k, v in inputs.items() if isinstance(v, torch.Tensor)},
                       out / f"nonfinite_step{step}.pt")
        return report
