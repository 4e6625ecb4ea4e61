"""The paper's physics reward as a TRL reward function (PADA's GRPO signal).

R = −100 if the completion does not parse; −min(0.01·E_pen, 50) if E_pen > 0; +50 if E_pen = 0,
with E_pen = Σ_{i<j} pen(i, j) in MILLIMETRES over pairs deeper than the tolerance (default 0).

``size_per_cm`` > 0 (NOT in the paper; 0 by default) also charges every object its size's distance
(cm) outside its category prior's band (:meth:`physcene.assets.SizePrior.outside_band_cm`), the total
still ≥ −max_penalty. A reward of penetration alone pays for flattening objects — a thin box cannot be
penetrated deeply — and a small policy finds that (docs/results.md, "Session 16 run").
``valid_terms`` (NOT in the paper; empty by default) pays a parsed layout that breaks one of them
``invalid`` whatever its penetration: ``floating`` (an object above its support) and ``shrunk`` (a
dimension far below its category's band). A collision-free reward pays for lifting and flattening
objects out of each other's way; 36 PADA steps did both (docs/results.md, "Session 18 run").

>>> reward = PhysicsReward(RewardConfig(device="cuda"))
>>> trainer = GRPOTrainer(..., reward_funcs=[reward])        # reward.last_metrics after each call

Each completion is parsed once, every parsed scene of the batch is scored in ONE engine call,
and unparsable completions never touch the engine. Canonical CTRC is read by the compiled
scanner (``PhysicsEngine.pack_texts``, config ``fast_parse``); :func:`physcene.ctrc.parse` reads
the rest and decides which completions are unparsable. The reward does not need the task's
zone (penetration does not change when a whole layout is translated); the per-object
``out_of_zone`` charge of PADA's ``object_credit`` reads it from the completion.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from physcene.assets import CATEGORY_PRIORS, canonical_category
from physcene.config import load_dataclass
from physcene.ctrc import ParseError, parse
from physcene.layout import category_from_instance
from physcene.scene import ZONE_TOLERANCE_CM, Scene

__all__ = ["OBJECT_TERMS", "PENETRATION_CHARGES", "VALID_TERMS", "PhysicsReward", "RewardConfig",
           "band_low_ratio", "completion_text_of", "penetration_charge_checked", "physics_reward",
           "prior_bands", "reward_from_energy", "size_outside_band_cm", "valid_terms_checked"]

# What an object can be charged with (cm) when PhysicsReward keeps per-object charges (PADA's
# object_credit): the penetration of the pairs it was written into, its support gap when it floats,
# how far its footprint leaves the zone, how far its size lies outside its category's band. Only the
# first is in the paper's reward.
OBJECT_TERMS = ("penetration", "floating", "out_of_zone", "size")
# How a penetrating pair charges its later-written object: its depth (cm), or 1 per pair. A depth charge
# falls with the objects' thickness (a flat box cannot be penetrated deeply), a pair count does not.
PENETRATION_CHARGES = ("depth", "pairs")
# What ``RewardConfig.valid_terms`` may ask of a layout before it is paid for its penetration.
VALID_TERMS = ("floating", "shrunk")


@dataclass(frozen=True, kw_only=True)
class RewardConfig:
    """Reward settings (``configs/reward.yaml``); lengths in mm as in the paper."""

    unparsable: float = -100.0
    """Reward of a completion that does not parse."""
    collision_free: float = 50.0
    """Reward when E_pen = 0."""
    per_mm: float = 0.01
    """Penalty per millimetre of summed pair depth."""
    max_penalty: float = 50.0
    """The penalty is capped here: R ≥ −max_penalty for any parsed layout."""
    tolerance_mm: float = 0.0
    """Only pairs deeper than this count in E_pen."""
    table_term: bool = False
    """Also add each object's depth below the table top (mm, deeper than the tolerance) to E_pen."""
    size_per_cm: float = 0.0
    """Penalty per cm that an object's size lies outside its category prior's band, summed over the
    layout's objects (0: the paper's reward). Not in the paper: it takes away what flattening objects
    wins from a penetration-only reward."""
    size_tolerance: float = 2.0
    """Half-width of that band, in prior spreads (log space): 2 leaves 8 % of the test references'
    objects outside it, by 0.12 cm on average."""
    valid_terms: tuple[str, ...] = ()
    """Not in the paper (empty: the paper's reward). A parsed layout that breaks one of these gets
    ``invalid``, whatever its penetration: ``floating``, an object more than the engine's
    ``floating_tolerance_cm`` above its support (the floating metric); ``shrunk``, an object with a
    dimension below ``shrink_ratio`` x the low edge of its category's size band at ``size_tolerance``
    (:meth:`physcene.assets.SizePrior.low_ratio`; a flattened box). Without it, lifting an object off
    its support or flattening it takes it out of a collision and earns the collision-free reward."""
    invalid: float = -50.0
    """Reward of a parsed layout that breaks a ``valid_terms`` term (the worst colliding layout's)."""
    shrink_ratio: float = 0.5
    """``shrunk``: a dimension below this fraction of its band's low edge (test references: 2 of 1,899
    objects; the SFT model's greedy outputs 23; after 36 PADA steps of the paper's reward 161)."""
    device: str = "cpu"
    """Engine device, ``cpu`` or ``cuda[:N]``."""
    fast_parse: bool = True
    """Read canonical CTRC completions with the compiled scanner (PhysicsEngine.pack_texts);
    the others, and every completion when False, with :func:`physcene.ctrc.parse`."""

    def __post_init__(self):
        object.__setattr__(self, "valid_terms", valid_terms_checked(self.valid_terms))

    @classmethod
    def load(cls, overrides: Sequence[str] = ()) -> RewardConfig:
        return load_dataclass(cls, "reward", overrides)


def completion_text_of(completion) -> str:
    """The text of a TRL completion: a string, or a chat list whose assistant turns are joined."""
    if isinstance(completion, str):
        return completion
    if isinstance(completion, dict):
        completion = [completion]
    parts = []
    for message in completion or []:
        if not isinstance(message, dict) or message.get("role", "assistant") != "assistant":
            continue
        content = message.get("content", "")
        if isinstance(content, list):  # multimodal parts: keep the text ones
            content = "".join(p.get("text", "") for p in content if isinstance(p, dict))
        parts.append(str(content))
    return "\n".join(parts)


def reward_from_energy(e_pen_mm: np.ndarray, config: RewardConfig) -> np.ndarray:
    """The paper's piecewise reward of E_pen (mm) for parsed layouts, (S,) float64."""
    e = np.asarray(e_pen_mm, dtype=np.float64)
    return np.where(e > 0, -np.minimum(config.per_mm * e, config.max_penalty), config.collision_free)


class PhysicsReward:
    """A TRL reward function ``f(prompts, completions, **columns) -> list[float]``.

    After every call ``last_metrics`` holds the batch's ``parse_failure_rate``,
    ``mean_energy_mm`` (over parsed layouts), ``collision_free_rate`` (over parsed layouts),
    ``mean_reward`` and ``mean_max_depth_mm``, for the trainer's log; with ``size_per_cm`` > 0 or the
    ``size`` object term, also ``mean_size_outside_cm`` (a parsed layout's summed
    :func:`size_outside_band_cm`: host work per object, so not measured otherwise).
    """

    __name__ = "physics_reward"  # TRL names reward columns after the function

    def __init__(self, config: RewardConfig | None = None, engine=None, *, object_depths: bool = False,
                 object_terms: Sequence[str] = ("penetration",), penetration_charge: str = "depth"):
        self.config = config or RewardConfig()
        self._engine = engine
        self.object_depths = object_depths
        """Also keep ``last_object_depths`` after each call (PADA's ``object_credit``)."""
        self.object_terms = object_terms_checked(object_terms)
        """What ``last_object_depths`` charges each object with (:data:`OBJECT_TERMS`)."""
        self.penetration_charge = penetration_charge_checked(penetration_charge)
        """``depth``: a penetrating pair charges its depth (cm); ``pairs``: 1 (PENETRATION_CHARGES)."""
        self.last_metrics: dict[str, float] = {}
        self.last_parse_errors: list[str | None] = []
        self.last_object_depths: list[np.ndarray | None] = []
        self.last_placement_depths: list[np.ndarray | None] = []
        """``last_object_depths`` less the ``size`` term: what moving the object can answer (PADA's
        ``denoise`` targets move objects; they do not resize them)."""

    @property
    def engine(self):
        if self._engine is None:
            from physcene.physics import PhysicsEngine

            self._engine = PhysicsEngine(device=self.config.device)
        return self._engine

    def __call__(self, prompts=None, completions=None, **columns) -> list[float]:
        if completions is None:
            raise ValueError("physics_reward needs completions")
        return self.score_texts([completion_text_of(c) for c in completions])

    def score_texts(self, texts: Sequence[str]) -> list[float]:
        """Rewards for completion texts, in order (one parse each, one engine call).

        With ``fast_parse`` the compiled scanner reads canonical CTRC straight into the engine
        batch and :func:`physcene.ctrc.parse` reads the rest; the rewards, metrics and
        ``last_parse_errors`` are those of parsing every text with :func:`parse`.
        """
        engine = self.engine
        if not self.config.fast_parse or not hasattr(engine, "pack_texts"):  # duck-typed engines
            return self.score_parsed([parse(t) for t in texts])
        pack = engine.pack_texts(texts, parse)
        return self._score(pack.batch, np.nonzero(pack.row >= 0)[0], pack.errors)

    def score_parsed(self, parsed: Sequence[Scene | ParseError]) -> list[float]:
        """Rewards for already parsed completions (a Scene or a ParseError each)."""
        ok = [k for k, p in enumerate(parsed) if isinstance(p, Scene)]
        batch = self.engine.pack([parsed[k] for k in ok]) if ok else None
        errors = [p.reason if isinstance(p, ParseError) else None for p in parsed]
        return self._score(batch, np.asarray(ok, dtype=np.int64), errors)

    def _score(self, batch, ok: np.ndarray, errors: list[str | None]) -> list[float]:
        """Rewards of n = len(errors) completions; ``batch`` row r scores completion ok[r]."""
        cfg = self.config
        n_text = len(errors)
        rewards = np.full(n_text, cfg.unparsable, dtype=np.float64)
        e_mm = np.zeros(0)
        depth_mm = np.zeros(0)
        size_cm = None
        if ok.size:
            out = self.engine.evaluate(batch, tolerance=cfg.tolerance_mm / 10.0)
            e = out["depth_sum"]
            if cfg.table_term:
                table = out["table_depth"]
                e = e + (table * (table > cfg.tolerance_mm / 10.0)).sum(dim=1)
            both = (torch.stack([e, out["max_depth"]]) * 10.0).cpu().numpy().astype(np.float64)  # one sync
            e_mm, depth_mm = both[0], both[1]
            rewards[ok] = reward_from_energy(e_mm, cfg)
            wants_size = cfg.size_per_cm or (self.object_depths and "size" in self.object_terms)
            bands = None  # host work per object: only when asked, and once for both of its uses
            if wants_size or "shrunk" in cfg.valid_terms:
                bands = prior_bands(batch, cfg.size_tolerance)
            if wants_size:
                size_cm = _outside_cm(bands)
            if cfg.size_per_cm:
                rewards[ok] = np.maximum(rewards[ok] - cfg.size_per_cm * size_cm.sum(1), -cfg.max_penalty)
            if cfg.valid_terms:
                broken = self.broken_objects(batch, bands)
                invalid = np.zeros(ok.size, dtype=bool)
                for objects in broken.values():
                    invalid |= objects.any(1)
                rewards[ok] = np.where(invalid, cfg.invalid, rewards[ok])
        self.last_object_depths = [None] * n_text
        self.last_placement_depths = [None] * n_text
        if self.object_depths and ok.size:
            sized = "size" in self.object_terms
            for r, depths in enumerate(self._object_depths(batch, out)):
                self.last_placement_depths[int(ok[r])] = depths
                self.last_object_depths[int(ok[r])] = depths + size_cm[r, :depths.size] if sized else depths
        n = max(n_text, 1)
        self.last_parse_errors = list(errors)
        self.last_metrics = {
            "parse_failure_rate": (n_text - ok.size) / n,
            "mean_energy_mm": float(e_mm.mean()) if ok.size else 0.0,
            "collision_free_rate": float((e_mm == 0).mean()) if ok.size else 0.0,
            "mean_max_depth_mm": float(depth_mm.mean()) if ok.size else 0.0,
            "mean_reward": float(rewards.mean()) if n_text else 0.0,
        }
        if size_cm is not None:
            self.last_metrics["mean_size_outside_cm"] = float(size_cm.sum(1).mean())
        if cfg.valid_terms and ok.size:
            self.last_metrics["invalid_rate"] = float(invalid.mean())
            for term, objects in broken.items():
                self.last_metrics[f"mean_{term}_objects"] = float(objects.sum(1).mean())
        return rewards.tolist()

    def broken_objects(self, batch, bands=None) -> dict[str, np.ndarray]:
        """Per ``valid_terms`` term, (S, N) bool on the host: the objects of each scene that break it
        (padded slots never do). ``bands``: the batch's :func:`prior_bands` at ``size_tolerance``, if
        the caller has them."""
        cfg = self.config
        mask = batch.mask.cpu().numpy()
        broken = {}
        if "floating" in cfg.valid_terms:
            gap = self.engine.support_gap(batch).cpu().numpy()
            broken["floating"] = (gap > self.engine.config.floating_tolerance_cm) & mask
        if "shrunk" in cfg.valid_terms:
            if bands is None:
                bands = prior_bands(batch, cfg.size_tolerance)
            broken["shrunk"] = (_low_ratio(bands) < cfg.shrink_ratio) & mask
        return broken

    def _object_depths(self, batch, out: dict) -> list[np.ndarray]:
        """Per batch row, (n_objects,) cm: what each object is charged with (``object_terms``; the
        ``size`` term, :func:`size_outside_band_cm` at ``size_tolerance``, is added by the caller).

        ``penetration``: a pair deeper than the tolerance charges its depth (``penetration_charge``
        ``depth``) or 1 (``pairs``) to the object written later (the larger index: objects keep the
        completion's order), the one placed into a space already taken; with ``table_term`` an object's
        own table depth is charged to it too (a depth either way).
        ``floating``: an object whose bottom is more than the engine's ``floating_tolerance_cm``
        above its support (the floating metric) is charged that gap. ``out_of_zone``: an object whose
        yawed footprint leaves the zone by more than ``ZONE_TOLERANCE_CM`` (the out-of-zone metric)
        is charged how far it reaches past it.
        """
        tolerance_cm = self.config.tolerance_mm / 10.0
        count = batch.count.cpu().numpy().astype(np.int64)
        depths = [np.zeros(int(n)) for n in count]
        per_object = []  # (S, N) host charges, each counted beyond its tolerance
        if "penetration" in self.object_terms:
            for s, pairs in enumerate(batch.deep_pairs(out["pair_depth"], tolerance_cm)):
                for i, j, d in pairs:
                    depths[s][max(i, j)] += d if self.penetration_charge == "depth" else 1.0
            if self.config.table_term:
                per_object.append((out["table_depth"].cpu().numpy(), tolerance_cm))
        if "floating" in self.object_terms:
            per_object.append((self.engine.support_gap(batch).cpu().numpy(),
                               self.engine.config.floating_tolerance_cm))
        if "out_of_zone" in self.object_terms:
            per_object.append((batch.zone_overshoot(), ZONE_TOLERANCE_CM))
        for value, tolerance in per_object:
            charged = np.where(value > tolerance, value, 0.0)
            for s, n in enumerate(count):
                depths[s] += charged[s, :n]
        return depths

    def describe(self) -> dict:
        return asdict(self.config)


def object_terms_checked(terms: Sequence[str]) -> tuple[str, ...]:
    """``terms`` as a tuple, each one of :data:`OBJECT_TERMS`, at least one, no repeats."""
    return _distinct_names(terms, OBJECT_TERMS, "object terms", at_least_one=True)


def valid_terms_checked(terms: Sequence[str]) -> tuple[str, ...]:
    """``terms`` as a tuple, each one of :data:`VALID_TERMS`, no repeats (none: the paper's reward)."""
    return _distinct_names(terms, VALID_TERMS, "valid terms", at_least_one=False)


def _distinct_names(terms, allowed: tuple[str, ...], what: str, *, at_least_one: bool) -> tuple[str, ...]:
    """``terms`` (one name or a sequence of them) as a tuple of distinct names among ``allowed``, else a
    ValueError naming ``what`` and the allowed names."""
    if isinstance(terms, str):
        terms = (terms,) if terms else ()
    terms = tuple(str(t) for t in terms)
    unknown = [t for t in terms if t not in allowed]
    if unknown or (at_least_one and not terms) or len(set(terms)) != len(terms):
        least = " (at least one)" if at_least_one else ""
        raise ValueError(f"{what} must be distinct names among {list(allowed)}{least}, got {list(terms)}")
    return terms


@functools.lru_cache(maxsize=4096)
def _prior_of(instance: str):
    return CATEGORY_PRIORS.get(canonical_category(category_from_instance(instance)))


def prior_bands(batch, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """On the host, per object of ``batch``: its size (S, N, 3) sorted ascending, and the low and high
    edges (S, N, 3) of its category prior's band at ``tolerance`` spreads, per ascending dimension
    (:meth:`physcene.assets.SizePrior.band_cm`; the category read from the instance id), with ``known``
    (S, N): whether it has a prior (edges 1 otherwise; False on padded slots). One look-up per object,
    the arithmetic batched."""
    sizes = np.sort(batch.sizes.detach().cpu().numpy().astype(np.float64), axis=-1)
    low, high = np.ones_like(sizes), np.ones_like(sizes)
    known = np.zeros(sizes.shape[:2], dtype=bool)
    for s, n in enumerate(batch.count.cpu().tolist()):
        ids = batch.ids[s]
        for k in range(int(n)):
            band = _band_of(ids[k], float(tolerance))
            if band is not None:
                low[s, k], high[s, k] = band
                known[s, k] = True
    return sizes, low, high, known


@functools.lru_cache(maxsize=8192)
def _band_of(instance: str, tolerance: float):
    prior = _prior_of(instance)
    return None if prior is None else prior.band_cm(tolerance)


def size_outside_band_cm(batch, tolerance: float) -> np.ndarray:
    """(S, N) cm on the host: how far each object's size lies outside its category prior's band at
    ``tolerance`` spreads (:meth:`physcene.assets.SizePrior.outside_band_cm`, batched by
    :func:`prior_bands`). 0 inside the band, for a category without a prior and on padded slots."""
    return _outside_cm(prior_bands(batch, tolerance))


def band_low_ratio(batch, tolerance: float) -> np.ndarray:
    """(S, N) on the host: each object's :meth:`physcene.assets.SizePrior.low_ratio` (the smallest ratio
    of a dimension to its band's low edge), batched by :func:`prior_bands`; inf without a prior."""
    return _low_ratio(prior_bands(batch, tolerance))


def _outside_cm(bands) -> np.ndarray:
    sizes, low, high, known = bands
    return np.where(known, (np.maximum(low - sizes, 0.0) + np.maximum(sizes - high, 0.0)).sum(-1), 0.0)


def _low_ratio(bands) -> np.ndarray:
    sizes, low, _, known = bands
    return np.where(known, (sizes / low).min(-1), np.inf)


def penetration_charge_checked(charge: str) -> str:
    """``charge`` if it is one of :data:`PENETRATION_CHARGES`, else a ValueError naming them."""
    if charge not in PENETRATION_CHARGES:
        raise ValueError(f"penetration charge must be one of {list(PENETRATION_CHARGES)}, got {charge!r}")
    return charge


_BY_DEVICE: dict[str, PhysicsReward] = {}


@functools.lru_cache(maxsize=1)
def _default_config() -> RewardConfig:
    return RewardConfig.load()


def physics_reward(prompts=None, completions=None, *, device=None, **columns) -> list[float]:
    """The reward with ``configs/reward.yaml`` defaults; see the module doc.

    ``device`` (e.g. this rank's ``cuda:N``) overrides the config's; one engine per device and
    process. The last batch's metrics are in ``physics_reward.last_metrics``.
    """
    config = _default_config()
    key = str(device) if device is not None else config.device
    reward = _BY_DEVICE.get(key)
    if reward is None:
        reward = _BY_DEVICE[key] = PhysicsReward(replace(config, device=key))
    rewards = reward(prompts, completions, **columns)
    physics_reward.last_metrics = reward.last_metrics
    return rewards


physics_reward.last_metrics = {}
