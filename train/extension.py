"""The one hook through which everything PADA does beyond the paper's objective reaches the trainer.

:class:`~physcene.train.pada.PADATrainer` computes GRPO + α · CE(anchor) and calls each of its
extensions at five points of a step; an extension overrides the points it needs (the base class does
nothing at each). The extensions, each in its own module, off by default and configured by
:class:`~physcene.train.config.PADAConfig`'s extension fields:

- :class:`~physcene.train.constrained_rollouts.ConstrainedRollouts`: sample under the CTRC constraint
  (a logits processor) and leave the tokens it chose out of the loss;
- :class:`~physcene.train.object_credit.ObjectCredit`: per-token advantages from per-object charges;
- :class:`~physcene.train.denoise.Denoise`: a CE toward each rollout's on-policy repair;
- :class:`~physcene.train.diagnostics.NonfiniteProbe`: take apart a micro-batch whose gradient broke.

Extensions log through ``trainer.log_value(name, value)``: the trainer's own metric buffers, written
with TRL's metrics at each logging step.
"""

from __future__ import annotations

__all__ = ["PADAExtension"]


class PADAExtension:
    """Points of a PADA step an extension may act at; each is a no-op here."""

    def logits_processors(self, trainer, prompts: list) -> list:
        """Logits processors for this generation call (``prompts``: the round's prompts in row order)."""
        return []

    def after_generation(self, trainer) -> None:
        """After a generation call that used this extension's logits processors."""

    def after_scoring(self, trainer, inputs: list[dict], output: dict) -> None:
        """After TRL generated and scored a round: ``output`` (TRL's batch dict) may be changed in place,
        before the anchor targets are added. ``inputs``: the round's dataset rows."""

    def extra_loss(self, trainer, model, inputs: dict):
        """A term added to the GRPO loss of a micro-batch (before the anchor CE), or None."""
        return None

    def after_backward(self, trainer, model) -> None:
        """After a micro-batch's backward (``training_step``)."""
