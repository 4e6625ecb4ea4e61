"""Category size priors per object of a batch: the bands the size guard and the ``shrunk`` term read.

Not in the paper. A reward of penetration alone pays for flattening objects (a thin box cannot be
penetrated deeply); the reward's ``size_per_cm`` and ``valid_terms=[shrunk]`` read how far each
object's size lies from its category prior's band (:class:`physcene.assets.SizePrior`). One cached
look-up per object, the arithmetic batched over (S, N, 3) arrays on the host.
"""

from __future__ import annotations

import functools

import numpy as np

from physcene.assets import CATEGORY_PRIORS, canonical_category
from physcene.layout import category_from_instance

__all__ = ["band_low_ratio", "low_ratio", "outside_cm", "prior_bands", "size_outside_band_cm"]


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
    return outside_cm(prior_bands(batch, tolerance))


def band_low_ratio(batch, tolerance: float) -> np.ndarray:
    """(S, N) on the host: each object's :meth:`physcene.assets.SizePrior.low_ratio` (the smallest ratio
    of a dimension to its band's low edge), batched by :func:`prior_bands`; inf without a prior."""
    return low_ratio(prior_bands(batch, tolerance))


def outside_cm(bands) -> np.ndarray:
    """(S, N) cm outside the band of :func:`prior_bands` ``bands`` (0 without a prior)."""
    sizes, low, high, known = bands
    return np.where(known, (np.maximum(low - sizes, 0.0) + np.maximum(sizes - high, 0.0)).sum(-1), 0.0)


def low_ratio(bands) -> np.ndarray:
    """(S, N) smallest ratio of a dimension to its band's low edge of ``bands`` (inf without a prior)."""
    sizes, low, _, known = bands
    return np.where(known, (sizes / low).min(-1), np.inf)
