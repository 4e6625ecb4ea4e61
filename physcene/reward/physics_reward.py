"""The paper's physics reward as a TRL reward function (PADA's GRPO signal).

R = −100 if the completion does not parse; −min(0.01·E_pen, 50) if E_pen > 0; +50 if E_pen = 0,
with E_pen = Σ_{i<j} pen(i, j) in MILLIMETRES over pairs deeper than the tolerance (default 0).

``size_per_cm`` > 0 (NOT in the paper; 0 by default) also charges every object its size's distance
(cm) outside its category prior's band (:meth:`physcene.assets.SizePrior.outside_band_cm`), the total
still ≥ −max_penalty. A reward of penetration alone pays for flattening objects — a thin box cannot be
penetrated deeply — and a small policy finds that (docs/results.md).
``valid_terms`` (NOT in the paper; empty by default) pays a parsed layout that breaks one of them
``invalid`` whatever its penetration: ``floating`` (an object above its support) and ``shrunk`` (a
dimension far below its category's band). A collision-free reward pays for lifting and flattening
objects out of each other's way; 36 PADA steps did both (docs/results.md).

>>> reward = PhysicsReward(RewardConfig(device="cuda"))
>>> batch = reward.score(texts)            # RewardBatch: rewards, metrics, parse errors, charges
>>> trainer = GRPOTrainer(..., reward_funcs=[reward])        # TRL's signature: a list of floats

Each completion is parsed once, every parsed scene of the batch is scored in ONE engine call,
and unparsable completions never touch the engine. Canonical CTRC is read by the compiled
scanner (:mod:`physcene.reward.text_batch`, config ``fast_parse``); :func:`physcene.ctrc.parse` reads
the rest and decides which completions are unparsable. The reward does not need the task's
zone (penetration does not change when a whole layout is translated); the per-object
``out_of_zone`` charge of PADA's ``object_credit`` reads it from the completion.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from physcene.config import load_dataclass
from physcene.ctrc import ParseError, parse
from physcene.physics import PhysicsEngine
from physcene.reward.size_prior import low_ratio, outside_cm, prior_bands
from physcene.reward.text_batch import TextPacker
from physcene.scene import ZONE_TOLERANCE_CM, Scene, footprint_half_extents

__all__ = ["OBJECT_TERMS", "PENETRATION_CHARGES", "VALID_TERMS", "ChargeConfig", "PhysicsReward",
           "RewardBatch", "RewardConfig", "completion_text_of", "object_terms_checked",
           "penetration_charge_checked", "reward_from_energy", "valid_terms_checked"]

# What an object can be charged with (cm) when PhysicsReward keeps per-object charges (PADA's
# object_credit): the penetration of the pairs it was written into, its support gap when it floats,
# how far its footprint leaves the zone, how far its size lies outside its category's band. Only the
# first is in the paper's reward.
OBJECT_TERMS = ("penetration", "floating", "out_of_zone", "size")
# How a penetrating pair charges its later-written object: its depth (cm), or 1 per pair. A depth charge
# falls with the objects' thickness (a flat box cannot be penetrated deeply), a pair count does not.
PENETRATION_CHARGES = ("depth", "pairs")
# What ``RewardConfig.valid_terms`` may ask of a layout before it is paid for its penetration.
VALID_TERMS = ("floating", "shrunk", "out_of_zone")


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
    (:meth:`physcene.assets.SizePrior.low_ratio`; a flattened box); ``out_of_zone``, an object whose
    yawed footprint leaves the zone by more than ``ZONE_TOLERANCE_CM`` (the out-of-zone metric).
    Without them, lifting an object off its support, flattening it or pushing it off the zone takes
    it out of a collision and earns the collision-free reward."""
    invalid: float = -50.0
    """Reward of a parsed layout that breaks a ``valid_terms`` term (the worst colliding layout's)."""
    shrink_ratio: float = 0.5
    """``shrunk``: a dimension below this fraction of its band's low edge (test references: 2 of 1,899
    objects; the SFT model's greedy outputs 23; after 36 PADA steps of the paper's reward 161)."""
    device: str = "cpu"
    """Engine device, ``cpu`` or ``cuda[:N]``."""
    fast_parse: bool = True
    """Read canonical CTRC completions with the compiled scanner (:mod:`physcene.reward.text_batch`);
    the others, and every completion when False, with :func:`physcene.ctrc.parse`. The scanner
    writes into a :class:`~physcene.physics.PhysicsEngine`'s batch: an engine that only packs
    Scenes needs False."""

    max_overlapping_pairs: int = 2048
    """A parsed layout with more object pairs whose boxes overlap than this is refused like a
    completion that does not parse (``unparsable``, the reason names the count): it bounds the cost
    of one completion (999 objects stacked at one spot are ~500,000 deep pairs, seconds of engine
    time each). The benchmark's scenes have at most a few dozen such pairs."""

    def __post_init__(self):
        object.__setattr__(self, "valid_terms", valid_terms_checked(self.valid_terms))
        if self.max_overlapping_pairs < 1:
            raise ValueError(f"max_overlapping_pairs must be >= 1, got {self.max_overlapping_pairs}")

    @classmethod
    def load(cls, overrides: Sequence[str] = ()) -> RewardConfig:
        return load_dataclass(cls, "reward", overrides)


def overlapping_box_pairs(scene: Scene) -> int:
    """How many object pairs of ``scene`` have overlapping boxes (the axis-aligned bounds of the
    yawed footprints, and the z ranges): the pairs the engine's narrowphase would read."""
    centre = np.array([o.center for o in scene.objects], dtype=np.float64)
    size = np.array([o.size for o in scene.objects], dtype=np.float64)
    yaw = np.array([o.yaw for o in scene.objects], dtype=np.float64)
    half = np.concatenate([footprint_half_extents(size[:, :2], yaw), 0.5 * size[:, 2:]], 1)
    lo, hi = centre - half, centre + half
    meet = np.ones((len(centre), len(centre)), bool)
    for axis in range(3):
        meet &= (lo[:, None, axis] < hi[None, :, axis]) & (lo[None, :, axis] < hi[:, None, axis])
    return int(np.triu(meet, 1).sum())


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


@dataclass(frozen=True, kw_only=True)
class ChargeConfig:
    """What :meth:`PhysicsReward.score` charges each object of a parsed layout with (PADA's
    ``object_credit`` and ``denoise``; not in the paper's reward)."""

    terms: tuple[str, ...] = ("penetration",)
    """The charged terms, distinct names among :data:`OBJECT_TERMS`, at least one."""
    penetration: str = "depth"
    """``depth``: a penetrating pair charges its depth (cm); ``pairs``: 1 (:data:`PENETRATION_CHARGES`)."""

    def __post_init__(self):
        object.__setattr__(self, "terms", object_terms_checked(self.terms))
        penetration_charge_checked(self.penetration)


@dataclass(frozen=True)
class RewardBatch:
    """What :meth:`PhysicsReward.score` found for one batch of completions, in input order."""

    rewards: np.ndarray
    """(n_text,) float64 rewards."""
    metrics: Mapping[str, float]
    """``parse_failure_rate``, ``mean_energy_mm`` (over parsed layouts), ``collision_free_rate`` (over
    parsed layouts), ``mean_max_depth_mm`` and ``mean_reward``; with ``size_per_cm`` > 0 or the ``size``
    charge term ``mean_size_outside_cm`` (a parsed layout's summed size distance outside its band);
    with ``valid_terms`` ``invalid_rate`` and ``mean_<term>_objects`` per term."""
    parse_errors: tuple[str | None, ...]
    """Per completion, the ParseError reason, None where the text parsed."""
    object_charges: tuple[np.ndarray | None, ...]
    """Per completion, (n_objects,) the charge of each object (:class:`ChargeConfig`: cm of penetration,
    support gap, zone overshoot and size distance, or pair counts); None where the text did not parse
    or charges were not asked for."""
    placement_charges: tuple[np.ndarray | None, ...]
    """``object_charges`` less the ``size`` term: what moving the object can answer (PADA's
    ``denoise`` targets move objects; they do not resize them)."""


class PhysicsReward:
    """A TRL reward function ``f(prompts, completions, **columns) -> list[float]``; :meth:`score` gives
    the whole :class:`RewardBatch` (rewards, metrics, parse errors, per-object charges).

    ``charges``: the per-object charges every call computes (None: none, unless a call asks).
    """

    __name__ = "physics_reward"  # TRL names reward columns after the function

    def __init__(self, config: RewardConfig | None = None, engine: PhysicsEngine | None = None, *,
                 charges: ChargeConfig | None = None):
        self.config = config or RewardConfig()
        self._engine = engine
        self.charges = charges
        self._text_packer: TextPacker | None = None

    @property
    def engine(self):
        if self._engine is None:
            self._engine = PhysicsEngine(device=self.config.device)
        return self._engine

    def __call__(self, prompts=None, completions=None, *, charges: ChargeConfig | None = None,
                 on_batch=None, **columns) -> list[float]:
        """TRL's signature. ``charges`` and ``on_batch`` (called with the :class:`RewardBatch`) are for a
        trainer that reads more than the rewards (PADA's object credit)."""
        if completions is None:
            raise ValueError("physics_reward needs completions")
        batch = self.score([completion_text_of(c) for c in completions], charges=charges)
        if on_batch is not None:
            on_batch(batch)
        return batch.rewards.tolist()

    def score(self, texts: Sequence[str], *, charges: ChargeConfig | None = None) -> RewardBatch:
        """The rewards of completion texts, in order (one parse each, one engine call).

        With ``fast_parse`` the compiled scanner reads canonical CTRC straight into the engine
        batch and :func:`physcene.ctrc.parse` reads the rest; the rewards, metrics and parse
        errors are those of parsing every text with :func:`parse`. ``charges`` (default: the
        reward's own) asks for the per-object charges.
        """
        charges = charges or self.charges
        engine = self.engine
        if not self.config.fast_parse:
            return self.score_parsed([parse(t) for t in texts], charges=charges)
        if self._text_packer is None or self._text_packer.engine is not engine:
            self._text_packer = TextPacker(engine)
        # the compiled scanner reads at most MAX_ENTRIES objects: the texts it leaves to the parser
        # are the ones that can hold more pairs than the bound
        pack = self._text_packer.pack(texts, lambda text: self.bounded(parse(text)))
        return self._score(pack.batch, np.nonzero(pack.row >= 0)[0], pack.errors, charges)

    def bounded(self, parsed: Scene | ParseError) -> Scene | ParseError:
        """``parsed``, or a ParseError when its objects overlap in more than ``max_overlapping_pairs``
        pairs of boxes (yawed footprints' bounding boxes × z ranges)."""
        limit = self.config.max_overlapping_pairs
        if not isinstance(parsed, Scene) or len(parsed.objects) * (len(parsed.objects) - 1) // 2 <= limit:
            return parsed
        n = overlapping_box_pairs(parsed)
        if n <= limit:
            return parsed
        return ParseError(f"{n} pairs of objects overlap (limit {limit}, reward.max_overlapping_pairs)")

    def score_parsed(self, parsed: Sequence[Scene | ParseError], *,
                     charges: ChargeConfig | None = None) -> RewardBatch:
        """The rewards of already parsed completions (a Scene or a ParseError each)."""
        parsed = [self.bounded(p) for p in parsed]
        ok = [k for k, p in enumerate(parsed) if isinstance(p, Scene)]
        batch = self.engine.pack([parsed[k] for k in ok]) if ok else None
        errors = [p.reason if isinstance(p, ParseError) else None for p in parsed]
        return self._score(batch, np.asarray(ok, dtype=np.int64), errors, charges or self.charges)

    def _score(self, batch, ok: np.ndarray, errors: list[str | None],
               charges: ChargeConfig | None) -> RewardBatch:
        """The RewardBatch of n = len(errors) completions; ``batch`` row r scores completion ok[r]."""
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
            wants_size = cfg.size_per_cm or (charges is not None and "size" in charges.terms)
            bands = None  # host work per object: only when asked, and once for both of its uses
            if wants_size or "shrunk" in cfg.valid_terms:
                bands = prior_bands(batch, cfg.size_tolerance)
            if wants_size:
                size_cm = outside_cm(bands)
            if cfg.size_per_cm:
                rewards[ok] = np.maximum(rewards[ok] - cfg.size_per_cm * size_cm.sum(1), -cfg.max_penalty)
            if cfg.valid_terms:
                broken = self.broken_objects(batch, bands)
                invalid = np.zeros(ok.size, dtype=bool)
                for objects in broken.values():
                    invalid |= objects.any(1)
                rewards[ok] = np.where(invalid, cfg.invalid, rewards[ok])
        object_charges: list[np.ndarray | None] = [None] * n_text
        placement_charges: list[np.ndarray | None] = [None] * n_text
        if charges is not None and ok.size:
            sized = "size" in charges.terms
            for r, charged in enumerate(self._object_charges(batch, out, charges)):
                placement_charges[int(ok[r])] = charged
                object_charges[int(ok[r])] = charged + size_cm[r, :charged.size] if sized else charged
        n = max(n_text, 1)
        metrics = {
            "parse_failure_rate": (n_text - ok.size) / n,
            "mean_energy_mm": float(e_mm.mean()) if ok.size else 0.0,
            "collision_free_rate": float((e_mm == 0).mean()) if ok.size else 0.0,
            "mean_max_depth_mm": float(depth_mm.mean()) if ok.size else 0.0,
            "mean_reward": float(rewards.mean()) if n_text else 0.0,
        }
        if size_cm is not None:
            metrics["mean_size_outside_cm"] = float(size_cm.sum(1).mean())
        if cfg.valid_terms and ok.size:
            metrics["invalid_rate"] = float(invalid.mean())
            for term, objects in broken.items():
                metrics[f"mean_{term}_objects"] = float(objects.sum(1).mean())
        return RewardBatch(rewards=rewards, metrics=metrics, parse_errors=tuple(errors),
                           object_charges=tuple(object_charges), placement_charges=tuple(placement_charges))

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
            broken["shrunk"] = (low_ratio(bands) < cfg.shrink_ratio) & mask
        if "out_of_zone" in cfg.valid_terms:
            broken["out_of_zone"] = (batch.zone_overshoot() > ZONE_TOLERANCE_CM) & mask
        return broken

    def _object_charges(self, batch, out: dict, charges: ChargeConfig) -> list[np.ndarray]:
        """Per batch row, (n_objects,): what each object is charged with (``charges.terms``; the
        ``size`` term, :func:`size_outside_band_cm` at ``size_tolerance``, is added by the caller).

        ``penetration``: a pair deeper than the tolerance charges its depth (``charges.penetration``
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
        charged = [np.zeros(int(n)) for n in count]
        per_object = []  # (S, N) host charges, each counted beyond its tolerance
        if "penetration" in charges.terms:
            for s, pairs in enumerate(batch.deep_pairs(out["pair_depth"], tolerance_cm)):
                for i, j, d in pairs:
                    charged[s][max(i, j)] += d if charges.penetration == "depth" else 1.0
            if self.config.table_term:
                per_object.append((out["table_depth"].cpu().numpy(), tolerance_cm))
        if "floating" in charges.terms:
            per_object.append((self.engine.support_gap(batch).cpu().numpy(),
                               self.engine.config.floating_tolerance_cm))
        if "out_of_zone" in charges.terms:
            per_object.append((batch.zone_overshoot(), ZONE_TOLERANCE_CM))
        for value, tolerance in per_object:
            beyond = np.where(value > tolerance, value, 0.0)
            for s, n in enumerate(count):
                charged[s] += beyond[s, :n]
        return charged

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


def penetration_charge_checked(charge: str) -> str:
    """``charge`` if it is one of :data:`PENETRATION_CHARGES`, else a ValueError naming them."""
    if charge not in PENETRATION_CHARGES:
        raise ValueError(f"penetration charge must be one of {list(PENETRATION_CHARGES)}, got {charge!r}")
    return charge
