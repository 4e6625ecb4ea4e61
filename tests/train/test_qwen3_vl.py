"""The paper's backbone class at tiny size on CPU: a random Qwen3-VL checkpoint (``conftest.py``) through
``physcene train sft`` (full fine-tune, vision tower frozen), ``train anchors``, ``train pada`` (LoRA
r 16 / α 32 on the language model's q, k, v, o, gate, up, down), ``eval`` and ``generate`` with
``--generator model:PATH``, all by the CLI with ``--config qwen3_vl_8b model.path=<checkpoint>``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file
from transformers import AutoTokenizer

from physcene.cli import main
from physcene.train.records import load_records, write_records

# The qwen3_vl_8b config made tiny: 4 records, 2 SFT steps, 1 PADA step of 2 prompts x G = 4,
# short lengths; fp32 on the CPU.
TINY = ["data.train=synth:train:4", "model.dtype=float32", "sft.max_steps=2", "sft.global_batch_size=2",
        "sft.per_device_batch_size=2", "sft.max_length=640", "sft.save_steps=100", "sft.logging_steps=1",
        "sft.gradient_checkpointing=false", "anchors.max_new_tokens=8", "anchors.batch_size=4",
        "anchors.tto=[steps=5]", "pada.max_steps=1", "pada.global_batch_size=8",
        "pada.per_device_batch_size=8", "pada.max_completion_length=8", "pada.save_steps=100",
        "pada.gradient_checkpointing=false", "eval.max_new_tokens=8"]
LORA_NAMES = {"q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj"}


def _vision(state: dict) -> dict:
    return {k: v for k, v in state.items() if ".visual." in f".{k}"}


@pytest.fixture(scope="module")
def qwen3_vl_run(qwen3_vl_checkpoint, tmp_path_factory):
    """SFT, anchors and PADA on the tiny Qwen3-VL by the CLI; the token ids the model's embedding saw
    in every forward that builds a graph (training, not generation). A 2-step SFT model writes
    nothing that parses, so PADA pulls toward anchors made from the reference completions (the
    anchors stage itself runs on the model's own output)."""
    out = tmp_path_factory.mktemp("qwen3_vl_run")
    args = ["--config", "qwen3_vl_8b", f"model.path={qwen3_vl_checkpoint}", f"output_dir={out}", *TINY]
    seen: list[torch.Tensor] = []
    vocab = len(AutoTokenizer.from_pretrained(str(qwen3_vl_checkpoint)))
    forward = torch.nn.Embedding.forward

    def recording(self, ids):
        if self.num_embeddings == vocab and torch.is_grad_enabled():
            seen.append(ids.detach().cpu())
        return forward(self, ids)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny matmuls on shared cores: threads only contend
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch.nn.Embedding, "forward", recording)
        assert main(["train", "sft", *args]) == 0
        sft_seen = len(seen)
        assert main(["train", "anchors", *args]) == 0
        rows = [dict(r, anchor=r["completion"], anchor_raw=r["completion"])
                for r in load_records(str(out / "anchors.jsonl"))]
        write_records(rows, out / "anchors_ref.jsonl")
        anchors = f"pada.anchors={out / 'anchors_ref.jsonl'}"
        assert main(["train", "pada", "--variant", "pada", *args, anchors]) == 0
    torch.set_num_threads(threads)
    return {"out": out, "args": args, "sft_seen": seen[:sft_seen], "pada_seen": seen[sft_seen:]}


def test_qwen3_vl_checkpoint_is_the_image_text_class_with_chatml(qwen3_vl_checkpoint):
    config = json.loads((qwen3_vl_checkpoint / "config.json").read_text())
    assert config["model_type"] == "qwen3_vl"
    assert config["architectures"] == ["Qwen3VLForConditionalGeneration"]
    text, vision = config["text_config"], config["vision_config"]
    assert (text["hidden_size"], text["num_hidden_layers"], text["num_attention_heads"],
            text["num_key_value_heads"], text["head_dim"]) == (64, 2, 4, 2, 16)
    assert vision["depth"] == 2 and all(0 <= i < vision["depth"] for i in vision["deepstack_visual_indexes"])
    processor = json.loads((qwen3_vl_checkpoint / "processor_config.json").read_text())
    assert processor["processor_class"] == "Qwen3VLProcessor"
    image = json.loads((qwen3_vl_checkpoint / "preprocessor_config.json").read_text())
    assert (image["patch_size"], image["merge_size"]) == (16, 2)
    tok = AutoTokenizer.from_pretrained(str(qwen3_vl_checkpoint))
    chat = tok.apply_chat_template([{"role": "user", "content": "a desk"}], tokenize=False,
                                   add_generation_prompt=True)
    assert chat == "<|im_start|>user\na desk<|im_end|>\n<|im_start|>assistant\n"
    assert tok.eos_token == "<|im_end|>" and tok.pad_token == "<|endoftext|>"


def test_qwen3_vl_sft_full_fine_tune_leaves_the_vision_tower_unchanged(qwen3_vl_checkpoint, qwen3_vl_run):
    sft = qwen3_vl_run["out"] / "sft"
    base = load_file(str(qwen3_vl_checkpoint / "model.safetensors"))
    tuned = load_file(str(sft / "model.safetensors"))
    assert set(base) == set(tuned)
    vision = _vision(base)
    assert len(vision) > 20 and all(torch.equal(v, tuned[k]) for k, v in vision.items())
    # full fine-tune: every language-model weight moved (2 optimizer steps, lr 1e-5)
    moved = [k for k in base if k not in vision and not torch.equal(base[k], tuned[k])]
    assert any(".language_model.layers.0.self_attn.q_proj" in k for k in moved) and "lm_head.weight" in moved
    info = json.loads((sft / "physcene_run.json").read_text())
    assert info["chat_format"] is True and info["steps"] == 2 and info["stage"] == "sft"


def test_qwen3_vl_prompts_go_through_the_chat_template(qwen3_vl_checkpoint, qwen3_vl_run):
    tok = AutoTokenizer.from_pretrained(str(qwen3_vl_checkpoint))
    start, end = tok.convert_tokens_to_ids("<|im_start|>"), tok.convert_tokens_to_ids("<|im_end|>")
    for stage in ("sft_seen", "pada_seen"):
        batches = qwen3_vl_run[stage]
        assert batches, stage
        # every row opens a user turn and an assistant turn: two <|im_start|> per row
        assert all(((ids == start).sum(dim=1) >= 2).all() for ids in batches), stage
    # SFT rows hold the whole conversation: the assistant turn closes with <|im_end|>
    assert all(((ids == end).sum(dim=1) >= 1).all() for ids in qwen3_vl_run["sft_seen"])
    for stage in ("sft", "pada"):
        info = json.loads((qwen3_vl_run["out"] / stage / "physcene_run.json").read_text())
        assert info["chat_format"] is True


def test_qwen3_vl_pada_lora_wraps_only_the_language_model(qwen3_vl_checkpoint, qwen3_vl_run):
    from peft import get_peft_model
    from peft.tuners.lora import LoraLayer

    from physcene.commands.train import training_config
    from physcene.train.generate import load_for_generation
    from physcene.train.models import load_model
    from physcene.train.sft import lora_config

    pada = qwen3_vl_run["out"] / "pada"
    adapter = json.loads((pada / "adapter_config.json").read_text())
    assert (adapter["r"], adapter["lora_alpha"]) == (16, 32)
    step = [e for e in json.loads((pada / "train_log.json").read_text()) if "reward" in e][0]
    assert step["anchor_ce"] > 0 and {"time/generate_s", "time/reward_s", "kl"} <= set(step)
    # the saved adapter: A and B of the 7 projections in both decoder layers, nothing else
    weights = load_file(str(pada / "adapter_model.safetensors"))
    wrapped = {re.sub(r"\.lora_[AB]\.weight$", "", k) for k in weights}
    assert len(weights) == 2 * len(wrapped) == 2 * 2 * len(LORA_NAMES)
    assert all(".language_model.layers." in k for k in wrapped)
    assert {k.rsplit(".", 1)[1] for k in wrapped} == LORA_NAMES
    # the same config on the base model, module by module: LoRA layers in the language model only
    cfg = training_config("qwen3_vl_8b", qwen3_vl_run["args"][2:])
    peft_model = get_peft_model(load_model(qwen3_vl_checkpoint, dtype="float32"), lora_config(cfg.pada.lora))
    lora = [n for n, m in peft_model.named_modules() if isinstance(m, LoraLayer)]
    assert len(lora) == 14 and all(".language_model." in n and ".visual." not in n for n in lora)
    # and PADA, merged for generation, still has the base model's vision tower bit for bit
    merged, _, info = load_for_generation(pada, device="cpu")
    base = _vision(load_file(str(qwen3_vl_checkpoint / "model.safetensors")))
    state = _vision(merged.state_dict())
    assert set(state) == set(base) and all(torch.equal(v, base[k]) for k, v in state.items())
    assert info["chat_format"] is True and info["variant"] == "pada"


def test_qwen3_vl_eval_and_generate_parse_and_reward_the_completions(qwen3_vl_run, tmp_path):
    from physcene.data import synthesize
    from physcene.reward import PhysicsReward, RewardConfig

    pada = qwen3_vl_run["out"] / "pada"
    assert main(["eval", "--generator", f"model:{pada}", "--n", "1", "--out", str(tmp_path / "eval"),
                 "--quiet", "render=0", "max_new_tokens=8"]) == 0
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert "Model (pada)" in json.dumps(results)
    code = main(["generate", "a desk with a laptop and a mug", "--generator", f"model:{pada}", "--n", "2",
                 "--max-new-tokens", "8", "--no-render", "--quiet", "-o", str(tmp_path / "gen")])
    assert code in (0, 1)  # 1: some sample did not parse (an 8-token completion cannot)
    summary = json.loads((tmp_path / "gen" / "generate.json").read_text())
    # an 8-token completion cannot parse: each sample keeps the model's reply and the parse error
    assert len(summary["samples"]) == 2 and all(s["error"] for s in summary["samples"])
    texts = [Path(s["files"]["reply"]).read_text() for s in summary["samples"]]
    # the reward scores model output that does not parse as -100, a parsing layout as a number >= -50
    reference = next(iter(synthesize("test", 1, seed=0)))["completion"]
    rewards = PhysicsReward(RewardConfig(device="cpu")).score([*texts, reference]).rewards.tolist()
    assert all(isinstance(r, float) for r in rewards)
    assert rewards[:2] == [-100.0, -100.0] and -50.0 <= rewards[2] <= 50.0


def test_qwen3_vl_lora_targets_skip_a_vision_tower_whose_layers_share_the_names():
    """Qwen2.5-VL's vision MLP names its layers gate_proj / up_proj / down_proj like the decoder's: a
    suffix list would wrap both; the targets of ``lora_config`` wrap the language model's only."""
    from omegaconf import OmegaConf
    from peft import inject_adapter_in_model
    from peft.tuners.lora import LoraLayer

    from physcene.train.models import TrainingSetupError, language_model_targets
    from physcene.train.sft import lora_config

    def block():
        return torch.nn.ModuleDict({"mlp": torch.nn.ModuleDict(
            {n: torch.nn.Linear(4, 4) for n in ("gate_proj", "up_proj", "down_proj")})})

    model = torch.nn.Module()
    model.model = torch.nn.Module()
    model.model.visual = torch.nn.ModuleDict({"blocks": torch.nn.ModuleList([block()])})
    model.model.language_model = torch.nn.ModuleDict({"layers": torch.nn.ModuleList([block(), block()])})
    lora = OmegaConf.create({"r": 16, "alpha": 32, "dropout": 0.0,
                             "target_modules": ["gate_proj", "down_proj"]})
    wrapped = [n for n, m in inject_adapter_in_model(lora_config(lora), model).named_modules()
               if isinstance(m, LoraLayer)]
    assert sorted(n.split("model.", 1)[1] for n in wrapped) == [
        f"language_model.layers.{i}.mlp.{name}" for i in (0, 1) for name in ("down_proj", "gate_proj")]
    assert not re.fullmatch(language_model_targets(["q_proj"]), "vision_tower.layers.0.q_proj")
    with pytest.raises(TrainingSetupError, match="lora.target_modules"):
        language_model_targets(["q_proj|.*"])
