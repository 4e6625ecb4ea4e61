"""Adaptive KL coefficient for PADA (``pada.adaptive_kl``; not in the paper, which fixes β = 0.04).

:class:`AdaptiveKLCallback` starts from the configured β and moves it toward a target KL after each
logged step (Ziegler et al. 2019); ``pada.adaptive_kl: null`` keeps β fixed. Logged: ``beta``.
"""

from __future__ import annotations

from transformers import TrainerCallback
from trl import GRPOTrainer

__all__ = ["AdaptiveKLCallback"]


class AdaptiveKLCallback(TrainerCallback):
    """Adaptive KL coefficient (Ziegler et al. 2019): β ← β · (1 + clip(KL/target − 1, ±0.2) · n/horizon).

    Reads the ``kl`` that GRPOTrainer logs (mean per-token KL to the reference), ``n`` = optimizer
    steps since the last update; β stays in ``[min_beta, max_beta]`` (it must stay > 0: TRL only
    computes reference log-probs when β ≠ 0). The new β goes into the log entry that carried the KL
    (``beta`` in ``train_log.json`` and the checkpoints' ``trainer_state.json``), and a run resumed
    from a checkpoint goes on from the last β logged there instead of the configured one.
    """

    def __init__(self, trainer: GRPOTrainer, target: float = 0.05, horizon: int = 100,
                 min_beta: float = 1e-3, max_beta: float = 1.0):
        if trainer.beta <= 0:
            raise ValueError(f"adaptive KL needs an initial beta > 0, got {trainer.beta}")
        if target <= 0 or horizon <= 0:
            raise ValueError(f"adaptive KL needs target > 0 and horizon > 0, got {target}, {horizon}")
        self.trainer, self.target, self.horizon = trainer, target, horizon
        self.min_beta, self.max_beta = min_beta, max_beta
        self._last_step = 0

    def update(self, kl: float, global_step: int) -> float:
        """Apply one update for the measured ``kl`` at ``global_step``; returns the new β."""
        error = min(max(kl / self.target - 1.0, -0.2), 0.2)
        steps = max(global_step - self._last_step, 1)
        self._last_step = global_step
        beta = self.trainer.beta * (1.0 + error * steps / self.horizon)
        self.trainer.beta = min(max(beta, self.min_beta), self.max_beta)
        return self.trainer.beta

    def on_train_begin(self, args, state, control, **kwargs):
        logged = [entry for entry in state.log_history if "beta" in entry]
        if state.global_step > 0 and logged:  # resumed: the history is the checkpoint's
            self.trainer.beta = float(logged[-1]["beta"])
            self._last_step = int(logged[-1].get("step", state.global_step))

    def on_log(self, args, state, control, logs=None, **kwargs):
        if logs and "kl" in logs and state.global_step > self._last_step:
            self.update(float(logs["kl"]), state.global_step)
            # GRPOTrainer empties its metric buffers once a log is written, so β goes straight into
            # the entry the Trainer has just appended for these logs
            if state.log_history and state.log_history[-1].get("step") == state.global_step:
                state.log_history[-1]["beta"] = self.trainer.beta
