"""Yawed boxes: rotations about z, footprint separation, the inflated-box overlap test.

A pose is vec4(x, y, z, yaw) (cm, rad) of the box centre; a half size vec3 (cm).
"""

# Warp needs typed constructors (float(0.0), int(0)) for variables a loop modifies.
# ruff: noqa: UP018

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["boxes_meet", "footprint_gap", "footprint_radius", "rotate_z"]


@wp.func
def rotate_z(c: float, s: float, v: wp.vec3):
    return wp.vec3(c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])



@wp.func
def footprint_radius(c: float, s: float, hw: float, hd: float, ux: float, uy: float):
    """Half-width of a yawed rectangle projected on the unit axis (ux, uy)."""
    return hw * wp.abs(c * ux + s * uy) + hd * wp.abs(-s * ux + c * uy)



@wp.func
def footprint_gap(pa: wp.vec4, ha: wp.vec3, pb: wp.vec4, hb: wp.vec3):
    """Largest separation of the two yawed footprints over the 4 candidate axes (cm, <0: overlap)."""
    ca = wp.cos(pa[3])
    sa = wp.sin(pa[3])
    cb = wp.cos(pb[3])
    sb = wp.sin(pb[3])
    dx = pb[0] - pa[0]
    dy = pb[1] - pa[1]
    gap = float(-1.0e30)
    for k in range(4):
        ux = ca
        uy = sa
        if k == 1:
            ux = -sa
            uy = ca
        elif k == 2:
            ux = cb
            uy = sb
        elif k == 3:
            ux = -sb
            uy = cb
        sep = wp.abs(dx * ux + dy * uy) - footprint_radius(ca, sa, ha[0], ha[1], ux, uy) \
            - footprint_radius(cb, sb, hb[0], hb[1], ux, uy)
        gap = wp.max(gap, sep)
    return gap



@wp.func
def boxes_meet(pa: wp.vec4, ha: wp.vec3, pb: wp.vec4, hb: wp.vec3, margin: float):
    """1 if the two yawed boxes (half sizes ha, hb), inflated by margin, overlap, else 0."""
    hit = int(0)
    if wp.abs(pa[2] - pb[2]) <= ha[2] + hb[2] + margin:
        if footprint_gap(pa, ha, pb, hb) <= margin:
            hit = 1
    return hit
