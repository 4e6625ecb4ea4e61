"""Training harness (installed as ``physcene.train``): SFT, anchor generation, PADA/GRPO on HF TRL."""
