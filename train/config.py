"""PADA's configuration: :class:`PADAConfig` (TRL's ``GRPOConfig`` plus the anchor term and the
extensions' settings, every check in ``__post_init__``) and :func:`pada_arguments`, which maps a
training YAML's ``pada:`` section onto it.

The paper's fields come first (α, the anchor column, the PADA* mask, β, G); the fields after them
configure the extensions, which are not in the paper and are off by default (one module each:
:mod:`physcene.train.constrained_rollouts`, :mod:`physcene.train.object_credit`,
:mod:`physcene.train.denoise`, :mod:`physcene.train.diagnostics`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import OmegaConf
from trl import GRPOConfig

from physcene.ctrc import MAX_DECIMALS
from physcene.reward import object_terms_checked, penetration_charge_checked
from physcene.train.decode import FAST_CACHES
from physcene.train.generate import check_cache
from physcene.train.sft import _precision, accumulation_steps, world_size
from physcene.train.targets import GEOMETRY_KEYS, object_credit_scope_checked

__all__ = ["SCALE_REWARDS", "VARIANTS", "PADAConfig", "pada_arguments", "reward_overrides"]

# variant -> (anchor column, numeric tokens masked out of the CE); grpo has no anchor (α = 0)
VARIANTS = {"pada": ("anchor", False), "pada_star": ("anchor_raw", True), "grpo": (None, False)}
# TRL's reward scaling of the advantages (GRPOConfig.scale_rewards): the std of each prompt's group (the
# paper's GRPO), of the whole generation batch, or none. With G = 4 and few clean rollouts per group,
# group scaling spends ~70 % of the advantage mass ranking colliding rollouts by depth; batch ~1.4 %.
SCALE_REWARDS = ("group", "batch", "none")
# what pada.compile_update compiles: the whole forward, or each decoder layer's (regional compilation)
COMPILE_SCOPES = ("model", "layers")


@dataclass(kw_only=True)
class PADAConfig(GRPOConfig):
    """``GRPOConfig`` plus the anchor term. Defaults are the paper's (α = 0.1, β = 0.04, G = 4); the
    extension fields (after ``num_generations``) default to off."""

    # --- the paper (Sec. 3.3): GRPO + α · CE(anchor) ---
    anchor_alpha: float = field(default=0.1, metadata={"help": "Weight α of the anchor CE; 0 = GRPO."})
    anchor_column: str = field(default="anchor", metadata={"help": "Dataset column holding the anchor text."})
    anchor_numeric_mask: bool = field(
        default=False, metadata={"help": "PADA*: leave geometry numbers out of the anchor CE."})
    anchor_geometry_keys: list[str] = field(
        default_factory=lambda: list(GEOMETRY_KEYS),
        metadata={"help": "JSON keys whose numeric values the PADA* mask removes from the CE."})
    beta: float = field(default=0.04, metadata={"help": "Initial KL coefficient (AdaptiveKLCallback)."})
    num_generations: int | None = field(default=4, metadata={"help": "Group size G."})
    scale_rewards: str = field(
        default="group", metadata={"help": "Divide the advantages by the reward std of each group (group, "
                                           "the paper's GRPO), of the generation batch (batch) or not "
                                           "(none); TRL's GRPOConfig.scale_rewards."})

    # --- generation (how the groups are sampled; the objective is unchanged) ---
    generation_compile: bool = field(
        default=False, metadata={"help": "Compile the decoding forward of a static-cache generation "
                                         "(pada.cache=static_compile); TRL itself always disables it."})
    fast_decode: str | None = field(
        default=None, metadata={"help": "Generate the groups with the fast decoder at this setting "
                                        "(physcene.train.decode.FAST_CACHES: fast, fast+fused, ...: "
                                        "pada.cache; not with vLLM); None: HF generate."})
    merge_adapters: bool = field(
        default=False, metadata={"help": "Decode the groups (fast_decode) with each LoRA adapter merged "
                                         "into a copy of its projection's weight: one matmul per "
                                         "projection instead of three (physcene.train.decode.merge); the "
                                         "trained weights are not touched; not bitwise the unmerged "
                                         "policy."})
    constraint_workers: int = field(
        default=0, metadata={"help": "Worker processes that check the CTRC constraint's rows beside the fast "
                                     "decoder (physcene.train.decode.shards): the host check, not the GPU, "
                                     "paces a constrained round of 128 rows; the same tokens with any "
                                     "number; 0 = in the training process."})
    constrained_decoding: bool = field(
        default=False, metadata={"help": "Sample the groups under the CTRC constraint, passed to generate "
                                         "as a logits processor (physcene.train.constrained_rollouts; HF "
                                         "generate only, not vLLM)."})

    length_grouping: bool = field(
        default=True, metadata={"help": "Within each optimizer step, micro-batches of rows of similar "
                                        "completion length, each cut to the columns its rows use "
                                        "(physcene.train.micro_batches): the step's gradient is the same "
                                        "sum (loss_type dapo), the padding's compute is not spent."})

    joint_anchor_pass: bool = field(
        default=False, metadata={"help": "Score a micro-batch's anchor rows in the policy's forward (one "
                                         "forward and one backward instead of two each; the same loss and "
                                         "gradient): half the update's kernel launches, which bound it on "
                                         "a small model (docs/training.md)."})

    adapter_input_cast: bool = field(
        default=True, metadata={"help": "PEFT's cast of each LoRA adapter's input to the adapter's float32 "
                                        "weights (PEFT's default). Under bf16 mixed precision autocast casts "
                                        "it back to bf16 for the adapter's matmul, so False (the input as "
                                        "autocast gives it: peft.helpers.disable_input_dtype_casting over "
                                        "the loss's forwards) gives the same loss and gradient without LoRA "
                                        "dropout, at two casts fewer per adapted projection; it acts only "
                                        "under bf16/fp16 mixed precision (docs/training.md)."})

    compile_update: bool = field(
        default=False, metadata={"help": "Run the update's forwards (the policy's, the reference model's, "
                                         "the anchors') through torch.compile with dynamic shapes, so a "
                                         "micro-batch of another length does not compile again and the "
                                         "backward is compiled with its forward: far fewer kernel launches "
                                         "(docs/training.md). The first step pays the compile; the LoRA "
                                         "dropout draws other random numbers than eager."})
    compile_backend: str = field(
        default="inductor", metadata={"help": "torch.compile's backend for compile_update (inductor; "
                                              "aot_eager traces without generating kernels)."})
    compile_scope: str = field(
        default="model", metadata={"help": "What compile_update compiles: 'model' (the whole forward, one "
                                           "graph) or 'layers' (each decoder layer's forward, one compiled "
                                           "function shared by every layer: regional compilation, a "
                                           "layer's compile time instead of the model's)."})

    # --- extensions: not in the paper, each off by default ---
    mask_overruled: bool = field(
        default=True, metadata={"help": "Leave the tokens the CTRC constraint chose instead of the "
                                        "policy's draw out of the GRPO loss and KL (like tool output); "
                                        "acts only under constrained_decoding."})
    nonfinite_probe: int = field(
        default=0, metadata={"help": "Micro-batches whose backward leaves a non-finite gradient to take "
                                     "apart (physcene.train.diagnostics): which loss term, which rows, "
                                     "which attention kernel; 0 = off."})
    object_credit: float = field(
        default=0.0, metadata={"help": "Lower the advantage of the tokens of each object's plan step and "
                                       "layout line by this much per cm charged to it "
                                       "(physcene.train.object_credit); 0 = off."})
    object_credit_terms: list[str] = field(
        default_factory=lambda: ["penetration"],
        metadata={"help": "What object_credit charges each object with (cm), of "
                          "physcene.reward.OBJECT_TERMS: penetration (the paper's reward term), "
                          "floating (its support gap), out_of_zone (how far its footprint leaves the zone), "
                          "size (how far its size lies outside its category's band; reward.size_tolerance)."})
    object_credit_penetration: str = field(
        default="depth", metadata={"help": "How a penetrating pair charges its later-written object: depth "
                                           "(its depth, cm) or pairs (1 per pair: does not fall when the "
                                           "objects are written thinner)."})
    object_credit_scope: str = field(
        default="line", metadata={"help": "Which tokens of a charged object object_credit lowers: line (its "
                                          "plan step and layout line) or numbers (only the numbers of its "
                                          "relative_bbox and relative_rotation_deg)."})
    denoise: float = field(
        default=0.0, metadata={"help": "Weight of the cross-entropy toward each rollout's on-policy repair "
                                       "(physcene.train.denoise); a rewritten token weighs like a GRPO "
                                       "token of advantage `denoise`; 0 = off."})
    denoise_margin_cm: float = field(
        default=1.0, metadata={"help": "Clearance (cm) the denoising repair keeps around a blamed "
                                       "table-level object."})
    denoise_decimals: int | None = field(
        default=None, metadata={"help": "Digits after the point of the denoising targets' rewritten numbers "
                                        "(the training data's record.decimals); None: each rollout's usual "
                                        "precision (physcene.ctrc.usual_decimals)."})
    denoise_tto: list[str] = field(
        default_factory=lambda: ["lambda_zone=100.0"],
        metadata={"help": "configs/tto.yaml overrides for the denoising repair (key=value; the zone "
                          "weighed 10x, train/denoise.py); its device is the reward engine's."})

    @property
    def adapter_inputs_uncast(self) -> bool:
        """Whether the LoRA adapters read their inputs as autocast gives them: ``adapter_input_cast`` off,
        under bf16/fp16 mixed precision (without it there is nothing to leave uncast)."""
        return not self.adapter_input_cast and bool(self.bf16 or self.fp16)

    def __post_init__(self):
        # The messages name the YAML key (pada.<field>): the fields are the pada: section's keys.
        scale = {True: "group", False: "none"}.get(self.scale_rewards, self.scale_rewards)
        if scale not in SCALE_REWARDS:
            raise ValueError(f"pada.scale_rewards must be one of {list(SCALE_REWARDS)}, "
                             f"got {self.scale_rewards!r}")
        self.scale_rewards = scale
        g = self.num_generations
        if not (isinstance(g, int) and not isinstance(g, bool) and g >= 2):
            raise ValueError(f"pada.num_generations (the group size G) must be an integer >= 2, got {g!r}")
        if self.num_iterations < 1:
            raise ValueError(f"pada.num_iterations must be a positive integer, got {self.num_iterations}")
        if self.object_credit < 0:
            raise ValueError(f"pada.object_credit must be >= 0 (advantage per cm of penetration), "
                             f"got {self.object_credit}")
        if self.denoise < 0 or self.denoise_margin_cm < 0:
            raise ValueError(f"pada.denoise and pada.denoise_margin_cm must be >= 0, got {self.denoise}, "
                             f"{self.denoise_margin_cm}")
        decimals = self.denoise_decimals
        whole = isinstance(decimals, int) and not isinstance(decimals, bool)
        if decimals is not None and not (whole and 0 <= decimals <= MAX_DECIMALS):
            raise ValueError(f"pada.denoise_decimals must be null or an integer from 0 to {MAX_DECIMALS}, "
                             f"got {decimals!r}")
        if self.merge_adapters and self.fast_decode is None:
            raise ValueError("pada.merge_adapters merges the adapters for the fast decoder: set pada.cache "
                             f"to one of {sorted(FAST_CACHES)}, or pada.merge_adapters to false")
        workers = self.constraint_workers
        if not (isinstance(workers, int) and not isinstance(workers, bool) and workers >= 0):
            raise ValueError(f"pada.constraint_workers must be an integer >= 0, got {workers!r}")
        if self.compile_scope not in COMPILE_SCOPES:
            raise ValueError(f"pada.compile_scope must be one of {COMPILE_SCOPES}, "
                             f"got {self.compile_scope!r}")
        if self.compile_update:
            import torch

            backends = torch._dynamo.list_backends(exclude_tags=())
            if self.compile_backend not in backends:
                raise ValueError(f"pada.compile_backend must be one of torch.compile's backends {backends}, "
                                 f"got {self.compile_backend!r}")
        if self.nonfinite_probe < 0:
            raise ValueError(f"pada.nonfinite_probe must be >= 0, got {self.nonfinite_probe}")
        for key, check in (("object_credit_scope", object_credit_scope_checked),
                           ("object_credit_penetration", penetration_charge_checked)):
            try:
                check(getattr(self, key))
            except ValueError as exc:
                raise ValueError(f"pada.{key}: {exc}") from None
        try:
            self.object_credit_terms = list(object_terms_checked(self.object_credit_terms))
        except ValueError as exc:
            raise ValueError(f"pada.object_credit_terms: {exc}") from None
        self.denoise_tto = [str(x) for x in self.denoise_tto or []]
        try:
            super().__post_init__()
        except ValueError as exc:  # TRL's check that a generation round holds whole groups
            if "num_generations" not in str(exc):
                raise
            raise ValueError(f"pada.num_generations={g} must divide the completions of a generation round "
                             f"(pada.global_batch_size x pada.generation_batches): {exc}") from None


def _listed(value) -> list:
    """A YAML list (an omegaconf ListConfig) or a Python one as a plain list."""
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


def pada_arguments(cfg, variant: str) -> PADAConfig:
    """The :class:`PADAConfig` of ``cfg.pada`` for ``variant`` (paper stage 2 defaults in the configs)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown PADA variant {variant!r}; use one of {sorted(VARIANTS)}")
    p = cfg.pada
    column, numeric_mask = VARIANTS[variant]
    cache = check_cache(str(p.get("cache", "dynamic")))
    deepspeed = OmegaConf.to_container(p.deepspeed, resolve=True) if p.deepspeed is not None else None
    accumulation = accumulation_steps(int(p.global_batch_size), int(p.per_device_batch_size), world_size())
    generation_batches = int(p.get("generation_batches", 1))
    if generation_batches < 1:  # a YAML key only: it becomes TRL's steps_per_generation
        raise ValueError(f"pada.generation_batches must be a positive integer, got {generation_batches}")
    return PADAConfig(
        output_dir=str(p.output_dir),
        anchor_alpha=0.0 if column is None else float(p.alpha),
        anchor_column=column or "anchor",
        anchor_numeric_mask=numeric_mask,
        beta=float(p.beta),
        num_generations=int(p.num_generations),
        scale_rewards=str(p.get("scale_rewards", "group")),
        max_completion_length=int(p.max_completion_length),
        temperature=float(p.temperature),
        # TRL passes it to GenerationConfig (HF generate, use_vllm=False); None = HF's dynamic cache
        cache_implementation=None if cache == "dynamic" or cache in FAST_CACHES else "static",
        generation_compile=cache == "static_compile",
        fast_decode=cache if cache in FAST_CACHES else None,
        merge_adapters=bool(p.get("merge_adapters", False)),
        constraint_workers=int(p.get("constraint_workers", 0) or 0),
        length_grouping=bool(p.get("length_grouping", True)),
        joint_anchor_pass=bool(p.get("joint_anchor_pass", False)),
        adapter_input_cast=bool(p.get("adapter_input_cast", True)),
        compile_update=bool(p.get("compile_update", False)),
        compile_backend=str(p.get("compile_backend", "inductor")),
        compile_scope=str(p.get("compile_scope", "model")),
        constrained_decoding=bool(p.get("constrained", False)),
        mask_overruled=bool(p.get("mask_overruled", True)),
        nonfinite_probe=int(p.get("nonfinite_probe", 0) or 0),
        object_credit=float(p.get("object_credit", 0.0) or 0.0),
        object_credit_terms=_listed(p.get("object_credit_terms", ["penetration"])),
        object_credit_scope=str(p.get("object_credit_scope", "line")),
        object_credit_penetration=str(p.get("object_credit_penetration", "depth")),
        denoise=float(p.get("denoise", 0.0) or 0.0),
        denoise_margin_cm=float(p.get("denoise_margin_cm", 1.0)),
        denoise_tto=_listed(p.get("denoise_tto", ["lambda_zone=100.0"])) or [],
        denoise_decimals=p.get("denoise_decimals"),
        learning_rate=float(p.learning_rate),
        **_schedule(p),
        num_train_epochs=float(p.epochs),
        max_steps=int(p.max_steps),
        per_device_train_batch_size=int(p.per_device_batch_size),
        gradient_accumulation_steps=accumulation,
        # TRL counts steps_per_generation in micro-batches: one generation round feeds
        # `generation_batches` optimizer steps of global_batch_size completions each.
        steps_per_generation=accumulation * generation_batches,
        num_iterations=int(p.get("num_iterations", 1)),
        save_steps=int(p.save_steps),
        save_total_limit=None if p.get("save_total_limit", 2) is None else int(p.save_total_limit),
        logging_steps=int(p.logging_steps),
        report_to="none",
        seed=int(cfg.seed),
        deepspeed=deepspeed,
        dataloader_num_workers=0,
        # TRL turns it on by default; the tiny/small models have memory to spare and run faster without.
        gradient_checkpointing=bool(p.get("gradient_checkpointing", False)),
        # Two forwards (GRPO, anchor) feed one backward; every trainable (LoRA) weight is used by
        # both, so DDP needs no unused-parameter search, which would trip over the second forward.
        ddp_find_unused_parameters=False,
        **_precision(cfg),
    )


def _schedule(p) -> dict:
    """``pada.lr_scheduler_type`` and its arguments. ``pada.decay_steps: N`` holds the rate constant and
    takes it down a cosine to 0 over the last N of ``pada.max_steps`` (transformers'
    ``warmup_stable_decay``); a constant run resumed with it decays from where it stopped."""
    kind, decay = str(p.lr_scheduler_type), p.get("decay_steps")
    if decay is None:
        return {"lr_scheduler_type": kind}
    decay, steps = int(decay), int(p.max_steps)
    if kind != "constant":
        raise ValueError(f"pada.decay_steps={decay} decays a constant rate; "
                         f"got pada.lr_scheduler_type={kind!r}")
    if not 0 < decay <= steps:
        raise ValueError(f"pada.decay_steps={decay} must be in 1..pada.max_steps ({steps})")
    return {"lr_scheduler_type": "warmup_stable_decay", "lr_scheduler_kwargs": {"num_decay_steps": decay}}


def reward_overrides(cfg, variant: str) -> list[str]:
    """The configs/reward.yaml overrides of ``variant``'s reward: ``pada.reward``, then its entry of
    ``pada.variant_reward`` (e.g. the validity terms on for one variant, the paper's bare reward for
    another)."""
    per_variant = cfg.pada.get("variant_reward") or {}
    unknown = sorted(set(per_variant) - set(VARIANTS))
    if unknown:
        raise ValueError(f"pada.variant_reward: unknown variant(s) {unknown}; "
                         f"expected some of {sorted(VARIANTS)}")
    shared, own = _listed(cfg.pada.get("reward") or []), _listed(per_variant.get(variant) or [])
    return [str(o) for o in [*shared, *own]]
