"""Unit tests of the training harness: tokenizer, PADA loss, PADA* mask, GRPO variant, adaptive KL, resume."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch
from datasets import Dataset
from peft import LoraConfig
from transformers import TrainerCallback

from physcene.config import load_config
from physcene.train.constrained_rollouts import mask_overruled
from physcene.train.decode import text_model
from physcene.train.decode.fuse import decoder_layers
from physcene.train.models import build_scratch_model, count_parameters
from physcene.train.pada import (
    AdaptiveKLCallback,
    PADAConfig,
    PADATrainer,
    numeric_spans,
    pada_arguments,
    tokenize_anchor,
)
from physcene.train.sft import SHARD_BYTES, TrainingSetupError, accumulation_steps, shard_weights
from physcene.train.tokenizer import build_tokenizer

ANCHOR = ('**Sub-instruction:**\n1. Place pen_0 in holder_1.\n\n**Scene Layout:**\n{"objects": [\n'
          '{"layer": 1, "instance_id": "holder_1", "parent_id": "root_zone", "relation_type": "near", '
          '"relative_bbox": [12.5, 20.25, -3.0, 4.0, 0.0, 11.0], "relative_rotation_deg": -45.5},\n'
          '{"layer": 2, "instance_id": "pen_0", "parent_id": "holder_1", "relation_type": "in", '
          '"relative_bbox": [1.0, 2.0, 1.0, 2.0, 1.0, 14.0], "relative_rotation_deg": 0.0}],\n'
          '"item_placement_zone": [0.0, 80.5, 0.0, 41.9]}\n')


@pytest.fixture(autouse=True)
def one_thread():
    # Two busy shared cores: more torch threads than free cores makes tiny matmuls ~20x slower.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def tokenizer():
    texts = [ANCHOR] * 20 + ["Instruction: place a pen in the holder.\nLayout:"] * 5
    return build_tokenizer(texts, vocab_size=320)


def test_tokenizer_splits_numbers_into_digits_and_signs(tokenizer):
    ids = tokenizer("[-12.75, 3.5e2]", add_special_tokens=False)["input_ids"]
    pieces = [tokenizer.decode([i]) for i in ids]
    assert pieces[:7] == ["[", "-", "1", "2", ".", "7", "5"]
    assert all(len(p.strip()) <= 1 for p in pieces if any(c.isdigit() for c in p))
    text = "Über 1000 cm — ✓ 😀 {\"a\": -0.001}"
    assert tokenizer.decode(tokenizer(text, add_special_tokens=False)["input_ids"]) == text


def test_numeric_spans_cover_only_geometry_values():
    spans = numeric_spans(ANCHOR)
    values = [ANCHOR[a:b] for a, b in spans]
    assert values == ["12.5", "20.25", "-3.0", "4.0", "0.0", "11.0", "-45.5",
                      "1.0", "2.0", "1.0", "2.0", "1.0", "14.0", "0.0"]


def test_pada_star_mask_drops_geometry_numbers_only(tokenizer):
    ids, full = tokenize_anchor(tokenizer, ANCHOR, max_length=10_000)
    ids_m, mask = tokenize_anchor(tokenizer, ANCHOR, max_length=10_000, numeric_mask=True)
    assert ids == ids_m and all(full) and ids[-1] == tokenizer.eos_token_id and mask[-1] == 1
    masked = "".join(tokenizer.decode([i]) for i, m in zip(ids, mask) if m == 0)
    assert set(masked) <= set("0123456789.-") and masked.count(".") == 14
    kept = tokenizer.decode([i for i, m in zip(ids, mask) if m == 1])
    # Semantic numbers stay supervised: instance ids, layers, the zone.
    assert "pen_0" in kept and '"layer": 2' in kept and "[0.0, 80.5, 0.0, 41.9]" in kept
    assert "12.5" not in kept and "-45.5" not in kept
    assert tokenize_anchor(tokenizer, "", max_length=8) == ([], [])


def _trainer(tokenizer, tmp_path, alpha: float, beta: float = 0.0) -> PADATrainer:
    torch.manual_seed(0)
    arch = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                num_key_value_heads=1, head_dim=16, max_position_embeddings=512)
    model = build_scratch_model(arch, tokenizer)
    args = PADAConfig(output_dir=str(tmp_path), anchor_alpha=alpha, beta=beta, num_generations=2,
                      per_device_train_batch_size=4, max_completion_length=16, use_cpu=True, report_to="none",
                      logging_steps=1)
    dataset = Dataset.from_list([{"prompt": "Instruction: place a pen.", "anchor": ANCHOR}] * 4)
    return PADATrainer(model, reward_funcs=[lambda prompts, completions, **kw: [0.0] * len(prompts)],
                       args=args, train_dataset=dataset, processing_class=tokenizer)


def _controlled_batch(tokenizer, numeric_mask: bool = False) -> dict:
    g = torch.Generator().manual_seed(1)
    vocab = len(tokenizer)
    pad = tokenizer.pad_token_id
    prompt_ids = torch.randint(2, vocab, (4, 6), generator=g)
    prompt_mask = torch.ones(4, 6, dtype=torch.long)
    prompt_ids[0, :2], prompt_mask[0, :2] = pad, 0  # left padding
    completion_ids = torch.randint(2, vocab, (4, 5), generator=g)
    completion_mask = torch.ones(4, 5, dtype=torch.long)
    completion_mask[1, 3:] = 0
    rows = [tokenize_anchor(tokenizer, ANCHOR[:80 + 30 * k], max_length=40, numeric_mask=numeric_mask)
            for k in range(4)]
    width = max(len(i) for i, _ in rows)
    return {
        "prompt_ids": prompt_ids, "prompt_mask": prompt_mask,
        "completion_ids": completion_ids, "completion_mask": completion_mask,
        "advantages": torch.tensor([1.0, -1.0, 0.5, -0.5]),
        "num_items_in_batch": completion_mask.sum(),
        "anchor_ids": torch.tensor([i + [pad] * (width - len(i)) for i, _ in rows]),
        "anchor_attention_mask": torch.tensor([[1] * len(i) + [0] * (width - len(i)) for i, _ in rows]),
        "anchor_loss_mask": torch.tensor([m + [0] * (width - len(m)) for _, m in rows]),
    }


def _manual_ce(model, batch) -> torch.Tensor:
    """Token NLL of the anchors from plain logits (independent of TRL's fused log-prob path)."""
    ids = torch.cat([batch["prompt_ids"], batch["anchor_ids"]], 1)
    attn = torch.cat([batch["prompt_mask"], batch["anchor_attention_mask"]], 1)
    logits = model(input_ids=ids, attention_mask=attn).logits[:, :-1]
    logp = torch.log_softmax(logits.float(), -1).gather(-1, ids[:, 1:, None])[..., 0]
    t = batch["anchor_ids"].shape[1]
    logp, mask = logp[:, -t:], batch["anchor_loss_mask"].float()
    return -(logp * mask).sum() / mask.sum()


@pytest.mark.parametrize("numeric_mask", [False, True])
def test_pada_loss_is_grpo_loss_plus_alpha_ce(tokenizer, tmp_path, numeric_mask):
    trainer = _trainer(tokenizer, tmp_path, alpha=0.1)
    model = trainer.model.eval()  # eval mode: no dropout, accumulation normaliser 1
    batch = _controlled_batch(tokenizer, numeric_mask)
    with torch.no_grad():
        pada = trainer._compute_loss(model, batch)
        grpo = super(PADATrainer, trainer)._compute_loss(model, batch)
        ce = _manual_ce(model, batch)
    assert ce.item() > 1.0  # an untrained model: the anchor term is far from zero
    assert pada.item() == pytest.approx(grpo.item() + 0.1 * ce.item(), rel=1e-5, abs=1e-6)
    assert trainer._metrics["eval"]["anchor_ce"][-1] == pytest.approx(ce.item(), rel=1e-5)


def test_pada_anchor_term_has_gradient(tokenizer, tmp_path):
    trainer = _trainer(tokenizer, tmp_path, alpha=0.1)
    model = trainer.model.eval()
    batch = _controlled_batch(tokenizer)
    batch["advantages"] = torch.zeros(4)  # GRPO term has no gradient: all of it is the anchor's
    trainer._compute_loss(model, batch).backward()
    grad = model.get_input_embeddings().weight.grad
    assert grad is not None and grad.abs().sum() > 0


@pytest.mark.parametrize("wider", ["anchors", "completions"])
def test_the_joint_anchor_pass_gives_the_same_loss_and_gradient_in_one_forward(tokenizer, tmp_path, wider):
    batch = _controlled_batch(tokenizer)
    batch["anchor_loss_mask"][1] = 0  # a prompt's repeated completion: no anchor row of its own
    if wider == "completions":  # completions past the anchors' width: the anchors are the padded part
        g = torch.Generator().manual_seed(2)
        extra = torch.randint(2, len(tokenizer), (4, 48), generator=g)
        batch["completion_ids"] = torch.cat([batch["completion_ids"], extra], 1)
        ones = torch.ones(4, 48, dtype=torch.long)
        batch["completion_mask"] = torch.cat([batch["completion_mask"], ones], 1)
        batch["completion_mask"][1, 3:] = 0
        batch["num_items_in_batch"] = batch["completion_mask"].sum()
    assert (batch["completion_ids"].size(1) > batch["anchor_ids"].size(1)) == (wider == "completions")
    seen = {}
    for joint in (False, True):
        trainer = _trainer(tokenizer, tmp_path / str(joint), alpha=0.1)
        trainer.args.joint_anchor_pass = joint
        # no dropout; float64: in float32 TRL's fused LM head rounds the same rows differently in another
        # batch (up to ~2.5e-3 of a gradient's norm on this model), in float64 the two agree to ~1e-8
        model = trainer.model.eval().to(torch.float64)
        forwards = []
        hook = model.register_forward_hook(lambda *_, calls=forwards: calls.append(1))
        loss = trainer._compute_loss(model, {k: v.double() if v.is_floating_point() else v
                                             for k, v in batch.items()})
        hook.remove()
        loss.backward()
        grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
        seen[joint] = (loss.item(), grads, len(forwards), trainer._metrics["eval"]["anchor_ce"][-1])
    (loss0, grads0, forwards0, ce0), (loss1, grads1, forwards1, ce1) = seen[False], seen[True]
    assert (forwards0, forwards1) == (2, 1)
    assert ce1 == pytest.approx(ce0, rel=1e-9) and ce0 > 1.0
    assert loss1 == pytest.approx(loss0, rel=1e-9, abs=1e-12)
    assert grads0.keys() == grads1.keys() and grads0
    for name, grad in grads0.items():
        assert (grads1[name] - grad).norm() <= 1e-6 * grad.norm(), name


def _lora_trainer(tokenizer, tmp_path, bf16: bool = False, beta: float = 0.04, layers: int = 1,
                  **args) -> PADATrainer:
    """A PADA trainer of a scratch model of ``layers`` decoder layers (bf16 weights under bf16 mixed
    precision, else float32) with LoRA adapters and no LoRA dropout; ``args`` go to its
    :class:`PADAConfig`."""
    torch.manual_seed(0)
    arch = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=layers, num_attention_heads=2,
                num_key_value_heads=1, head_dim=16, max_position_embeddings=512)
    model = build_scratch_model(arch, tokenizer)
    config = PADAConfig(output_dir=str(tmp_path), anchor_alpha=0.1, beta=beta, num_generations=2,
                        per_device_train_batch_size=4, max_completion_length=8, use_cpu=True, bf16=bf16,
                        report_to="none", logging_steps=1, save_strategy="no", **args)
    dataset = Dataset.from_list([{"prompt": "Instruction: place a pen.", "anchor": ANCHOR}] * 4)
    lora = LoraConfig(r=4, lora_alpha=8, lora_dropout=0.0, target_modules=["q_proj", "v_proj", "gate_proj"])

    def reward(prompts, completions, **kw):
        return [float(len(c)) for c in completions]

    return PADATrainer(model.to(torch.bfloat16) if bf16 else model, reward_funcs=[reward], args=config,
                       train_dataset=dataset, processing_class=tokenizer, peft_config=lora)


def _mixed_precision_trainer(tokenizer, tmp_path, cast: bool, **args) -> PADATrainer:
    """A PADA trainer of a bf16 model with float32 LoRA adapters (PEFT's default) and no LoRA dropout,
    under bf16 mixed precision on the CPU (accelerate's CPU autocast)."""
    return _lora_trainer(tokenizer, tmp_path, bf16=True, beta=0.0, adapter_input_cast=cast, **args)


def _cast_flags(model) -> set[bool]:
    """PEFT's input-cast switch of every LoRA layer of ``model``."""
    return {m.cast_input_dtype_enabled for m in model.modules() if hasattr(m, "cast_input_dtype_enabled")}


def _adapter_input_dtypes(model) -> tuple[list, list]:
    """(hooks, the dtypes each LoRA A matrix reads in a forward with gradient: the loss's, not sampling's)."""
    seen, hooks = [], []
    for name, module in model.named_modules():
        if name.endswith("lora_A.default"):
            hooks.append(module.register_forward_pre_hook(
                lambda _, args: seen.append(args[0].dtype) if torch.is_grad_enabled() else None))
    return hooks, seen


def test_adapters_that_read_the_autocast_inputs_give_the_same_loss_and_gradient(tokenizer, tmp_path):
    batch = _controlled_batch(tokenizer)
    seen = {}
    for cast in (True, False):
        trainer = _mixed_precision_trainer(tokenizer, tmp_path / str(cast), cast)
        model = trainer.model.eval()
        hooks, dtypes = _adapter_input_dtypes(model)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss = trainer._compute_loss(model, batch)
        loss.backward()
        for hook in hooks:
            hook.remove()
        grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
        flags = _cast_flags(model)
        seen[cast] = (loss, grads, set(dtypes), flags)
    (loss0, grads0, dtypes0, flags0), (loss1, grads1, dtypes1, flags1) = seen[True], seen[False]
    # PEFT's cast: the adapters read float32; without it, the bf16 that autocast gives every matmul
    assert dtypes0 == {torch.float32} and dtypes1 == {torch.bfloat16}
    assert flags0 == flags1 == {True}  # the switch lives only for the loss's forwards
    assert torch.equal(loss0, loss1) and loss0.item() > 0.1
    assert grads0.keys() == grads1.keys() and any("lora_A" in n for n in grads0)
    assert all(g.dtype == torch.float32 for n, g in grads0.items() if "lora_" in n)
    for name, grad in grads0.items():
        assert torch.equal(grad, grads1[name]), name


def test_a_mixed_precision_pada_step_with_uncast_adapter_inputs_trains_as_with_the_cast(tokenizer, tmp_path):
    steps = {}
    for cast in (True, False):
        # TRL's default gradient checkpointing: the backward recomputes each layer's forward
        trainer = _mixed_precision_trainer(tokenizer, tmp_path / str(cast), cast, max_steps=1,
                                           learning_rate=1e-2, seed=3, gradient_checkpointing=True)
        before = {n: p.detach().clone() for n, p in trainer.model.named_parameters() if p.requires_grad}
        hooks, dtypes = _adapter_input_dtypes(trainer.model)
        trainer.train()
        for hook in hooks:
            hook.remove()
        after = {n: p.detach().clone() for n, p in trainer.model.named_parameters() if p.requires_grad}
        log = trainer.state.log_history[0]
        steps[cast] = (before, after, set(dtypes), log["loss"], log["grad_norm"], log["anchor_ce"])
    (before0, after0, dtypes0, *log0), (before1, after1, dtypes1, *log1) = steps[True], steps[False]
    assert dtypes0 == {torch.float32} and dtypes1 == {torch.bfloat16}  # the trainer's autocast was on
    assert log0 == log1 and log0[2] > 1.0
    assert all(torch.equal(before0[n], before1[n]) for n in before0)
    assert all(torch.equal(after0[n], after1[n]) for n in after0)
    assert sum(not torch.equal(before0[n], after0[n]) for n in before0) >= len(before0) // 2  # it trained
    assert _cast_flags(trainer.model) == {True}  # PEFT's cast is back for sampling and saving


def _counting_backend(name: str):
    """A torch.compile backend registered as ``name`` that counts the frames Dynamo captures and runs
    their graphs eagerly (Dynamo's capture, guards and dynamic shapes without AOTAutograd's trace, which
    triples this test's time: the slow whole-step test below runs aot_eager)."""
    from torch._dynamo.backends import registry
    from torch._dynamo.backends.registry import register_backend
    from torch._dynamo.testing import CompileCounterWithBackend

    counter = CompileCounterWithBackend("eager")
    for names in (registry._BACKENDS, getattr(registry, "_COMPILER_FNS", {})):  # a name registered before
        names.pop(name, None)
    register_backend(compiler_fn=counter, name=name)
    return counter


@pytest.mark.parametrize("scope", ["model", "layers"])
def test_the_compiled_update_passes_give_eager_loss_gradient_and_reference_at_any_length(tokenizer, tmp_path,
                                                                                        scope):
    """``compile_update`` with either ``compile_scope``: the reference log-probabilities, the loss and every
    gradient of eager's at two lengths, the second compiling nothing new; ``layers`` (a model of two
    layers) compiles one function for both layers and leaves no layer patched after a pass."""
    backend = f"physcene_test_update_counter_{scope}"
    counter = _counting_backend(backend)
    short = _controlled_batch(tokenizer)
    long = {k: v.clone() if torch.is_tensor(v) else v for k, v in short.items()}
    g = torch.Generator().manual_seed(2)
    long["completion_ids"] = torch.cat([long["completion_ids"], torch.randint(2, len(tokenizer), (4, 9),
                                                                              generator=g)], 1)
    long["completion_mask"] = torch.cat([long["completion_mask"], torch.ones(4, 9, dtype=torch.long)], 1)
    long["num_items_in_batch"] = long["completion_mask"].sum()
    seen, frames = {}, []
    for compiled in (False, True):
        trainer = _lora_trainer(tokenizer, tmp_path / str(compiled), compile_update=compiled,
                                compile_backend=backend, compile_scope=scope,
                                layers=2 if scope == "layers" else 1)
        model = trainer.model.eval()
        rows = []
        for batch in (short, long):
            ids = torch.cat([batch["prompt_ids"], batch["completion_ids"]], 1)
            mask = torch.cat([batch["prompt_mask"], batch["completion_mask"]], 1)
            with torch.no_grad(), model.disable_adapter():  # the reference model's pass, as TRL runs it
                ref, _, _ = trainer._get_per_token_logps_and_entropies(model, ids, mask,
                                                                       batch["completion_ids"].size(1))
            batch = dict(batch, ref_per_token_logps=ref)
            loss = trainer._compute_loss(model, batch)
            loss.backward()
            grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
            model.zero_grad(set_to_none=True)
            rows.append((ref, loss.detach(), grads))
            frames.append(counter.frame_count)
        seen[compiled] = (rows, set(trainer._compiled) == {id(model)})
        assert all("forward" not in vars(layer) for layer in decoder_layers(text_model(model)))
    # one compiled module, of the model itself; none where the layers are compiled instead
    assert (seen[False][1], seen[True][1]) == (False, scope == "model")
    # eager compiles nothing; the compiled passes compile at the first length (policy and reference:
    # the reference runs with the adapters switched off) and not again at the second
    assert frames[0] == frames[1] == 0 and frames[2] >= 2 and frames[3] == frames[2]
    if scope == "layers":  # one compiled function for both layers: fewer captures than a layer and state each
        assert frames[2] < 2 * 2
    for (ref0, loss0, grads0), (ref1, loss1, grads1) in zip(seen[False][0], seen[True][0]):
        torch.testing.assert_close(ref1, ref0, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(loss1, loss0, rtol=1e-5, atol=1e-7)
        assert grads0.keys() == grads1.keys() and any("lora_A" in n for n in grads0)
        for name, grad in grads0.items():
            assert (grads1[name] - grad).norm() <= 1e-5 * grad.norm() + 1e-9, name


class _GradientsBeforeTheStep(TrainerCallback):
    """Keeps every gradient as the optimizer is about to read it."""

    def __init__(self, model):
        self.model, self.grads = model, {}

    def on_pre_optimizer_step(self, args, state, control, **kwargs):
        self.grads = {n: p.grad.clone() for n, p in self.model.named_parameters() if p.grad is not None}


@pytest.mark.slow  # ~45 s on 2 cores: the compiles of a whole step's passes
@pytest.mark.parametrize("scope", ["model", "layers"])
def test_a_pada_step_with_compiled_update_passes_trains_as_eager(tokenizer, tmp_path, scope):
    steps = {}
    for compiled in (False, True):
        # gradient checkpointing off: the configs' setting
        trainer = _lora_trainer(tokenizer, tmp_path / str(compiled), compile_update=compiled,
                                compile_backend="aot_eager", compile_scope=scope, max_steps=1,
                                learning_rate=1e-2, seed=3, gradient_checkpointing=False)
        before = {n: p.detach().clone() for n, p in trainer.model.named_parameters() if p.requires_grad}
        kept = _GradientsBeforeTheStep(trainer.model)
        trainer.add_callback(kept)
        trainer.train()
        moved = sum(not torch.equal(before[n], p) for n, p in trainer.model.named_parameters() if n in before)
        log = trainer.state.log_history[0]
        steps[compiled] = (kept.grads, moved, [log[k] for k in ("loss", "grad_norm", "anchor_ce")],
                           len(trainer._compiled))
    (grads0, moved0, log0, n0), (grads1, moved1, log1, n1) = steps[False], steps[True]
    assert (n0, n1) == (0, scope == "model") and log0[2] > 1.0  # layers: no compiled module kept
    assert moved0 == moved1 >= len(grads0) // 2  # both trained
    # the same rollouts, loss and anchor CE; the compiled backward's gradients agree with eager's to
    # ~0.4 % of a LoRA B matrix's in a whole step (a group's GRPO terms cancel, so rounding shows)
    assert log1[0] == log0[0] and log1[2] == log0[2]
    assert log1[1] == pytest.approx(log0[1], rel=2e-3)
    assert grads0.keys() == grads1.keys() and any(g.norm() > 0 for g in grads0.values())
    for name, grad in grads0.items():
        assert (grads1[name] - grad).norm() <= 1e-2 * grad.norm(), name


def test_compile_update_is_read_from_the_yaml_and_its_backend_checked():
    cfg = load_config("train_tiny")
    assert pada_arguments(cfg, "pada").compile_update is False
    cfg.pada.compile_update = True
    args = pada_arguments(cfg, "pada")
    assert args.compile_update is True and args.compile_backend == "inductor"
    assert args.compile_scope == "model"
    cfg.pada.compile_scope = "layers"
    assert pada_arguments(cfg, "pada").compile_scope == "layers"
    cfg.pada.compile_scope = "blocks"
    with pytest.raises(ValueError, match="pada.compile_scope must be one of"):
        pada_arguments(cfg, "pada")
    cfg.pada.compile_scope = "model"
    cfg.pada.compile_backend = "no_such_backend"
    with pytest.raises(ValueError, match="pada.compile_backend must be one of"):
        pada_arguments(cfg, "pada")


def test_adapter_input_cast_is_read_from_the_yaml():
    cfg = load_config("train_tiny")
    assert pada_arguments(cfg, "pada").adapter_input_cast is True
    cfg.pada.adapter_input_cast = False
    assert pada_arguments(cfg, "pada").adapter_input_cast is False


def test_grpo_variant_has_alpha_zero_and_ignores_anchors(tokenizer, tmp_path):
    cfg = load_config("train_tiny")
    assert pada_arguments(cfg, "grpo").anchor_alpha == 0.0
    assert pada_arguments(cfg, "pada").anchor_alpha == pytest.approx(0.1)
    star = pada_arguments(cfg, "pada_star")
    assert star.anchor_column == "anchor_raw" and star.anchor_numeric_mask
    with pytest.raises(ValueError, match="unknown PADA variant"):
        pada_arguments(cfg, "ppo")
    trainer = _trainer(tokenizer, tmp_path, alpha=0.0)
    model = trainer.model.eval()
    batch = _controlled_batch(tokenizer)
    with torch.no_grad():
        assert trainer._compute_loss(model, batch).item() == super(PADATrainer, trainer)._compute_loss(
            model, batch).item()
    assert "anchor_ce" not in trainer._metrics["eval"]


def test_adaptive_kl_moves_beta_toward_target():
    # The callback reads and writes only the trainer's beta.
    trainer = SimpleNamespace(beta=0.04)
    kl = AdaptiveKLCallback(trainer, target=0.05, horizon=10, min_beta=0.01, max_beta=0.05)
    assert kl.update(1.0, 1) == pytest.approx(0.04 * 1.02)  # error clipped at +0.2, n/horizon = 0.1
    assert kl.update(0.0, 6) == pytest.approx(0.04 * 1.02 * 0.9)  # -0.2 over 5 steps
    for step in range(7, 200):
        kl.update(0.0, step)
    assert trainer.beta == pytest.approx(0.01)  # clamped at min_beta (> 0 keeps the reference model)
    with pytest.raises(ValueError, match="initial beta > 0"):
        AdaptiveKLCallback(SimpleNamespace(beta=0.0))


def test_adaptive_kl_logs_beta_and_a_resumed_run_goes_on_from_it():
    """β lands in the log entry of the KL that moved it (GRPOTrainer empties its metric buffers after
    each log, so a β put there is never written), and a resumed run starts from the last logged β."""
    from transformers import TrainerControl, TrainerState

    trainer = SimpleNamespace(beta=0.04)
    callback = AdaptiveKLCallback(trainer, target=0.05, horizon=10)
    state = TrainerState()
    for step, kl in ((1, 1.0), (2, 1.0)):
        state.global_step = step
        logs = {"kl": kl, "loss": 0.1}
        state.log_history.append({**logs, "step": step})  # what Trainer.log does before on_log
        callback.on_log(None, state, TrainerControl(), logs=logs)
    assert [e["beta"] for e in state.log_history] == pytest.approx([0.04 * 1.02, 0.04 * 1.02 ** 2])
    # resumed: a new trainer and callback with the configured β, the checkpoint's history and step
    resumed = SimpleNamespace(beta=0.04)
    again = AdaptiveKLCallback(resumed, target=0.05, horizon=10)
    again.on_train_begin(None, state, TrainerControl())
    assert resumed.beta == pytest.approx(0.04 * 1.02 ** 2)
    state.global_step = 3
    state.log_history.append({"kl": 1.0, "step": 3})
    again.on_log(None, state, TrainerControl(), logs={"kl": 1.0})
    assert state.log_history[-1]["beta"] == pytest.approx(0.04 * 1.02 ** 3)  # one step since step 2
    fresh = SimpleNamespace(beta=0.04)  # a run from step 0 keeps the configured β
    AdaptiveKLCallback(fresh).on_train_begin(None, TrainerState(), TrainerControl())
    assert fresh.beta == 0.04


def test_accumulation_steps_make_the_global_batch():
    assert accumulation_steps(64, 2, 8) == 4
    assert accumulation_steps(128, 16, 8) == 1
    with pytest.raises(TrainingSetupError, match="not a multiple"):
        accumulation_steps(64, 3, 2)


def configured_parameters(name: str) -> int:
    """Parameters of config ``name``'s model at its configured vocabulary (the trained tokenizer fills
    its vocab_size; a tiny one stands in and the embedding rows it lacks are counted)."""
    cfg = load_config(name)
    tok = build_tokenizer(["abc 123"] * 4, vocab_size=300)
    arch = dict(cfg.model.arch)
    model = build_scratch_model(arch, tok)
    return count_parameters(model) + (int(cfg.model.tokenizer.vocab_size) - len(tok)) * arch["hidden_size"]


def test_small_config_is_20_to_60m_params_and_fits_64mb():
    n = configured_parameters("train_small")
    assert 20e6 <= n <= 60e6 and n * 2 < 64e6
    assert n == 27_272_704


def test_medium_config_is_60_to_120m_params_and_saves_in_shards_that_travel():
    cfg = load_config("train_medium")
    n = configured_parameters("train_medium")
    assert 60e6 <= n <= 120e6 and n == 61_621_376
    assert cfg.model.tokenizer.kind == "ctrc" and cfg.model.dtype == "bfloat16"
    assert n * 2 > SHARD_BYTES  # so its final save is written in shards (shard_weights)


def test_a_checkpoint_over_the_shard_size_is_written_in_shards_that_load_the_same(tmp_path):
    from transformers import AutoModelForCausalLM

    tok = build_tokenizer(["abc 123 table mug"] * 4, vocab_size=300)
    model = build_scratch_model(dict(load_config("train_tiny").model.arch), tok, seed=3)
    model.save_pretrained(tmp_path / "one")
    size = (tmp_path / "one" / "model.safetensors").stat().st_size
    assert shard_weights(model, tmp_path / "one", max_bytes=2 * size) == ["model.safetensors"]  # small: kept
    names = shard_weights(model, tmp_path / "one", max_bytes=size // 3)
    assert len(names) >= 3 and not (tmp_path / "one" / "model.safetensors").exists()
    assert all((tmp_path / "one" / f).stat().st_size <= size // 3 for f in names)
    assert (tmp_path / "one" / "model.safetensors.index.json").is_file()
    loaded = AutoModelForCausalLM.from_pretrained(tmp_path / "one")
    for (name, a), (_, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), name
    with pytest.raises(FileNotFoundError, match="no weights"):
        shard_weights(model, tmp_path / "empty")


def test_sft_resumes_from_last_checkpoint(tmp_path, step_counter):
    from physcene.train.sft import run_sft

    records = [{"id": f"r{i}", "prompt": f"Instruction {i}: place a pen.\nLayout:", "completion": ANCHOR}
               for i in range(4)]
    data = tmp_path / "train.jsonl"
    data.write_text("".join(json.dumps(r) + "\n" for r in records))
    base = [f"data.train={data}", f"output_dir={tmp_path / 'run'}", "sft.global_batch_size=2",
            "sft.per_device_batch_size=2", "sft.save_steps=1", "sft.max_length=256"]

    first, second = step_counter(), step_counter()
    out = run_sft(load_config("train_tiny", [*base, "sft.max_steps=2"]), callbacks=[first])
    assert (first.begin, first.steps) == (0, 2) and (out / "checkpoint-2").is_dir()
    run_sft(load_config("train_tiny", [*base, "sft.max_steps=3"]), callbacks=[second])
    assert second.steps == 1  # resumed at step 2: only step 3 ran
    state = json.loads((out / "checkpoint-3" / "trainer_state.json").read_text())
    assert state["global_step"] == 3
    info = json.loads((out / "physcene_run.json").read_text())
    assert info["stage"] == "sft" and info["chat_format"] is False


def test_sft_stops_at_a_unix_time_and_the_rerun_goes_on(tmp_path, step_counter):
    """``sft.stop_at`` in the past: the run stops after its first step, saves a checkpoint and writes
    the final model (stopped by the budget); the same command without it resumes toward max_steps."""
    import time

    from physcene.train.sft import TimeBudget, run_sft, time_budget_callbacks

    records = [{"id": f"r{i}", "prompt": f"Instruction {i}: place a pen.\nLayout:", "completion": ANCHOR}
               for i in range(4)]
    data = tmp_path / "train.jsonl"
    data.write_text("".join(json.dumps(r) + "\n" for r in records))
    base = [f"data.train={data}", f"output_dir={tmp_path / 'run'}", "sft.global_batch_size=2",
            "sft.per_device_batch_size=2", "sft.save_steps=100", "sft.max_length=256", "sft.max_steps=3"]
    first, second = step_counter(), step_counter()
    out = run_sft(load_config("train_tiny", [*base, f"sft.stop_at={time.time() - 1:.0f}"]), callbacks=[first])
    assert first.steps == 1 and (out / "checkpoint-1").is_dir()
    assert json.loads((out / "physcene_run.json").read_text())["stopped_by_budget"] is True
    run_sft(load_config("train_tiny", base), callbacks=[second])
    assert second.steps == 2
    assert time_budget_callbacks(load_config("train_tiny").sft) == []
    (budget,) = time_budget_callbacks(load_config("train_tiny", ["sft.max_minutes=2", "sft.stop_at=5"]).sft)
    assert (budget.seconds, budget.stop_at) == (120.0, 5.0)
    with pytest.raises(ValueError, match="seconds or stop_at"):
        TimeBudget()


def test_sft_continues_an_earlier_scratch_checkpoint(tmp_path):
    """model.init_from: a second SFT run on new data starts from the first run's weights (fp32) and
    vocabulary, and saves in model.dtype like a scratch run."""
    from transformers import TrainerCallback

    from physcene.train.models import TrainingSetupError, load_model
    from physcene.train.sft import run_sft

    data = tmp_path / "train.jsonl"
    data.write_text("".join(json.dumps({"id": f"r{i}", "prompt": f"Instruction {i}: place a pen.\nLayout:",
                                        "completion": ANCHOR}) + "\n" for i in range(4)))
    base = [f"data.train={data}", "sft.global_batch_size=2", "sft.per_device_batch_size=2", "sft.max_steps=1",
            "sft.max_length=256", "model.dtype=bfloat16"]
    first = run_sft(load_config("train_tiny", [*base, f"output_dir={tmp_path / 'a'}"]))
    start = {k: v.float() for k, v in load_model(first, dtype="float32").state_dict().items()}

    class Start(TrainerCallback):
        def on_train_begin(self, args, state, control, model=None, **kw):
            # on the CPU: on a GPU machine the trainer has moved the model to cuda
            self.weights = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
            self.dtype = next(model.parameters()).dtype

    seen = Start()
    second = run_sft(load_config("train_tiny", [*base, f"output_dir={tmp_path / 'b'}",
                                                f"model.init_from={first}"]), callbacks=[seen])
    assert seen.dtype == torch.float32 and seen.weights.keys() == start.keys()
    assert all(torch.equal(seen.weights[k], start[k]) for k in start)
    assert (second / "tokenizer.json").read_text() == (first / "tokenizer.json").read_text()
    from safetensors import safe_open

    with safe_open(str(second / "model.safetensors"), "pt") as f:
        assert {f.get_tensor(k).dtype for k in f.keys()} == {torch.bfloat16}
    assert json.loads((second / "physcene_run.json").read_text())["init_from"] == str(first)
    with pytest.raises(TrainingSetupError, match="init_from"):
        run_sft(load_config("train_tiny", [*base, f"output_dir={tmp_path / 'c'}",
                                           f"model.init_from={tmp_path / 'missing'}"]))


def test_a_step_with_a_nan_gradient_is_dropped_not_applied(tmp_path, caplog):
    """SkipNonFiniteSteps: a NaN in one gradient at step 2 leaves the weights as step 1 wrote them
    (instead of NaN everywhere after clipping), step 3 trains again, the run info names step 2 and
    the warning names the tensor that held the NaN."""
    import logging

    from transformers import TrainerCallback

    from physcene.train.sft import run_sft

    data = tmp_path / "train.jsonl"
    data.write_text("".join(json.dumps({"id": f"r{i}", "prompt": f"Instruction {i}: place a pen.\nLayout:",
                                        "completion": ANCHOR}) + "\n" for i in range(4)))

    class PoisonStep2(TrainerCallback):  # runs before the guard (user callbacks come first)
        def on_pre_optimizer_step(self, args, state, control, model=None, **kw):
            if state.global_step + 1 == 2:
                next(p for p in model.parameters() if p.grad is not None).grad.view(-1)[0] = float("nan")

    class Weights(TrainerCallback):
        def __init__(self):
            self.after = {}

        def on_step_end(self, args, state, control, model=None, **kw):
            self.model = model
            self.after[state.global_step] = [p.detach().clone() for p in model.parameters()]

    seen = Weights()
    with caplog.at_level(logging.WARNING, logger="physcene.train.sft"):
        out = run_sft(load_config("train_tiny", [f"data.train={data}", f"output_dir={tmp_path / 'run'}",
                                                 "sft.global_batch_size=2", "sft.per_device_batch_size=2",
                                                 "sft.max_steps=3", "sft.max_length=256"]),
                      callbacks=[PoisonStep2(), seen])
    poisoned = next(n for n, p in seen.model.named_parameters() if p.requires_grad)
    assert "step 2: non-finite gradient in 1 of " in caplog.text and poisoned in caplog.text
    assert all(torch.isfinite(w).all() for w in seen.after[3])
    assert all(torch.equal(a, b) for a, b in zip(seen.after[1], seen.after[2]))
    assert not all(torch.equal(a, b) for a, b in zip(seen.after[2], seen.after[3]))
    assert json.loads((out / "physcene_run.json").read_text())["nonfinite_steps_dropped"] == [2]


def test_ablation_row_and_table_from_an_eval_report():
    from physcene.train.ablation import ablation_row, markdown_table

    report = {"summary": {"n": 4, "parse_errors": 1, "QPR": {7.0: 0.25, 8.0: 0.0},
                          "collision": {0.0: {"SCR": 0.5, "ACR": 0.125}, 1.0: {"SCR": 0.0, "ACR": 0.0}},
                          "judge": {"avg": 7.5}, "parse_error_kinds": [("truncated JSON at char #", 1)]}}
    row = ablation_row("pada", report)
    assert row == {"name": "pada", "scr": 0.5, "acr": 0.125, "qpr7": 0.25, "judge_avg": 7.5,
                   "parse_rate": 0.75, "n": 4, "parse_error_kinds": [["truncated JSON at char #", 1]]}
    nan = float("nan")
    empty = ablation_row("sft", {"summary": {"n": 2, "parse_errors": 2, "QPR": {7.0: 0.0},
                                             "collision": {0.0: {"SCR": nan, "ACR": nan}},
                                             "judge": {"avg": nan}}})
    assert empty["scr"] is None and empty["parse_rate"] == 0.0
    table = markdown_table([row, empty, {"name": "pada*", "skipped": "no anchors"}])
    assert "| pada | 0 | 0 | 50.0% | 12.5% | 25.0% / — / — | 7.50 | 75.0% | — | — | — | 4 |" in table
    assert "| sft | 0 | 0 | — |" in table
    assert "skipped: no anchors" in table
    # the eval harness's floating share of objects, where the report has it (NaN: nothing parsed)
    report["summary"]["floating"] = {"objects": 0.07, "scenes": 0.52}
    assert ablation_row("pada", report)["floating"] == 0.07
    assert "| 75.0% | 7.0% | — | — | 4 |" in markdown_table([ablation_row("pada", report)])
    empty_report = {"summary": {"n": 1, "parse_errors": 1, "QPR": {7.0: 0.0}, "judge": {"avg": nan},
                                "collision": {0.0: {"SCR": nan, "ACR": nan}},
                                "floating": {"objects": nan, "scenes": nan}}}
    assert ablation_row("sft", empty_report)["floating"] is None


def test_configs_carry_the_paper_hyperparameters(monkeypatch):
    from physcene.train.sft import sft_arguments

    cfg = load_config("train_qwen3_vl_8b", ["model.path=/models/qwen3-vl-8b"])
    assert sft_arguments(cfg).gradient_accumulation_steps == 32  # one process: 2 x 32 = 64
    monkeypatch.setattr("physcene.train.sft.world_size", lambda: 8)  # what WORLD_SIZE says on 8 GPUs
    sft = sft_arguments(cfg)
    assert (sft.learning_rate, sft.adam_beta1, sft.adam_beta2, sft.warmup_steps) == (1e-5, 0.9, 0.95, 0.03)
    assert sft.lr_scheduler_type == "cosine" and sft.num_train_epochs == 5 and sft.completion_only_loss
    assert sft.per_device_train_batch_size * sft.gradient_accumulation_steps * 8 == 64
    assert cfg.sft.lora is None and cfg.model.freeze_vision and cfg.model.chat_format
    monkeypatch.undo()
    assert sft_arguments(load_config("train_small", ["sft.dataset_num_proc=8"])).dataset_num_proc == 8
    assert sft_arguments(load_config("train_small")).dataset_num_proc is None
    for name in ("qwen3_vl_8b", "small"):
        c = load_config(f"train_{name}", ["model.path=/m"])
        pada = pada_arguments(c, "pada")
        assert (pada.learning_rate, pada.lr_scheduler_type, pada.num_train_epochs) == (5e-4, "constant", 1)
        assert (pada.num_generations, pada.beta, pada.anchor_alpha) == (4, 0.04, 0.1)
        assert int(c.pada.global_batch_size) == 128 and (c.pada.lora.r, c.pada.lora.alpha) == (16, 32)
        assert set(c.pada.lora.target_modules) == {"q_proj", "k_proj", "v_proj", "o_proj", "gate_proj",
                                                   "up_proj", "down_proj"}




def test_tokens_the_constraint_chose_leave_the_policy_loss(tokenizer, tmp_path):
    """pada.mask_overruled: the positions the CTRC constraint overruled join TRL's tool_mask, so the
    GRPO loss (and its token count) ignores them: changing such a token's advantage-weighted
    log-probability changes nothing, while the same change at a kept position does."""
    trainer = _trainer(tokenizer, tmp_path, alpha=0.0)
    trainer.beta = 0.1  # the KL term (against the given reference log-probs) reads every log-prob
    model = trainer.model.eval()
    batch = _controlled_batch(tokenizer)
    batch["ref_per_token_logps"] = -torch.rand(4, 5, generator=torch.Generator().manual_seed(2))
    mask_overruled(trainer, batch, [[1, 3], [], [0, 9], [4]])  # 9: past the completion, ignored
    expected = torch.ones(4, 5, dtype=torch.long)
    expected[0, 1] = expected[0, 3] = expected[2, 0] = expected[3, 4] = 0
    assert torch.equal(batch["tool_mask"], expected)
    assert int(batch["num_items_in_batch"]) == int((batch["completion_mask"] * expected).sum())
    assert trainer._metrics["train" if model.training else "eval"]["constraint/overruled_frac"][-1] == \
        pytest.approx(4 / int(batch["completion_mask"].sum()))

    def loss_with(ids):
        return float(trainer._compute_loss(model, dict(batch, completion_ids=ids)))

    with torch.no_grad():
        base = loss_with(batch["completion_ids"])
        last = batch["completion_ids"].clone()
        last[3, 4] = (last[3, 4] + 1) % len(tokenizer)  # an overruled last token: nothing reads it
        assert loss_with(last) == pytest.approx(base, abs=1e-7)
        kept = batch["completion_ids"].clone()
        kept[2, 4] = (kept[2, 4] + 1) % len(tokenizer)  # a kept last token of the same kind
        assert loss_with(kept) != pytest.approx(base, abs=1e-7)

def test_generation_rounds_map_to_trl_micro_steps():
    """pada.generation_batches counts optimizer steps per generation round; TRL counts micro-batches."""
    cfg = load_config("train_small", ["pada.global_batch_size=64", "pada.per_device_batch_size=16",
                                      "pada.generation_batches=4", "pada.num_iterations=2"])
    args = pada_arguments(cfg, "pada")
    assert args.gradient_accumulation_steps == 4 and args.steps_per_generation == 16
    assert args.generation_batch_size == 256 and args.num_iterations == 2
    assert pada_arguments(load_config("train_small"), "pada").steps_per_generation == 4  # TRL's default
    for key in ("generation_batches", "num_iterations"):
        with pytest.raises(ValueError, match=f"pada.{key} must be a positive integer"):
            pada_arguments(load_config("train_small", [f"pada.{key}=0"]), "pada")

@pytest.mark.cuda
def test_reward_function_on_the_rank_device_matches_cpu():
    from physcene.ctrc import completion_text
    from physcene.data.noisy import noisy_scenes
    from physcene.train.pada import PhysicsRewardFunction

    texts = [completion_text(s) for s in noisy_scenes(6, n_objects=6, seed=3)] + ["not a layout"]
    logged = {}
    gpu = PhysicsRewardFunction("cuda:0")(None, texts, log_metric=logged.__setitem__)
    cpu = PhysicsRewardFunction("cpu")(None, texts)
    assert gpu == pytest.approx(cpu, rel=1e-4, abs=1e-4) and gpu[-1] == -100.0
    assert logged["parse_rate"] == pytest.approx(6 / 7) and logged["penetration_mm"] >= 0


def test_completion_length_tells_truncated_rows_from_finished_ones():
    from physcene.train.anchors import completion_length

    class Tok:
        eos_token_id = 7

    assert completion_length([3, 4, 7, 0, 0], Tok()) == (3, False)  # EOS then padding
    assert completion_length([3, 4, 5], Tok()) == (3, True)         # cut at max_new_tokens


def test_anchors_are_made_only_for_the_levels_pada_trains_on(tmp_path):
    from physcene.data import synthesize
    from physcene.train.anchors import anchor_prompts
    from physcene.train.records import write_records

    records = list(synthesize("train", 60, seed=4))
    assert {1, 2} <= {r["level"] for r in records} and max(r["level"] for r in records) > 2
    write_records(records, tmp_path / "train.jsonl")
    base = [f"data.train={tmp_path / 'train.jsonl'}", "anchors.n_records=5"]
    every = anchor_prompts(load_config("train_tiny", base))
    assert [r["id"] for r in every] == [r["id"] for r in records[:5]]
    low = anchor_prompts(load_config("train_tiny", [*base, "pada.max_level=2"]))  # anchors.max_level follows
    assert len(low) == 5 and all(r["level"] <= 2 for r in low)
    assert [r["id"] for r in low] == [r["id"] for r in records if r["level"] <= 2][:5]
    both = anchor_prompts(load_config("train_tiny", [*base, "pada.max_level=2", "data.max_level=1"]))
    assert both and all(r["level"] == 1 for r in both)  # the tighter of the two
    unfiltered = load_config("train_tiny", [*base, "pada.max_level=2", "anchors.max_level=null"])
    assert anchor_prompts(unfiltered) == every


def test_a_complete_anchor_file_needs_no_training_data(tmp_path):
    """run_anchors keeps an anchor file holding anchors.n_records rows even where data.train is absent
    (the RL and eval stages on a machine that got only the SFT model and the anchors); a short file
    still needs the data to be completed."""
    from physcene.data import synthesize
    from physcene.train.anchors import run_anchors
    from physcene.train.records import write_records

    anchors = tmp_path / "anchors.jsonl"
    write_records([{**r, "anchor": r["completion"]} for r in synthesize("train", 3, seed=1)], anchors)
    cfg = [f"data.train={tmp_path / 'absent.jsonl'}", f"anchors.output={anchors}"]
    before = anchors.read_bytes()
    assert run_anchors(load_config("train_tiny", [*cfg, "anchors.n_records=3"])) == anchors
    assert anchors.read_bytes() == before
    with pytest.raises(FileNotFoundError, match="absent.jsonl"):
        run_anchors(load_config("train_tiny", [*cfg, "anchors.n_records=4"]))


def test_records_read_from_jsonl_and_gzipped_jsonl(tmp_path):
    import gzip

    from physcene.train.records import load_records, write_records

    rows = [{"id": f"r{k}", "level": 1 + k % 3, "prompt": f"p{k}", "completion": f"c{k}"} for k in range(5)]
    write_records(rows, tmp_path / "a.jsonl")
    with gzip.open(tmp_path / "a.jsonl.gz", "wt") as fh:
        fh.write((tmp_path / "a.jsonl").read_text())
    assert load_records(str(tmp_path / "a.jsonl")) == rows
    assert load_records(str(tmp_path / "a.jsonl.gz")) == rows
    assert load_records(str(tmp_path / "a.jsonl.gz"), max_level=1) == [r for r in rows if r["level"] == 1]
    # a .gz name is written gzipped (an anchor file named anchors.jsonl.gz was once written as plain text
    # and its reader stopped PADA with BadGzipFile)
    write_records(rows, tmp_path / "b.jsonl.gz")
    with gzip.open(tmp_path / "b.jsonl.gz", "rt") as fh:
        assert fh.read() == (tmp_path / "a.jsonl").read_text()
    assert load_records(str(tmp_path / "b.jsonl.gz")) == rows


@pytest.fixture
def cudnn_flag():
    old = torch.backends.cuda.cudnn_sdp_enabled()
    yield
    torch.backends.cuda.enable_cudnn_sdp(old)


def test_training_forbids_cudnn_attention_unless_the_config_allows_it(cudnn_flag):
    """``model.cudnn_attention``: off by default in every training config (torch 2.11's cuDNN attention
    backward NaNs on left-padded rows), on when asked."""
    from physcene.train.models import set_attention_kernels

    for name in ("train_tiny", "train_small", "train_qwen3_vl_8b"):
        torch.backends.cuda.enable_cudnn_sdp(True)
        assert set_attention_kernels(load_config(name).model) is False
        assert not torch.backends.cuda.cudnn_sdp_enabled()
    assert set_attention_kernels(load_config("train_tiny", ["model.cudnn_attention=true"]).model) is True
    assert torch.backends.cuda.cudnn_sdp_enabled()


@pytest.mark.cuda
@pytest.mark.parametrize("length", [704, 2240])  # 64 past a multiple of 128: where cuDNN's backward broke
def test_attention_gradient_over_left_padded_rows_is_finite_with_the_training_kernels(cudnn_flag, length):
    """The PADA anchor forward's shape: a causal batch whose first row is left-padded (its pad queries
    attend to nothing). Under the kernels training allows, the backward of SDPA stays finite."""
    import torch.nn.functional as F

    from physcene.train.models import set_attention_kernels

    set_attention_kernels({})
    gen = torch.Generator(device="cuda").manual_seed(0)
    q, k, v = (torch.randn(2, 4, length, 64, device="cuda", generator=gen).to(torch.bfloat16).requires_grad_()
               for _ in range(3))
    keep = torch.ones(2, length, dtype=torch.bool, device="cuda")
    keep[0, :31] = False  # row 0: 31 tokens of left padding
    causal = torch.ones(length, length, dtype=torch.bool, device="cuda").tril()
    mask = (causal[None] & keep[:, None, :])[:, None]  # (batch, 1, query, key)
    out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    (out.float() * keep[:, None, :, None]).sum().backward()  # the loss reads real tokens only
    assert all(bool(torch.isfinite(t.grad).all()) for t in (q, k, v))


def test_pada_config_checks_its_extension_fields_itself(tmp_path):
    """The checks live in PADAConfig.__post_init__, not only in the YAML mapping."""
    base = dict(output_dir=str(tmp_path), use_cpu=True, report_to="none")
    assert PADAConfig(**base).object_credit_terms == ["penetration"]
    bad = [("object_credit", -1.0, "pada.object_credit must be >= 0"),
           ("object_credit_scope", "box", "pada.object_credit_scope: object credit scope"),
           ("object_credit_terms", ["float"], "pada.object_credit_terms: object terms"),
           ("denoise_decimals", 9, "pada.denoise_decimals must be null or an integer"),
           ("num_iterations", 0, "pada.num_iterations must be a positive integer")]
    for field, value, message in bad:
        with pytest.raises(ValueError, match=message):
            PADAConfig(**base, **{field: value})


def test_an_extensions_logits_processor_reaches_generate_unpatched(tokenizer, tmp_path):
    """The CTRC constraint's way into TRL's generation: an extension's logits processor is passed to
    ``generate`` (``model.generate`` is never replaced), and the completions are TRL's own for the
    same seed when the processor leaves the scores as they are."""
    from transformers import LogitsProcessor

    from physcene.train.extension import PADAExtension

    class Identity(LogitsProcessor):
        calls = 0

        def __call__(self, input_ids, scores):
            Identity.calls += 1
            return scores

    class Recording(PADAExtension):
        prompts, generated = None, 0

        def logits_processors(self, trainer, prompts):
            self.prompts = prompts
            return [Identity()]

        def after_generation(self, trainer):
            self.generated += 1
            assert "generate" not in vars(trainer.accelerator.unwrap_model(trainer.model_wrapped))

    trainer = _trainer(tokenizer, tmp_path, alpha=0.0)
    prompt_ids = [tokenizer("Instruction: place a pen.", add_special_tokens=False)["input_ids"],
                  tokenizer("Layout:", add_special_tokens=False)["input_ids"]]
    torch.manual_seed(3)
    plain, _ = trainer._generate_single_turn(prompt_ids, None, {}, 1)
    assert Identity.calls == 0  # no extension: TRL's own call
    trainer.extensions = [Recording()]
    trainer._round_prompts = ["Instruction: place a pen.", "Layout:"]
    torch.manual_seed(3)
    processed, _ = trainer._generate_single_turn(prompt_ids, None, {}, 1)
    assert Identity.calls > 0 and trainer.extensions[0].generated == 1
    assert trainer.extensions[0].prompts == trainer._round_prompts
    assert processed == plain and all(1 <= len(c) <= 16 for c in processed)


def test_micro_batches_cut_and_regroup_only_what_they_know():
    """``physcene.train.micro_batches``: a micro-batch is cut to the completion columns its rows use
    and the prompt columns some row uses; a per-row tensor of the completion's width it does not know
    leaves it uncut; regrouping keeps each step's rows, sorted by length, in equal micro-batches."""
    from physcene.train.micro_batches import grouped_by_length, trimmed

    mask = torch.tensor([[1, 1, 0, 0, 0], [1, 0, 0, 0, 0]])
    batch = {"prompt_ids": torch.tensor([[0, 0, 7], [0, 6, 7]]),
             "prompt_mask": torch.tensor([[0, 0, 1], [0, 1, 1]]),
             "completion_ids": torch.arange(10).view(2, 5), "completion_mask": mask,
             "ref_per_token_logps": torch.zeros(2, 5), "advantages": torch.tensor([1.0, -1.0]),
             "num_items_in_batch": torch.tensor(3), "anchor_ids": torch.zeros(2, 5, dtype=torch.long)}
    cut = trimmed(batch)
    assert cut["completion_ids"].tolist() == [[0, 1], [5, 6]] and cut["ref_per_token_logps"].shape == (2, 2)
    assert cut["prompt_ids"].tolist() == [[0, 7], [6, 7]] and cut["advantages"].shape == (2,)
    assert cut["anchor_ids"].shape == (2, 5)  # the anchors' own width
    assert trimmed({**batch, "unknown_per_token": torch.zeros(2, 5)})["completion_ids"].shape == (2, 5)
    long = {**batch, "completion_mask": torch.tensor([[1, 1, 1, 1, 1], [1, 1, 1, 0, 0]]),
            "advantages": torch.tensor([3.0, 2.0])}
    regrouped = grouped_by_length([batch, long], per_step=2)
    assert [b["completion_mask"].sum(1).tolist() for b in regrouped] == [[5, 3], [2, 1]]
    assert [b["advantages"].tolist() for b in regrouped] == [[3.0, 2.0], [1.0, -1.0]]
    assert int(regrouped[1]["num_items_in_batch"]) == 3
    assert grouped_by_length([batch, long, batch], per_step=2)[2] is batch  # not whole steps: unchanged
