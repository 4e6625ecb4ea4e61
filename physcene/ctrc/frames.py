"""Relative placement: the parent frames a CTRC box is written in, and relative <-> absolute boxes.

A child's ``relative_bbox`` is its own box (own-frame extents w, d, h, centred at its centre)
written in the parent's yawed frame, x/y measured from the parent's (xmin, ymin) corner;
``relative_rotation_deg`` = child yaw − parent yaw; z is measured from the parent's bottom for
``in`` and from its top for ``on`` (``ON_CONTACT_GAP_CM`` above it: zmin 0 rests the child on its
support without a float32 contact). Table-level objects use the zone's (xmin, ymin) corner, no
rotation, and z from the table top. All lengths in cm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from physcene.ctrc.grammar import ON_CONTACT_GAP_CM
from physcene.scene import SceneObject, Zone, wrap_angle

__all__ = ["Frame", "absolute", "relative", "rounded"]


@dataclass(frozen=True)
class Frame:
    """Where a child's relative box is measured from: corner (cm), yaw (rad), z bases (cm)."""

    x0: float
    y0: float
    yaw: float
    z_in: float
    z_on: float

    @classmethod
    def of_zone(cls, zone: Zone) -> Frame:
        return cls(zone.xmin, zone.ymin, 0.0, 0.0, 0.0)

    @classmethod
    def of_object(cls, o: SceneObject) -> Frame:
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        hw, hd = 0.5 * o.size[0], 0.5 * o.size[1]
        return cls(o.center[0] - c * hw + s * hd, o.center[1] - s * hw - c * hd, o.yaw, o.zmin,
                   o.zmax + ON_CONTACT_GAP_CM)

    def z_base(self, relation: str) -> float:
        return self.z_in if relation == "in" else self.z_on


def relative(o: SceneObject, frame: Frame, relation: str) -> tuple[list[float], float]:
    """(relative_bbox [xmin, xmax, ymin, ymax, zmin, zmax] cm, relative rotation deg)."""
    c, s = math.cos(frame.yaw), math.sin(frame.yaw)
    dx, dy = o.center[0] - frame.x0, o.center[1] - frame.y0
    rx, ry = c * dx + s * dy, -s * dx + c * dy
    zb = frame.z_base(relation)
    hw, hd = 0.5 * o.size[0], 0.5 * o.size[1]
    box = [rx - hw, rx + hw, ry - hd, ry + hd, o.zmin - zb, o.zmax - zb]
    if relation == "on" and -2.0 * ON_CONTACT_GAP_CM <= box[4] < 0.0:  # touching (no gap): resting on it
        box[4], box[5] = 0.0, box[5] - box[4]
    return box, math.degrees(wrap_angle(o.yaw - frame.yaw))


def absolute(box: Sequence[float], rot_deg: float, frame: Frame, relation: str):
    """(center (3,), size (3,), yaw rad) of a relative box; inverse of :func:`relative`."""
    rx, ry = 0.5 * (box[0] + box[1]), 0.5 * (box[2] + box[3])
    c, s = math.cos(frame.yaw), math.sin(frame.yaw)
    cz = frame.z_base(relation) + 0.5 * (box[4] + box[5])
    center = (frame.x0 + c * rx - s * ry, frame.y0 + s * rx + c * ry, cz)
    size = (box[1] - box[0], box[3] - box[2], box[5] - box[4])
    return center, size, wrap_angle(frame.yaw + math.radians(rot_deg))


def rounded(v: float, decimals: int | None) -> float:
    """``v`` at ``decimals`` digits after the point (None: as it is); never -0.0."""
    return v if decimals is None else round(v, decimals) + 0.0  # + 0.0 turns -0.0 into 0.0
