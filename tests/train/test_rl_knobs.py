"""The RL knobs: reward scaling over the batch, the group size, the validity terms per variant
(out_of_zone among them) and the prompt pool over every level a rollout length allows."""

from __future__ import annotations

import math

import pytest

from physcene.commands.train import training_config
from physcene.ctrc import completion_text
from physcene.reward import PhysicsReward, RewardConfig
from physcene.scene import TABLE
from physcene.train.config import PADAConfig, pada_arguments, reward_overrides
from physcene.train.records import prompt_pool


def arguments(tmp_path, *overrides: str, variant: str = "pada") -> PADAConfig:
    return pada_arguments(training_config("tiny", [f"output_dir={tmp_path}", *overrides]), variant)


def test_scale_rewards_is_a_config_knob_checked_by_name(tmp_path):
    assert arguments(tmp_path).scale_rewards == "group"  # the paper's GRPO, TRL's default
    for value in ("batch", "none"):
        assert arguments(tmp_path, f"pada.scale_rewards={value}", variant="grpo").scale_rewards == value
    assert PADAConfig(output_dir=str(tmp_path), scale_rewards=False, num_generations=2, use_cpu=True,
                      per_device_train_batch_size=2).scale_rewards == "none"  # TRL's boolean spelling
    with pytest.raises(ValueError, match=r"pada.scale_rewards must be one of "
                                         r"\['group', 'batch', 'none'\], got 'prompt'"):
        arguments(tmp_path, "pada.scale_rewards=prompt")


def test_the_group_size_goes_to_16_and_must_divide_a_generation_round(tmp_path):
    big = ["pada.num_generations=16", "pada.global_batch_size=32", "pada.per_device_batch_size=16"]
    assert arguments(tmp_path, *big).num_generations == 16
    with pytest.raises(ValueError, match=r"pada.num_generations=16 must divide the completions of a "
                                         r"generation round \(pada.global_batch_size x "
                                         r"pada.generation_batches"):
        arguments(tmp_path, "pada.num_generations=16")
    with pytest.raises(ValueError, match=r"pada.num_generations \(the group size G\) must be an integer "
                                         r">= 2, got 1"):
        PADAConfig(output_dir=str(tmp_path), num_generations=1, use_cpu=True)


def test_validity_terms_per_variant(tmp_path):
    terms = "valid_terms=[floating,shrunk,out_of_zone]"
    cfg = training_config("tiny", [f"output_dir={tmp_path}", "pada.reward=[size_per_cm=0.5]",
                                   f"pada.variant_reward={{pada: ['{terms}']}}"])
    assert reward_overrides(cfg, "pada") == ["size_per_cm=0.5", terms]
    assert reward_overrides(cfg, "grpo") == ["size_per_cm=0.5"]  # the paper's bare reward beside it
    bad = training_config("tiny", [f"output_dir={tmp_path}", "pada.variant_reward={padda: []}"])
    with pytest.raises(ValueError, match=r"pada.variant_reward: unknown variant\(s\) \['padda'\]"):
        reward_overrides(bad, "pada")


def test_out_of_zone_is_a_validity_term(written_into):
    clean, _ = written_into(3.0)
    parents = {o.parent for o in clean.objects}
    alone = next(o for o in clean.objects if o.parent == TABLE and o.instance_id not in parents)
    width = clean.zone.xmax - clean.zone.xmin
    pushed = clean.with_objects(o.moved(center=(o.center[0] + width, *o.center[1:])) if o is alone else o
                                for o in clean.objects)
    texts = [completion_text(s, decimals=2) for s in (clean, pushed)]
    paper = PhysicsReward(RewardConfig()).score(texts).rewards
    assert paper.tolist() == [50.0, 50.0]  # pushed off the table out of every collision: paid as clean
    scored = PhysicsReward(RewardConfig(valid_terms=("out_of_zone",))).score(texts)
    assert scored.rewards.tolist() == [50.0, -50.0]
    assert scored.metrics["mean_out_of_zone_objects"] == pytest.approx(0.5)


class CharacterTokenizer:
    """One token per character: the fit of a completion is its length."""

    def __call__(self, texts, add_special_tokens=False):
        return {"input_ids": [list(range(len(t))) for t in texts]}


def test_the_prompt_pool_spreads_over_the_levels_that_fit():
    # level L: 10 records of completions 10 * L characters long, and 5 of 100 characters
    records = [{"id": f"{lv}-{k}", "level": lv, "prompt": "p", "completion": "x" * (10 * lv)}
               for k in range(10) for lv in range(1, 6)]
    records += [{"id": f"long-{k}", "level": 1 + k % 5, "prompt": "p", "completion": "x" * 100}
                for k in range(5)]
    pool, counts = prompt_pool(records, CharacterTokenizer(), size=26, max_tokens=41)
    assert {lv: (c["records"], c["fit"]) for lv, c in counts.items()} == \
        {1: (11, 10), 2: (11, 10), 3: (11, 10), 4: (11, 10), 5: (11, 0)}  # 40 + EOS fits, 50 does not
    assert [counts[lv]["picked"] for lv in range(1, 6)] == [7, 7, 6, 6, 0]  # one of each level per round
    assert len(pool) == 26 and all(len(r["completion"]) <= 40 for r in pool)
    assert pool == [r for r in records if r in pool]  # the records' own order
    every, counts = prompt_pool(records, CharacterTokenizer(), size=4096, max_tokens=1000)
    assert len(every) == len(records) and sum(c["picked"] for c in counts.values()) == 55
    with pytest.raises(ValueError, match="prompt pool: size and max_tokens must be >= 1"):
        prompt_pool(records, CharacterTokenizer(), size=0, max_tokens=10)


def test_a_resumed_constant_run_decays_from_where_it_stopped(tmp_path):
    """``pada.decay_steps``: the schedule the Trainer builds (its ``create_scheduler`` call) holds the
    learning rate until ``max_steps - decay_steps`` and then takes it down a cosine to 0; loaded with a
    constant run's scheduler state at step 6 (what a resume does), its next steps are the decay's, not a
    restart."""
    import torch
    from transformers.optimization import get_scheduler

    def scheduler(args, optimizer):  # transformers.Trainer.create_scheduler, as it calls it
        return get_scheduler(args.lr_scheduler_type, optimizer=optimizer,
                             num_warmup_steps=args.get_warmup_steps(args.max_steps),
                             num_training_steps=args.max_steps,
                             scheduler_specific_kwargs=args.lr_scheduler_kwargs)

    def optimizer(lr):
        return torch.optim.AdamW([torch.nn.Parameter(torch.zeros(2))], lr=lr)

    constant = arguments(tmp_path, "pada.max_steps=6")
    assert constant.lr_scheduler_type == "constant"
    before = scheduler(constant, optimizer(constant.learning_rate))
    for _ in range(6):
        before.optimizer.step()
        before.step()
    decay = arguments(tmp_path, "pada.max_steps=10", "pada.decay_steps=4")
    assert decay.lr_scheduler_kwargs == {"num_decay_steps": 4}
    after = scheduler(decay, optimizer(decay.learning_rate))
    after.load_state_dict(before.state_dict())
    lr = decay.learning_rate
    seen = [after.get_last_lr()[0]]
    for _ in range(4):
        after.optimizer.step()
        after.step()
        seen.append(after.get_last_lr()[0])
    assert seen[0] == pytest.approx(lr)  # step 6: still the constant run's rate
    assert seen[1:] == pytest.approx([lr * (1 + math.cos(math.pi * k / 4)) / 2 for k in (1, 2, 3, 4)])
    assert seen[-1] == pytest.approx(0.0)
    with pytest.raises(ValueError, match=r"pada.decay_steps=4 decays a constant rate; got "
                                         r"pada.lr_scheduler_type='cosine'"):
        arguments(tmp_path, "pada.max_steps=10", "pada.decay_steps=4", "pada.lr_scheduler_type=cosine")
    with pytest.raises(ValueError, match=r"pada.decay_steps=12 must be in 1..pada.max_steps \(10\)"):
        arguments(tmp_path, "pada.max_steps=10", "pada.decay_steps=12")
