"""The tiny training pipeline end to end on CPU: SFT steps -> anchors (generation + TTO) -> GRPO,
PADA* and PADA steps -> generation and evaluation of the trained policy (parse rate, reward).

Kept small (12 two-object scenes, a 0.2 M-parameter model, 1-3 optimizer steps per stage) so it runs
in well under a minute on two busy cores. A 3-step SFT model cannot write layouts yet, so the PADA
stages train on anchors made from the noisy reference completions (TTO-repaired, like anchors made
from SFT output); the anchors stage itself still runs on the model's own generations.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from physcene.config import load_config
from physcene.ctrc import ParseError, build_prompt, completion_text, parse
from physcene.data.noisy import noisy_scenes
from physcene.layout import layout_to_dict
from physcene.reward import ChargeConfig, PhysicsReward, RewardConfig
from physcene.train.anchors import anchor_nll, anchor_prompts, anchor_records, anchor_summary, run_anchors
from physcene.train.generate import generate, load_for_generation
from physcene.train.pada import run_pada
from physcene.train.records import load_records, write_records
from physcene.train.sft import run_sft
from physcene.tto import TTOConfig

TTO_FAST = ["steps=20", "report_relations=false"]


def _records(n: int, seed: int) -> list[dict]:
    scenes = noisy_scenes(n, n_objects=2, seed=seed, noise_cm=3.0)
    return [{"id": f"s{seed}_{k}", "scene_type": "office", "level": 1,
             "instruction": "Place the objects on the desk.",
             "prompt": build_prompt("Place the objects on the desk.", "office", s.zone, s.objects),
             "completion": completion_text(s), "layout": layout_to_dict(s)} for k, s in enumerate(scenes)]


def _sft_for_pada(tmp_path, n: int, seed: int, *pada_overrides: str):
    """The tiny config on ``n`` two-object scenes that are their own anchors, after one SFT step: PADA
    (unconstrained, 16-token completions, a log entry per step) with ``pada_overrides``."""
    train = [dict(r, anchor=r["completion"]) for r in _records(n, seed=seed)]
    write_records(train, tmp_path / "train.jsonl")
    cfg = load_config("train_tiny", [
        f"data.train={tmp_path / 'train.jsonl'}", f"output_dir={tmp_path / 'run'}", "sft.max_steps=1",
        "sft.max_length=1024", f"pada.anchors={tmp_path / 'train.jsonl'}", "pada.max_completion_length=16",
        "pada.logging_steps=1", "pada.save_steps=100", "pada.constrained=false", *pada_overrides])
    run_sft(cfg)
    return cfg


@pytest.fixture
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny matmuls on two shared cores: threads only contend
    yield
    torch.set_num_threads(old)


def test_tiny_pipeline_end_to_end(tmp_path, one_thread, monkeypatch):
    from physcene.physics import PhysicsEngine

    engine = PhysicsEngine()
    train = _records(12, seed=0)
    write_records(train, tmp_path / "train.jsonl")
    cfg = load_config("train_tiny", [
        f"data.train={tmp_path / 'train.jsonl'}", f"output_dir={tmp_path / 'run'}", "sft.max_steps=3",
        "sft.max_length=1024", "anchors.max_new_tokens=32", f"anchors.tto=[{','.join(TTO_FAST)}]",
        "pada.max_steps=1", "pada.max_completion_length=32", "pada.logging_steps=1"])

    # Stage 1: SFT.
    sft_dir = run_sft(cfg)
    assert (sft_dir / "model.safetensors").is_file() and (sft_dir / "tokenizer.json").is_file()
    log = json.loads((sft_dir / "train_log.json").read_text())
    assert [e["step"] for e in log if "loss" in e] == [1, 2, 3]

    # Anchors from the SFT model's own generations: one row per record, summary written.
    anchors_path = run_anchors(cfg)
    rows = load_records(str(anchors_path))
    assert [r["id"] for r in rows] == [r["id"] for r in train]
    assert all({"anchor", "anchor_raw", "anchor_parse_error", "sft_completion"} <= set(r) for r in rows)
    # each row either ended with EOS within the 32 new tokens or was cut at exactly 32
    assert all(1 <= r["sft_tokens"] <= 32 for r in rows)
    assert all(r["sft_tokens"] == 32 for r in rows if r["sft_truncated"])
    summary = json.loads(anchors_path.with_suffix(".summary.json").read_text())
    assert summary["n"] == 12 and 0.0 <= summary["parse_rate"] <= 1.0
    assert summary["tokens_max"] <= 32 and 0.0 <= summary["truncated_rate"] <= 1.0

    # Anchors through the same TTO path from the noisy reference completions (SFT-like, colliding).
    rows = anchor_records(train, [r["completion"] for r in train], tto_config=TTOConfig.load(TTO_FAST),
                          engine=engine)
    stats = anchor_summary(rows)
    assert stats["parse_rate"] == 1.0
    assert stats["energy_before_mean_cm"] > 0
    assert stats["energy_after_mean_cm"] < stats["energy_before_mean_cm"]
    assert all(not isinstance(parse(r["anchor"]), ParseError) for r in rows)
    write_records(rows, tmp_path / "anchors_ref.jsonl")

    # Stage 2: one optimizer step of each variant; the paper's reward, sharing this test's engine.
    reward = PhysicsReward(RewardConfig(device="cpu"), engine=engine)
    outs = {}
    vcfg = OmegaConf.merge(cfg, {"pada": {"anchors": str(tmp_path / "anchors_ref.jsonl")}})
    from physcene.train.constrained import CTRCConstraint

    calls = []
    plain_call = CTRCConstraint.__call__
    monkeypatch.setattr(CTRCConstraint, "__call__", lambda self, *a: calls.append(1) or plain_call(self, *a))
    for variant in ("grpo", "pada_star", "pada"):
        # pada samples its groups under the CTRC constraint (pada.constrained), the others without
        # (and leaves the tokens the constraint chose out of its loss: pada.mask_overruled)
        # (and stops a run once the constraint overrules more than pada.stop_overruled of the tokens)
        constrained = OmegaConf.merge(vcfg, {"pada": {"constrained": variant == "pada",
                                                      "mask_overruled": variant == "pada",
                                                      "stop_overruled": 1e-6, "stop_overruled_steps": 1}})
        outs[variant] = run_pada(constrained, variant=variant, reward=reward)
        assert bool(calls) == (variant == "pada")
        assert outs[variant].name == variant and (outs[variant] / "adapter_model.safetensors").is_file()
        step = [e for e in json.loads((outs[variant] / "train_log.json").read_text()) if "reward" in e][0]
        assert {"parse_rate", "kl", "rewards/physics/mean"} <= set(step)
        assert 0 < step["beta"] <= 1.0  # the adaptive KL coefficient after this step (configs: 0.04 to start)
        # where the step's time went: generation (with the constraint's host time) and the reward
        assert 0 < step["time/reward_s"] and 0 < step["time/generate_s"] < step["step_time"]
        assert ("time/constraint_s" in step) == (variant == "pada")
        if variant == "pada":
            assert 0 < step["time/constraint_s"] < step["time/generate_s"]
            assert 0 <= step["time/constraint_scan_s"] <= step["time/constraint_s"]
            assert step["time/constraint_wait_s"] == 0.0  # no device to wait for on the CPU
            assert step["constraint/refused_draws"] >= 0 and step["constraint/vocabulary_scans"] >= 0
            assert 0 <= step["constraint/overruled_frac"] <= 1
            info = json.loads((outs[variant] / "physcene_run.json").read_text())
            assert info["stopped_off_grammar"] == (1 if step["constraint/overruled_frac"] > 1e-6 else None)
        assert ("anchor_ce" in step) == (variant != "grpo")
        if variant != "grpo":
            assert step["anchor_ce"] > 0

    # Evaluate the PADA policy on held-out prompts: parse rate and reward of its layouts.
    test = _records(4, seed=1)
    texts = generate(outs["pada"], [r["prompt"] for r in test], max_new_tokens=32, batch_size=4)
    assert len(texts) == 4 and all(isinstance(t, str) for t in texts)
    scored = reward.score(texts)
    rewards = scored.rewards.tolist()
    assert all(r == -100.0 or r == 50.0 or -50.0 <= r < 0.0 for r in rewards)
    assert 0.0 <= scored.metrics["parse_failure_rate"] <= 1.0
    # The reference completions score through the same path, and all parse.
    scored = reward.score([r["completion"] for r in test])
    assert scored.metrics["parse_failure_rate"] == 0.0 and -100.0 not in scored.rewards.tolist()


def test_train_cli_reports_bad_config_in_one_line(capsys):
    from physcene.cli import main

    assert main(["train", "sft", "--config", "no_such_config"]) == 2
    err = capsys.readouterr().err
    assert "unknown config 'train_no_such_config'" in err and "Traceback" not in err


CHAT_TEMPLATE = ("{% for m in messages %}<|im_start|>{{ m.role }}\n{{ m.content }}<|endoftext|>\n{% endfor %}"
                 "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}")


def test_chat_format_pretrained_checkpoint(tmp_path, one_thread):
    """The 8B code path at tiny size: a local 'pretrained' checkpoint with a chat template, conversational
    SFT, conversational PADA with anchors, chat-wrapped generation."""
    from physcene.train.models import build_scratch_model, load_tokenizer
    from physcene.train.tokenizer import train_tokenizer

    records = _records(4, seed=2)
    for r in records:
        r["anchor"] = r["anchor_raw"] = r["completion"]
    write_records(records, tmp_path / "train.jsonl")
    base = tmp_path / "base"
    tok = train_tokenizer([r["prompt"] + r["completion"] for r in records], base, vocab_size=300)
    tok.chat_template = CHAT_TEMPLATE
    tok.save_pretrained(base)
    arch = dict(load_config("train_tiny").model.arch)
    build_scratch_model(arch, load_tokenizer(base)).save_pretrained(base)
    cfg = load_config("train_tiny", [
        "model.source=pretrained", f"model.path={base}", "model.chat_format=true",
        f"data.train={tmp_path / 'train.jsonl'}", f"output_dir={tmp_path / 'run'}", "sft.max_steps=2",
        f"pada.anchors={tmp_path / 'train.jsonl'}", "pada.max_steps=1", "pada.max_completion_length=16"])
    sft_dir = run_sft(cfg)
    info = json.loads((sft_dir / "physcene_run.json").read_text())
    assert info["chat_format"] is True and info["base_model"] == str(base) and info["steps"] == 2
    out = run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")))
    step = [e for e in json.loads((out / "train_log.json").read_text()) if "reward" in e][0]
    assert step["anchor_ce"] > 0 and step["parse_rate"] == 0.0
    texts = generate(out, [r["prompt"] for r in records[:2]], max_new_tokens=8)
    # Completions only: neither the prompt nor the chat wrapping comes back.
    assert len(texts) == 2 and all(records[0]["prompt"][:30] not in t and "user\n" not in t for t in texts)


def test_ablation_rows_per_level_and_per_checkpoint(tmp_path, one_thread, capsys):
    """`physcene train ablation` with one RL variant and ``ablation.checkpoints``: the table has the
    SFT, SFT + TTO and GRPO rows, each with its per-level figures, and a row for the intermediate
    checkpoint (the final step is the GRPO row itself). Run again, it re-scores every model row from
    the layouts the first run wrote (the same checkpoints, the same settings) to the same figures, and
    decodes again a row whose settings changed."""
    from physcene.train.ablation import run_ablation

    write_records(_records(8, seed=0), tmp_path / "train.jsonl")
    out = tmp_path / "run"
    cfg = load_config("train_tiny", [
        f"data.train={tmp_path / 'train.jsonl'}", f"output_dir={out}", "sft.max_steps=2",
        "sft.max_length=1024", "anchors.max_new_tokens=16", f"anchors.tto=[{','.join(TTO_FAST)}]",
        "pada.max_steps=2", "pada.save_steps=1", "pada.save_total_limit=null",
        "pada.max_completion_length=16", "ablation.variants=[grpo]", "ablation.checkpoints=true",
        "ablation.n_test=2", "eval.max_new_tokens=16",
        f"ablation.heldout_anchors={tmp_path / 'heldout.jsonl'}"])
    write_records([dict(r, anchor=r["completion"]) for r in _records(3, seed=9)], tmp_path / "heldout.jsonl")
    result = run_ablation(cfg, budget_min=30)
    assert [r["name"] for r in result["rows"]] == ["sft", "sft+tto", "grpo"]
    # every model row scores the held-out anchors (sft+tto is the SFT model's layouts repaired: no model)
    nll = {r["name"]: r.get("anchor_nll") for r in result["rows"] + result["checkpoint_rows"]}
    assert nll["sft+tto"] is None and all(0 < nll[k] < 20 for k in ("sft", "grpo", "grpo@1"))
    assert [r["name"] for r in result["checkpoint_rows"]] == ["grpo@1"]
    for row in result["rows"] + result["checkpoint_rows"]:
        assert sum(level["n"] for level in row["by_level"].values()) == row["n"] == 2
    table = (out / "ablation.md").read_text()
    assert "| grpo@1 |" in table and "SCR / ACR" in table and "held-out anchor NLL" in table
    assert "pada" not in result["stages"] and not (out / "pada").exists()
    written = json.loads((out / "ablation.json").read_text())
    assert written["checkpoint_rows"][0]["by_level"] == result["checkpoint_rows"][0]["by_level"]
    # the table's schema: every row names its steps and its gzipped layouts; the curves come with it
    from physcene.train.ablation import check_ablation

    check_ablation(written)
    every = written["rows"] + written["checkpoint_rows"]
    assert [(r["rl_steps"], Path(r["layouts"]).name) for r in every] == \
        [(0, "sft.jsonl.gz"), (0, "sft_tto.jsonl.gz"), (2, "grpo.jsonl.gz"), (1, "grpo-1.jsonl.gz")]
    assert (out / "ablation" / "grpo-1.jsonl.gz").is_file() and (out / "ablation.svg").is_file()
    capsys.readouterr()
    again = run_ablation(cfg, budget_min=30)
    log = capsys.readouterr().err
    assert all(f"{name} layouts read from" in log for name in ("sft", "grpo", "grpo@1"))
    figures = ("scr", "acr", "parse_rate", "judge_avg", "by_level")
    assert [[r[k] for k in figures] for r in again["rows"] + again["checkpoint_rows"]] == \
        [[r[k] for k in figures] for r in result["rows"] + result["checkpoint_rows"]]
    run_ablation(OmegaConf.merge(cfg, {"eval": {"max_new_tokens": 12}}), budget_min=30)
    assert "layouts read from" not in capsys.readouterr().err


def test_pada_resumes_from_its_last_checkpoint_with_its_beta(tmp_path, one_thread, step_counter):
    """RL split over machines: a rerun of the same PADA command goes on from the last checkpoint (the
    optimizer steps already taken are not repeated) and from the adaptive-KL β logged there, not the
    configured one."""
    train = _records(8, seed=1)
    write_records(train, tmp_path / "train.jsonl")
    base = [f"data.train={tmp_path / 'train.jsonl'}", f"output_dir={tmp_path / 'run'}", "sft.max_steps=2",
            "sft.max_length=1024", f"pada.anchors={tmp_path / 'train.jsonl'}",
            "pada.max_completion_length=16", "pada.logging_steps=1", "pada.save_steps=1",
            "pada.constrained=false", "pada.adaptive_kl.horizon=2"]  # β moves ~10 % a step

    cfg = load_config("train_tiny", [*base, "pada.max_steps=2"])
    run_sft(cfg)
    reward = PhysicsReward(RewardConfig(device="cpu"))
    first, second = step_counter(), step_counter()
    out = run_pada(cfg, variant="grpo", reward=reward, callbacks=[first])
    assert (first.begin, first.steps) == (0, 2) and (out / "checkpoint-2").is_dir()
    logged = json.loads((out / "checkpoint-2" / "trainer_state.json").read_text())["log_history"]
    betas = [e["beta"] for e in logged if "beta" in e]
    assert len(betas) == 2 and betas[-1] != 0.04  # moved by the KL of each step
    run_pada(load_config("train_tiny", [*base, "pada.max_steps=3"]), variant="grpo", reward=reward,
             callbacks=[second])
    assert (second.begin, second.steps) == (2, 1)  # resumed at step 2: only step 3 ran
    log = json.loads((out / "train_log.json").read_text())
    step3 = [e for e in log if e.get("step") == 3 and "kl" in e][0]
    kl = cfg.pada.adaptive_kl
    error = min(max(step3["kl"] / kl.target - 1.0, -0.2), 0.2)
    assert step3["beta"] == pytest.approx(betas[-1] * (1.0 + error / kl.horizon))  # from step 2's β


def test_one_generation_round_feeds_several_optimizer_steps(tmp_path, one_thread, step_counter,
                                                              monkeypatch):
    """``pada.generation_batches`` x ``pada.num_iterations`` optimizer steps per generation round:
    TRL generates the round's completions once (with their anchors), splits them into batches of
    ``global_batch_size`` and passes over them ``num_iterations`` times; every step still adds the
    anchor CE."""
    from physcene.train.pada import PADATrainer

    cfg = _sft_for_pada(tmp_path, 8, 2, "pada.max_steps=4", "pada.generation_batches=2",
                        "pada.num_iterations=2")
    rounds = []
    original = PADATrainer._generate_and_score_completions

    def counted(self, inputs):
        output = original(self, inputs)
        rounds.append((len(inputs), tuple(output["anchor_ids"].shape)))
        return output

    monkeypatch.setattr(PADATrainer, "_generate_and_score_completions", counted)
    counter = step_counter()
    out = run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")), callbacks=[counter])
    assert counter.steps == 4
    assert len(rounds) == 1 and rounds[0][0] == 2 * int(cfg.pada.global_batch_size)  # 16 completions once
    assert rounds[0][1][0] == 16  # one anchor row per completion, split with them
    log = json.loads((out / "train_log.json").read_text())
    steps = [e for e in log if "anchor_ce" in e]
    assert [e["step"] for e in steps] == [1, 2, 3, 4]


def test_anchor_ce_reads_each_prompts_anchor_once(tmp_path, one_thread, monkeypatch):
    """The G completions of a prompt carry one anchor: the CE's forward sees one row per distinct
    (prompt, anchor) and the micro-batches' weights add up to one per optimizer step, so the term is
    the mean NLL over the round's distinct anchor tokens (the duplicates counted once, not G times)."""
    from physcene.train.pada import PADATrainer, anchor_owners

    assert anchor_owners([{"prompt": "p", "anchor": "a"}, {"prompt": "p", "anchor": "a"},
                          {"prompt": "q", "anchor": "b"}, {"prompt": "r", "anchor": ""},
                          {"prompt": "q", "anchor": "b"}], "anchor") == [True, False, True, False, False]
    cfg = _sft_for_pada(tmp_path, 8, 4, "pada.max_steps=2", "pada.num_generations=4",
                        "pada.global_batch_size=8", "pada.per_device_batch_size=2")
    rows, weights = [], []
    nll = PADATrainer.target_nll

    def counted(self, model, inputs, name):
        if name == "anchor":
            rows.append(inputs["anchor_ids"].size(0))
            assert bool((inputs["anchor_loss_mask"].sum(1) > 0).all())  # owners only
        return nll(self, model, inputs, name)

    compute = PADATrainer._compute_loss

    def weighed(self, model, inputs):
        if "anchor_tokens" in inputs:
            weights.append(float(inputs["anchor_loss_mask"].sum() / inputs["anchor_tokens"]))
        return compute(self, model, inputs)

    monkeypatch.setattr(PADATrainer, "target_nll", counted)
    monkeypatch.setattr(PADATrainer, "_compute_loss", weighed)
    run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")))
    # 2 steps x 4 micro-batches of 2 completions; 2 prompts x G = 4 per step: 2 anchors per step
    assert len(weights) == 8 and sum(rows) == 4 and max(rows) <= 2
    assert sum(weights[:4]) == pytest.approx(1.0) and sum(weights[4:]) == pytest.approx(1.0)


def test_length_grouped_micro_batches_give_the_same_gradient(tmp_path, one_thread, monkeypatch):
    """``pada.length_grouping``: rollouts of different lengths regrouped by length within each
    optimizer step and each micro-batch cut to its longest row give the gradient of TRL's random
    micro-batches at full width (the same sum in another order: LoRA dropout off, so that each row
    meets the same weights), and the cut happens."""
    from transformers import TrainerCallback

    from physcene.train import micro_batches
    from physcene.train.pada import PADATrainer

    def fixed_rollouts(self, prompt_ids, *args, **kwargs):  # lengths 2..13 tokens, then EOS
        eos = self.eos_token_ids[0]
        return [[5 + (i + k) % 40 for k in range(2 + (7 * i) % 12)] + [eos]
                for i in range(len(prompt_ids))], None

    widths = []

    def cut(batch):
        out = micro_batches.trimmed(batch)
        widths.append(out["completion_ids"].shape[1])
        return out

    class FirstGradient(TrainerCallback):
        def on_pre_optimizer_step(self, args, state, control, model=None, **kwargs):
            if state.global_step == 0:
                grads[grouping] = torch.cat([p.grad.flatten() for p in model.parameters()
                                             if p.requires_grad and p.grad is not None])

    monkeypatch.setattr(PADATrainer, "_generate_single_turn", fixed_rollouts)
    monkeypatch.setattr("physcene.train.pada.trimmed", cut)
    # a reward that tells the rollouts apart (their length), so the policy-gradient term is not zero
    monkeypatch.setattr("physcene.train.pada.PhysicsRewardFunction.__call__",
                        lambda self, prompts, completions, **kw: [float(len(c)) for c in completions])
    grads = {}
    for grouping in (False, True):
        cfg = _sft_for_pada(tmp_path / str(grouping), 8, 5, "pada.max_steps=1", "pada.num_generations=2",
                            "pada.global_batch_size=8", "pada.per_device_batch_size=2",
                            "pada.lora.dropout=0.0", f"pada.length_grouping={str(grouping).lower()}")
        run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")),
                 callbacks=[FirstGradient()])
    assert grads[True].norm() > 0
    assert torch.allclose(grads[True], grads[False], atol=1e-7, rtol=1e-4)
    assert len(widths) == 4 and min(widths) < max(widths) <= 14  # each micro-batch cut to its longest


def test_nonfinite_probe_names_the_loss_term_and_rows_that_broke(tmp_path, one_thread, monkeypatch):
    """``pada.nonfinite_probe``: an anchor CE whose value is finite but whose backward is NaN (the GPU
    runs' symptom: a finite loss, every LoRA gradient NaN) is found by the probe: the GRPO term's
    backward is finite, the anchor CE's is not, under either attention kernel and for each row alone;
    the micro-batch is saved for a replay, and the step is still dropped."""
    from physcene.train.pada import PADATrainer

    cfg = _sft_for_pada(tmp_path, 4, 3, "pada.max_steps=1", "pada.nonfinite_probe=1")
    clean = PADATrainer.anchor_cross_entropy

    def poisoned(self, model, inputs):  # sqrt at 0 under a zero weight: value unchanged, gradient NaN
        ce = clean(self, model, inputs)
        weight = next(p for p in model.parameters() if p.requires_grad)
        return ce + 0.0 * (weight.sum() * 0.0).sqrt()

    monkeypatch.setattr(PADATrainer, "anchor_cross_entropy", poisoned)
    out = run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")))
    report = json.loads((out / "nonfinite_probe.jsonl").read_text().splitlines()[0])
    assert report["step"] == 1
    assert report["grpo_loss"][1] is True and report["anchor_ce"][1] is False
    assert report["anchor_ce_eager"][1] is False
    assert report["anchor_rows"] and not any(r["finite"] for r in report["anchor_rows"])
    assert all(r["anchor_tokens"] <= r["anchor_width"] for r in report["anchor_rows"])
    saved = torch.load(out / f"nonfinite_step{report['step']}.pt")
    assert {"prompt_ids", "completion_ids", "anchor_ids", "anchor_loss_mask"} <= set(saved)
    assert json.loads((out / "physcene_run.json").read_text())["nonfinite_steps_dropped"] == [1]


def test_pada_with_object_credit_trains_on_per_token_advantages(tmp_path, one_thread, monkeypatch):
    """``pada.object_credit`` (not in the paper) through TRL: the advantages become (B, T), the steps run
    and the credit's figures are logged; a negative weight is refused."""
    from physcene.train.object_credit import ObjectCredit

    cfg = _sft_for_pada(tmp_path, 4, 4, "pada.max_steps=2", "pada.object_credit=1.0",
                        "pada.object_credit_penetration=pairs", "pada.object_credit_terms=[penetration,size]")
    seen, charges = [], []
    original = ObjectCredit.after_scoring

    def spy(self, trainer, inputs, output):
        original(self, trainer, inputs, output)
        seen.append(tuple(output["advantages"].shape))
        charges.append(trainer.reward_funcs[0].keywords["charges"])  # what the trainer asks the reward for

    monkeypatch.setattr(ObjectCredit, "after_scoring", spy)
    reward = PhysicsReward(RewardConfig(device="cpu"))
    out = run_pada(cfg, variant="pada", reward=reward)
    asked = ChargeConfig(terms=("penetration", "size"), penetration="pairs")
    assert charges and all(c == asked for c in charges)
    assert reward.charges is None  # the trainer binds its charges to its calls: the reward keeps no flags
    assert seen and all(len(shape) == 2 and shape[1] > 1 for shape in seen)
    log = json.loads((out / "train_log.json").read_text())
    assert any("object_credit/charged_token_frac" in e for e in log)
    assert json.loads((out / "physcene_run.json").read_text())["steps"] == 2
    with pytest.raises(ValueError, match="object_credit must be >= 0"):
        run_pada(load_config("train_tiny", [f"output_dir={tmp_path / 'neg'}", "pada.object_credit=-1"]),
                 variant="pada")


def test_anchor_nll_is_the_mean_nll_of_the_anchor_tokens_whatever_the_batching(tmp_path, one_thread):
    """The held-out anchor measure: the mean NLL per anchor token (EOS included) given the prompt, the
    same one row at a time as in padded batches of rows of different lengths, and equal to the NLL
    summed by hand from the model's logits; a record without an anchor is left out."""
    cfg = _sft_for_pada(tmp_path, 4, seed=3)
    rows = [dict(r, anchor=r["completion"]) for r in _records(5, seed=4)]
    rows[1]["anchor"] = rows[1]["anchor"][:40]  # rows of different lengths share a padded batch
    rows[2]["anchor"] = ""
    one = anchor_nll(cfg.sft.output_dir, rows, batch_size=1, device="cpu")
    batched = anchor_nll(cfg.sft.output_dir, rows, batch_size=4, device="cpu")
    assert one["n"] == batched["n"] == 4 and one["tokens"] == batched["tokens"]
    assert batched["nll"] == pytest.approx(one["nll"], rel=1e-4)
    model, tokenizer, _ = load_for_generation(cfg.sft.output_dir, device="cpu")
    prompt = tokenizer(rows[0]["prompt"], add_special_tokens=False)["input_ids"]
    target = tokenizer(rows[0]["anchor"], add_special_tokens=False)["input_ids"] + [tokenizer.eos_token_id]
    with torch.no_grad():
        logps = model(input_ids=torch.tensor([prompt + target])).logits[0].float().log_softmax(-1)
    by_hand = -sum(float(logps[len(prompt) - 1 + k, t]) for k, t in enumerate(target)) / len(target)
    assert anchor_nll(cfg.sft.output_dir, rows[:1], device="cpu")["nll"] == pytest.approx(by_hand, rel=1e-4)


def test_held_out_anchors_leave_out_the_pools_prompts(tmp_path):
    """``anchors.exclude``: the prompts of an earlier anchor file (the RL pool's) get no anchor, so the
    held-out anchors come from prompts the policy never trained on."""
    records = _records(6, seed=5)
    write_records(records, tmp_path / "train.jsonl")
    write_records(records[1:3], tmp_path / "pool.jsonl")
    cfg = load_config("train_tiny", [f"data.train={tmp_path / 'train.jsonl'}", f"output_dir={tmp_path}",
                                     f"anchors.exclude={tmp_path / 'pool.jsonl'}", "anchors.n_records=10"])
    assert [r["id"] for r in anchor_prompts(cfg)] == [records[k]["id"] for k in (0, 3, 4, 5)]


def test_anchor_likelihood_cli_scores_each_named_checkpoint(tmp_path, one_thread, monkeypatch, capsys):
    """`python -m physcene.train.analysis.anchor_likelihood ANCHORS NAME=PATH ... --out J`: each model's
    held-out anchor NLL, the one the ablation writes into its rows; a NAME=PATH that names no folder
    is one clear error."""
    from physcene.train.analysis import anchor_likelihood

    cfg = _sft_for_pada(tmp_path, 4, seed=3)
    write_records([dict(r, anchor=r["completion"]) for r in _records(3, seed=6)], tmp_path / "held.jsonl")
    out = tmp_path / "nll.json"
    monkeypatch.setattr("sys.argv", ["anchor_likelihood", str(tmp_path / "held.jsonl"),
                                     f"sft={cfg.sft.output_dir}", "--out", str(out)])
    anchor_likelihood.main()
    result = json.loads(out.read_text())
    expected = anchor_nll(cfg.sft.output_dir, load_records(str(tmp_path / "held.jsonl")), max_length=2304)
    assert result["n"] == 3 and result["models"]["sft"]["nll"] == pytest.approx(expected["nll"])
    assert result["command"].startswith("python -m physcene.train.analysis.anchor_likelihood")
    monkeypatch.setattr("sys.argv", ["anchor_likelihood", str(tmp_path / "held.jsonl"), "pada=/no/such/dir"])
    with pytest.raises(SystemExit):
        anchor_likelihood.main()
    assert "model pada: '/no/such/dir' is not a checkpoint folder" in capsys.readouterr().err


def test_pada_without_lora_trains_every_weight_and_loads_for_generation(tmp_path, one_thread):
    """``pada.lora=null``: PADA fine-tunes every weight of the policy (a small model from scratch, where
    LoRA's rank bounds what RL can change); the run saves a whole model, which differs from the SFT
    base, has no adapter, and decodes through the generation loader as the evaluation reads it."""
    from safetensors.torch import load_file

    from physcene.train.generate import generate_token_ids

    cfg = _sft_for_pada(tmp_path, 4, 6, "pada.max_steps=2", "pada.lora=null", "pada.num_generations=2",
                        "pada.global_batch_size=4", "pada.per_device_batch_size=2")
    out = run_pada(cfg, variant="pada", reward=PhysicsReward(RewardConfig(device="cpu")))
    assert not (out / "adapter_config.json").exists() and (out / "config.json").is_file()
    sft, rl = (load_file(next(Path(d).glob("*.safetensors"))) for d in (cfg.sft.output_dir, out))
    changed = [k for k in sft if k in rl and not torch.equal(sft[k].float(), rl[k].float())]
    assert len(changed) > len(sft) // 2  # the norms, embeddings and MLPs too, not a few projections
    assert json.loads((out / "physcene_run.json").read_text())["steps"] == 2
    model, tokenizer, _ = load_for_generation(out, device="cpu")
    prompt = json.loads(Path(cfg.data.train).read_text().splitlines()[0])["prompt"]
    ids = generate_token_ids(model, tokenizer, [prompt], max_new_tokens=8, batch_size=1)
    assert len(ids) == 1 and 0 < len(ids[0]) <= 8


def test_anchor_nll_at_a_temperature_divides_the_logits_by_it(tmp_path, one_thread):
    """``anchor_nll(..., temperature=T)``: the NLL under softmax(logits / T), the temperature PADA's
    cross-entropy is taken at (TRL's log-probabilities divide by ``pada.temperature``); T = 1 is the
    untempered figure, and a temperature that is not positive is refused."""
    cfg = _sft_for_pada(tmp_path, 4, seed=3)
    rows = [dict(r, anchor=r["completion"]) for r in _records(1, seed=4)]
    model, tokenizer, _ = load_for_generation(cfg.sft.output_dir, device="cpu")
    prompt = tokenizer(rows[0]["prompt"], add_special_tokens=False)["input_ids"]
    target = tokenizer(rows[0]["anchor"], add_special_tokens=False)["input_ids"] + [tokenizer.eos_token_id]
    with torch.no_grad():
        logits = model(input_ids=torch.tensor([prompt + target])).logits[0].float()
    for temperature in (0.4, 1.0):
        logps = (logits / temperature).log_softmax(-1)
        by_hand = -sum(float(logps[len(prompt) - 1 + k, t]) for k, t in enumerate(target)) / len(target)
        got = anchor_nll(cfg.sft.output_dir, rows, device="cpu", temperature=temperature)["nll"]
        assert got == pytest.approx(by_hand, rel=1e-4)
    assert anchor_nll(cfg.sft.output_dir, rows, device="cpu", temperature=0.4)["nll"] != pytest.approx(
        anchor_nll(cfg.sft.output_dir, rows, device="cpu")["nll"], rel=1e-3)
    with pytest.raises(ValueError, match="temperature must be > 0"):
        anchor_nll(cfg.sft.output_dir, rows, device="cpu", temperature=0.0)
