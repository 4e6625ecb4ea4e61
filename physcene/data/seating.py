"""Seating contents in containers on the assets' SDF grids (the engine's own geometry), in cm.

A content (pen, apple, toothbrush) is lowered into its container from the rim until one more
step would bring a surface point of either shape within ``in_clearance_cm`` of the other's
surface: both directions are checked (content points in the container's SDF, container points
in the content's SDF), as the engine's narrowphase does. Distances are the normalised SDF times
the smallest half-extent, the engine's conservative scaling (docs/physics.md), so "clear" here
means "clear" for the engine.

``container``/``content`` are any objects with ``category``, ``center`` (3,), ``size`` (3,) and
``yaw`` (rad); ``config`` anything with ``in_clearance_cm`` and ``in_step_cm``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ContainerFit"]


class ContainerFit:
    """Seats contents inside containers on the assets' SDF grids (the engine's own geometry).

    ``library`` is an :class:`~physcene.assets.AssetLibrary` (default: ``default_library()``,
    loaded on first use so that importing this module stays cheap).
    """

    def __init__(self, library=None):
        self._library = library
        self._assets: dict[str, object] = {}

    def asset(self, category: str):
        if category not in self._assets:
            if self._library is None:
                from physcene.assets import default_library

                self._library = default_library()
            self._assets[category] = self._library.resolve(category).asset
        return self._assets[category]

    @staticmethod
    def _sample(sdf: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Trilinear SDF (normalised units) at points q (..., 3) of the [-1, 1]^3 frame.

        Points outside the grid get +1 (outside the shape's box, so outside the shape); only the
        points inside are interpolated, on the flattened grid (8 gathers of one index array).
        """
        r = sdf.shape[0]
        out = np.ones(q.shape[:-1], dtype=np.float64)
        inside = np.all(np.abs(q) <= 1.0, axis=-1)
        if not inside.any():
            return out
        g = (q[inside] + 1.0) * (0.5 * (r - 1))  # (M, 3)
        i0 = np.minimum(g.astype(np.int64), r - 2)
        t = g - i0
        flat = sdf.reshape(-1)
        base = (i0[:, 0] * r + i0[:, 1]) * r + i0[:, 2]
        tx, ty, tz = t[:, 0], t[:, 1], t[:, 2]
        c00 = flat[base] * (1 - tz) + flat[base + 1] * tz
        c01 = flat[base + r] * (1 - tz) + flat[base + r + 1] * tz
        c10 = flat[base + r * r] * (1 - tz) + flat[base + r * r + 1] * tz
        c11 = flat[base + r * r + r] * (1 - tz) + flat[base + r * r + r + 1] * tz
        out[inside] = (c00 * (1 - ty) + c01 * ty) * (1 - tx) + (c10 * (1 - ty) + c11 * ty) * tx
        return out

    @staticmethod
    def _to_frame(points_world: np.ndarray, center: np.ndarray, yaw: float, size: np.ndarray) -> np.ndarray:
        c, s = math.cos(yaw), math.sin(yaw)
        d = points_world - center
        local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2]], axis=-1)
        return local / (0.5 * size)

    @staticmethod
    def _to_world(points_norm: np.ndarray, center: np.ndarray, yaw: float, size: np.ndarray) -> np.ndarray:
        p = points_norm * (0.5 * size)
        c, s = math.cos(yaw), math.sin(yaw)
        return (
            np.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1], p[..., 2]], axis=-1)
            + center
        )

    def _clear(self, container, content, zs: np.ndarray, config) -> np.ndarray:
        """(S,) bool: with its centre at each z (cm), the content keeps ``in_clearance_cm`` from the
        container in both directions (content points in the container's SDF and vice versa)."""
        ca, ka = self.asset(container.category), self.asset(content.category)
        centers = np.repeat(content.center[None, :], len(zs), axis=0)
        centers[:, 2] = zs
        kw = self._to_world(ka.points.astype(np.float64), np.zeros(3), content.yaw, content.size)
        kw = kw[None] + centers[:, None, :]  # (S, P, 3)
        phi_c = self._sample(ca.sdf, self._to_frame(kw, container.center, container.yaw, container.size))
        phi_c = phi_c * 0.5 * float(np.min(container.size))
        cw = self._to_world(ca.points.astype(np.float64), container.center, container.yaw, container.size)
        rel = cw[None] - centers[:, None, :]  # (S, Q, 3) container points around each content pose
        phi_k = self._sample(ka.sdf, self._to_frame(rel, np.zeros(3), content.yaw, content.size))
        phi_k = phi_k * 0.5 * float(np.min(content.size))
        return (phi_c.min(axis=1) >= config.in_clearance_cm) & (phi_k.min(axis=1) >= config.in_clearance_cm)

    def seat(self, container, content, config) -> float | None:
        """The lowest content centre z (cm) with no surface crossing, or None if even the rim fails.

        The content is lowered from "bottom at the container's top" in coarse steps of
        ``8 * in_step_cm`` (all at once); the first blocked step is refined by bisection to
        ``in_step_cm / 8``.
        """
        top = (
            container.center[2] + 0.5 * container.size[2] + 0.5 * content.size[2] + 2 * config.in_clearance_cm
        )
        bottom = container.center[2] - 0.5 * container.size[2] + 0.5 * content.size[2]
        coarse = 8.0 * config.in_step_cm
        zs = np.append(np.arange(top, bottom, -coarse), bottom)
        ok = self._clear(container, content, zs, config)
        if not ok[0]:
            return None
        bad = np.flatnonzero(~ok)
        if len(bad) == 0:
            return float(zs[-1])
        hi, lo = float(zs[bad[0] - 1]), float(zs[bad[0]])  # hi clear, lo blocked
        while hi - lo > config.in_step_cm / 8.0:
            mid = 0.5 * (hi + lo)
            if self._clear(container, content, np.array([mid]), config)[0]:
                hi = mid
            else:
                lo = mid
        return hi
