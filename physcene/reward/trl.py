"""The physics reward for TRL's trainers: the adapter PADA trains with and a default-config function.

:class:`PhysicsRewardFunction` scores this rank's completions with a :class:`PhysicsReward` on this
rank's device and logs the batch's figures through the trainer's ``log_metric``;
:func:`physics_reward` is the reward with ``configs/reward.yaml`` defaults, one engine per device.
Both take TRL's signature ``f(prompts, completions, **columns) -> list[float]``.
"""

from __future__ import annotations

import functools
import time
from dataclasses import replace

import torch

from physcene.reward.physics_reward import ChargeConfig, PhysicsReward, RewardConfig, completion_text_of

__all__ = ["PhysicsRewardFunction", "physics_reward", "reward_for_device"]


class PhysicsRewardFunction:
    """TRL reward function: :class:`PhysicsReward` with its engine on this rank's device.

    Each rank scores only its own completions (TRL gathers the rewards afterwards), so on N GPUs the
    engine runs N-way parallel. After each batch it logs, through the trainer's ``log_metric``:
    ``time/reward_s`` (this rank's seconds), ``parse_rate``, and over the parsed layouts
    ``penetration_mm`` (mean E_pen, mm), ``max_depth_mm`` and ``collision_free_rate``; with the
    reward's size guard ``size_outside_cm``, with its ``valid_terms`` ``invalid_rate`` and
    ``floating_objects`` / ``shrunk_objects`` (mean per layout).
    """

    __name__ = "physics"

    def __init__(self, device: str | torch.device = "cpu", reward: PhysicsReward | None = None, overrides=()):
        if reward is None:
            reward = PhysicsReward(replace(RewardConfig.load(list(overrides)), device=str(device)))
        self.reward = reward

    def __call__(self, prompts, completions, log_metric=None, *, charges: ChargeConfig | None = None,
                 on_batch=None, **columns) -> list[float]:
        """TRL's signature; ``charges`` and ``on_batch`` as :meth:`PhysicsReward.__call__`."""
        start = time.perf_counter()
        batch = self.reward.score([completion_text_of(c) for c in completions], charges=charges)
        seconds = time.perf_counter() - start
        m = batch.metrics
        if log_metric is not None:
            log_metric("time/reward_s", seconds)
            log_metric("parse_rate", 1.0 - m["parse_failure_rate"])
            if m["parse_failure_rate"] < 1.0:  # energy figures exist only for parsed layouts
                log_metric("penetration_mm", m["mean_energy_mm"])
                log_metric("max_depth_mm", m["mean_max_depth_mm"])
                log_metric("collision_free_rate", m["collision_free_rate"])
                if "mean_size_outside_cm" in m:
                    log_metric("size_outside_cm", m["mean_size_outside_cm"])
                if "invalid_rate" in m:  # reward.valid_terms: the share paid `invalid`, objects per term
                    log_metric("invalid_rate", m["invalid_rate"])
                    for term in self.reward.config.valid_terms:
                        log_metric(f"{term}_objects", m[f"mean_{term}_objects"])
        if on_batch is not None:
            on_batch(batch)
        return batch.rewards.tolist()


_BY_DEVICE: dict[str, PhysicsReward] = {}


@functools.lru_cache(maxsize=1)
def _default_config() -> RewardConfig:
    return RewardConfig.load()


def reward_for_device(device=None) -> PhysicsReward:
    """The :class:`PhysicsReward` with ``configs/reward.yaml`` defaults on ``device`` (default: the
    config's), one per device and process."""
    config = _default_config()
    key = str(device) if device is not None else config.device
    reward = _BY_DEVICE.get(key)
    if reward is None:
        reward = _BY_DEVICE[key] = PhysicsReward(replace(config, device=key))
    return reward


def physics_reward(prompts=None, completions=None, *, device=None, **columns) -> list[float]:
    """The reward with ``configs/reward.yaml`` defaults (:func:`reward_for_device`); ``device`` (e.g.
    this rank's ``cuda:N``) overrides the config's. For the metrics, call
    ``reward_for_device(device).score(texts)``."""
    return reward_for_device(device)(prompts, completions, **columns)
