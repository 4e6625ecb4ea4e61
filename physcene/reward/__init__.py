"""The paper's physics reward (PADA's GRPO signal) and what it reads: texts, size priors, TRL.

``physics_reward`` scores completions into a :class:`RewardBatch`; ``text_batch`` reads completion
texts into the engine's batch with the compiled CTRC reader; ``size_prior`` gives each object's
category size band; ``trl`` adapts the reward to TRL's trainers.
"""

from physcene.reward.physics_reward import (
    OBJECT_TERMS,
    PENETRATION_CHARGES,
    VALID_TERMS,
    ChargeConfig,
    PhysicsReward,
    RewardBatch,
    RewardConfig,
    completion_text_of,
    object_terms_checked,
    penetration_charge_checked,
    reward_from_energy,
    valid_terms_checked,
)
from physcene.reward.size_prior import band_low_ratio, prior_bands, size_outside_band_cm
from physcene.reward.text_batch import TextPack, TextPacker
from physcene.reward.trl import PhysicsRewardFunction, physics_reward, reward_for_device

__all__ = ["OBJECT_TERMS", "PENETRATION_CHARGES", "VALID_TERMS", "ChargeConfig", "PhysicsReward",
           "PhysicsRewardFunction", "RewardBatch", "RewardConfig", "TextPack", "TextPacker", "band_low_ratio",
           "completion_text_of", "object_terms_checked", "penetration_charge_checked", "physics_reward",
           "prior_bands", "reward_for_device", "reward_from_energy", "size_outside_band_cm",
           "valid_terms_checked"]
