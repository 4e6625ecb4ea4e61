"""Training harness (installed as ``physcene.train``): SFT, anchor generation, PADA/GRPO on HF TRL.

One stage per module (import them directly; this package imports nothing, so that loading one
stage does not load TRL for another):

- :mod:`~physcene.train.sft` stage 1, supervised fine-tuning; :mod:`~physcene.train.models`,
  :mod:`~physcene.train.tokenizer`, :mod:`~physcene.train.records` its model, tokenizer and data;
  :mod:`~physcene.train.checkpoints` the complete checkpoint a run resumes from;
- :mod:`~physcene.train.anchors` the physically-projected semantic anchors (SFT output + TTO);
- :mod:`~physcene.train.pada` stage 2, the paper's objective GRPO + α · CE(anchor) (PADA, PADA*,
  GRPO), configured by :mod:`~physcene.train.config`, its targets tokenised by
  :mod:`~physcene.train.targets`;
- the extensions not in the paper, each off by default, behind the one hook of
  :mod:`~physcene.train.extension`: :mod:`~physcene.train.constrained_rollouts`,
  :mod:`~physcene.train.object_credit`, :mod:`~physcene.train.denoise`,
  :mod:`~physcene.train.diagnostics`; β adapted by :mod:`~physcene.train.kl`;
- :mod:`~physcene.train.generate` generation from a checkpoint; :mod:`~physcene.train.constrained`
  the CTRC decoding constraint; :mod:`~physcene.train.ablation` the paper's ablation end to end,
  :mod:`~physcene.train.ablation_plot` its learning curves.
"""

__all__: list[str] = []
