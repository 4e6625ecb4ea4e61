"""Procedural meshes of the tabletop categories, built with trimesh (+ manifold3d for booleans).

:func:`procedural_mesh` returns one watertight mesh per category of :data:`CATEGORY_PRIORS`, in
centimetres, z up, resting on z = 0, sized to the category's mean [w, d, h]. Containers have real
cavities (an open top, walls with thickness and a floor): the vessels are solids of revolution of a
closed (r, z) profile that runs up the outer wall, over the rim and down the inner wall, so they
are watertight shells without any boolean; handles are unioned after the part that would poke
into the cavity is cut away. Every builder only uses the prior's size, so a prior and its mesh
never disagree.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from physcene.assets.categories import CATEGORY_PRIORS

__all__ = ["PROCEDURAL_BUILDERS", "procedural_mesh"]

_SECTIONS = 48  # around a solid of revolution: < 0.3 % radial error, a few thousand faces per mesh


# ---------------------------------------------------------------- parts (all lengths in cm)


def _box(extents, center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def _cylinder(radius, height, center=(0.0, 0.0, 0.0), axis="z", sections=_SECTIONS) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    return _orient(m, axis, center)


def _ellipsoid(radii, center=(0.0, 0.0, 0.0), subdivisions=3) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    m.apply_scale(radii)
    m.apply_translation(center)
    return m


def _orient(m: trimesh.Trimesh, axis: str, center) -> trimesh.Trimesh:
    """Turn a z-axis part to ``axis`` and move it to ``center``."""
    if axis == "x":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    elif axis == "y":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    m.apply_translation(center)
    return m


def _revolve(profile) -> trimesh.Trimesh:
    """Solid of revolution about z of a closed (r, z) profile from the axis back to the axis."""
    return trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=_SECTIONS)


def _vessel(outer, wall: float, floor: float) -> trimesh.Trimesh:
    """A container shell: ``outer`` is (r, z) up the outside from the base (r > 0) to the rim.

    The inner wall follows the outer one ``wall`` cm inward down to a floor ``floor`` cm thick.
    """
    outer = np.asarray(outer, dtype=np.float64)
    inner = [(max(r - wall, 0.05), z) for r, z in outer[::-1] if z >= floor]
    rim = outer[-1, 1]
    inner = [(r, min(z, rim)) for r, z in inner]
    inner.append((max(np.interp(floor, outer[:, 1], outer[:, 0]) - wall, 0.05), floor))
    return _revolve([(0.0, outer[0, 1]), *map(tuple, outer), *inner, (0.0, floor)])


def _arc(major: float, minor: float, start: float, stop: float, segments: int = 24) -> trimesh.Trimesh:
    """A tube of radius ``minor`` along a circular arc of radius ``major`` in the xz plane.

    Angles in radians from +x towards +z; the tube has flat ends (watertight).
    """
    angles = np.linspace(start, stop, segments + 1)
    ring = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    verts = []
    for a in angles:
        c = np.array([np.cos(a), 0.0, np.sin(a)])
        for b in ring:
            verts.append(c * (major + minor * np.cos(b)) + np.array([0.0, minor * np.sin(b), 0.0]))
    verts = np.array(verts)
    n = len(ring)
    faces = []
    for s in range(segments):
        for k in range(n):
            a0, a1 = s * n + k, s * n + (k + 1) % n
            b0, b1 = a0 + n, a1 + n
            faces += [(a0, b0, a1), (a1, b0, b1)]
    cap0, cap1 = len(verts), len(verts) + 1
    verts = np.vstack(
        [verts, major * np.array([[np.cos(start), 0, np.sin(start)], [np.cos(stop), 0, np.sin(stop)]])]
    )
    last = segments * n
    for k in range(n):
        faces += [(cap0, k, (k + 1) % n), (cap1, last + (k + 1) % n, last + k)]
    m = trimesh.Trimesh(verts, np.array(faces), process=True)
    if m.volume < 0:
        m.invert()
    return m


def _union(*parts: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.union(list(parts), engine="manifold")


def _difference(a: trimesh.Trimesh, *b: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.difference([a, *b], engine="manifold")


def _hull(points) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64))


def _tray(w: float, d: float, h: float, wall: float, floor: float) -> trimesh.Trimesh:
    """An open rectangular box: outer w x d x h, walls ``wall`` thick, floor ``floor`` thick."""
    outer = _box((w, d, h), (0, 0, h / 2))
    cavity = _box((w - 2 * wall, d - 2 * wall, h), (0, 0, floor + h / 2))
    return _difference(outer, cavity)


def _side_handle(
    body_radius: float, z: float, reach: float, height: float, thickness: float
) -> trimesh.Trimesh:
    """A D-shaped handle on +x of a round body: sticks out ``reach`` cm, ``height`` cm tall.

    The part of the loop inside the body is cut away so nothing enters the body's cavity.
    """
    major = reach + thickness / 2
    handle = _arc(major, thickness / 2, -np.pi / 2, np.pi / 2)
    handle.apply_scale((1.0, 1.0, (height - thickness) / (2 * major)))
    handle.apply_translation((body_radius - thickness, 0.0, z))
    return _difference(handle, _cylinder(body_radius - thickness / 4, 4 * height, (0, 0, z)))


# ---------------------------------------------------------------- containers


def _mug(w, d, h):
    r = d / 2
    body = _vessel([(r * 0.97, 0.0), (r, 0.3), (r, h)], wall=0.35, floor=0.6)
    return _union(body, _side_handle(r, h * 0.5, w - d, h * 0.7, 0.9))


def _cup(w, d, h):
    r = d / 2
    return _vessel([(r * 0.72, 0.0), (r, h)], wall=0.25, floor=0.4)


def _teacup(w, d, h):
    r = d / 2
    body = _vessel([(r * 0.45, 0.0), (r * 0.5, 0.4), (r * 0.85, h * 0.45), (r, h)], wall=0.3, floor=0.7)
    return _union(body, _side_handle(r * 0.93, h * 0.6, w - d, h * 0.6, 0.6))


def _glass(w, d, h):
    r = d / 2
    return _vessel([(r * 0.9, 0.0), (r, h)], wall=0.25, floor=1.0)


def _wine_glass(w, d, h):
    r = d / 2
    bowl_z = h * 0.45
    return _revolve(
        [
            (0.0, 0.0),
            (r * 0.85, 0.0),
            (r * 0.85, 0.3),
            (0.5, 0.8),
            (0.4, bowl_z - 1.0),
            (r * 0.7, bowl_z),
            (r, bowl_z + (h - bowl_z) * 0.45),
            (r * 0.85, h),
            (r * 0.85 - 0.2, h),
            (r - 0.2, bowl_z + (h - bowl_z) * 0.45),
            (r * 0.6, bowl_z + 0.6),
            (0.0, bowl_z + 0.4),
        ]
    )


def _bowl(w, d, h):
    r = d / 2
    t = np.linspace(0, np.pi / 2, 10)
    curve = [(r * 0.45 + (r * 0.55) * np.sin(a), h * 0.15 + (h * 0.85) * (1 - np.cos(a))) for a in t]
    return _vessel(
        [(r * 0.4, 0.0), (r * 0.45, h * 0.15), *curve[1:]], wall=max(0.3, r * 0.06), floor=h * 0.15 + 0.4
    )


def _pot(w, d, h):
    r = d / 2
    body = _vessel([(r, 0.0), (r, h)], wall=0.3, floor=0.5)
    grip = (w - d) / 2
    handles = [_box((grip + 0.5, 3.0, 1.0), (s * (r + grip / 2 - 0.25), 0.0, h * 0.85)) for s in (-1, 1)]
    return _union(body, *handles)


def _basket(w, d, h):
    bh = h * 0.5
    body = _tray(w, d, bh, wall=0.8, floor=0.8)
    arch = _arc(w / 2 - 0.6, 0.6, 0.0, np.pi, segments=32)
    arch.apply_scale((1.0, 1.0, (h - bh) / (w / 2)))  # stretch the half circle to reach the full height
    arch.apply_translation((0.0, 0.0, bh - 0.6))
    return _union(body, arch)


def _pen_holder(w, d, h):
    return _vessel([(d / 2, 0.0), (d / 2, h)], wall=0.3, floor=0.6)


def _vase(w, d, h):
    r = d / 2
    return _vessel(
        [(r * 0.55, 0.0), (r, h * 0.35), (r * 0.8, h * 0.7), (r * 0.4, h * 0.85), (r * 0.5, h)],
        wall=0.4,
        floor=1.0,
    )


def _plate(w, d, h):
    r = d / 2
    return _vessel(
        [(r * 0.6, 0.0), (r * 0.62, h * 0.4), (r * 0.85, h * 0.55), (r, h)], wall=0.35, floor=h * 0.4
    )


def _tray_category(w, d, h):
    return _tray(w, d, h, wall=0.8, floor=0.6)


def _open_box(w, d, h):
    return _tray(w, d, h, wall=0.5, floor=0.5)


def _soap_dish(w, d, h):
    return _tray(w, d, h, wall=0.6, floor=0.6)


def _jewelry_box(w, d, h):
    return _tray(w, d, h, wall=0.8, floor=1.0)


# ---------------------------------------------------------------- supports and flat things


def _slab(w, d, h):
    return _box((w, d, h), (0, 0, h / 2))


def _disc(w, d, h):
    m = _cylinder(d / 2, h, (0, 0, h / 2))
    m.apply_scale((w / d, 1.0, 1.0))
    return m


def _saucer(w, d, h):
    r = d / 2
    return _vessel([(r * 0.55, 0.0), (r * 0.6, h * 0.3), (r, h)], wall=0.3, floor=h * 0.45)


def _monitor_stand(w, d, h):
    top = _box((w, d, 1.5), (0, 0, h - 0.75))
    legs = [_box((3.0, d, h - 1.0), (s * (w / 2 - 1.5), 0, (h - 1.0) / 2)) for s in (-1, 1)]
    return _union(top, *legs)


def _laptop(w, d, h):
    return _union(
        _box((w, d, h * 0.55), (0, 0, h * 0.275)), _box((w - 0.4, d - 0.4, h * 0.5), (0, 0, h * 0.7))
    )


# ---------------------------------------------------------------- irregular shapes


def _lamp(w, d, h):
    r = d / 2
    return _revolve(
        [
            (0.0, 0.0),
            (r * 0.6, 0.0),
            (r * 0.6, 1.5),
            (0.8, 2.5),
            (0.8, h * 0.65),
            (r, h * 0.65),
            (r * 0.55, h),
            (0.0, h),
        ]
    )


def _headphones(w, d, h):
    band = _arc(w / 2 - 1.2, 1.0, 0.15, np.pi - 0.15, segments=28)
    band.apply_translation((0.0, 0.0, h - w / 2))
    cups = [_cylinder(d / 2, 3.0, (s * (w / 2 - 1.5), 0.0, h * 0.3), axis="x") for s in (-1, 1)]
    return _union(band, *cups)


def _plant(w, d, h):
    r = d / 2
    pot = _revolve([(0.0, 0.0), (r * 0.45, 0.0), (r * 0.6, h * 0.35), (0.0, h * 0.35)])
    stem = _cylinder(0.6, h * 0.2, (0, 0, h * 0.42))
    leaves = _ellipsoid((r, r * d / w * w / d, h * 0.3), (0, 0, h * 0.7))
    return _union(pot, stem, leaves)


def _teapot(w, d, h):
    r = d / 2
    body = _revolve(
        [
            (0.0, 0.0),
            (r * 0.6, 0.0),
            (r, h * 0.4),
            (r * 0.7, h * 0.8),
            (r * 0.25, h * 0.85),
            (r * 0.25, h * 0.95),
            (0.0, h),
        ]
    )
    spout = _hull(
        np.vstack(
            [
                _ellipsoid((1.6, 1.6, 1.6), (r * 0.6, 0, h * 0.35), 1).vertices,
                _ellipsoid((0.7, 0.7, 0.7), (w / 2 - 0.7, 0, h * 0.75), 1).vertices,
            ]
        )
    )
    handle = _arc(h * 0.28, 0.6, -np.pi / 2, np.pi / 2)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi, (0, 0, 1)))
    handle.apply_translation((-(w / 2 - h * 0.28 - 0.6), 0.0, h * 0.45))
    return _union(body, spout, _difference(handle, _cylinder(r * 0.8, h, (0, 0, h * 0.45))))


def _kettle(w, d, h):
    r = d / 2
    body = _revolve([(0.0, 0.0), (r, 0.0), (r * 0.9, h * 0.75), (0.0, h * 0.75)])
    grip = _box((w * 0.5, 2.0, 2.0), (0.0, 0.0, h - 1.0))
    posts = [_box((1.5, 2.0, h * 0.3), (s * w * 0.2, 0.0, h * 0.8)) for s in (-1, 1)]
    spout = _hull(
        np.vstack(
            [
                _ellipsoid((1.8, 1.8, 1.8), (r * 0.7, 0, h * 0.3), 1).vertices,
                _ellipsoid((0.8, 0.8, 0.8), (w / 2 - 0.8, 0, h * 0.7), 1).vertices,
            ]
        )
    )
    return _union(body, grip, *posts, spout)


def _monitor(w, d, h):
    screen_h = h * 0.65
    screen = _box((w, 2.5, screen_h), (0, 0, h - screen_h / 2))
    neck = _box((w * 0.1, 2.5, h - screen_h + 1.0), (0, d * 0.2, (h - screen_h + 1.0) / 2))
    base = _box((w * 0.4, d, 1.2), (0, 0, 0.6))
    return _union(screen, neck, base)


def _banana(w, d, h):
    radius = w * 0.75
    arc = _arc(radius, min(d, h) / 2, np.pi / 2 - 0.7, np.pi / 2 + 0.7, segments=16)
    arc.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))  # lies curved in xy
    return arc


def _glasses(w, d, h):
    lens_r = w * 0.21
    lenses = []
    for s in (-1, 1):
        ring = _arc(lens_r, 0.3, 0.0, 2 * np.pi - 0.01, segments=24)
        ring.apply_translation((s * (lens_r + 0.8), 0.0, h / 2))
        lenses.append(ring)
    temples = [_box((0.4, d, 0.5), (s * (w / 2 - 0.2), 0.0, h / 2)) for s in (-1, 1)]
    bridge = _box((1.8, 0.4, 0.4), (0, 0, h / 2 + lens_r * 0.5))
    return _union(*lenses, *temples, bridge)


def _mirror(w, d, h):
    disc = _cylinder(w / 2, 1.5, (0, 0, h - w / 2), axis="y")
    neck = _box((1.5, 1.5, h - w + 1.0), (0, 0, (h - w + 1.0) / 2))
    base = _cylinder(d / 2, 1.5, (0, 0, 0.75))
    return _union(disc, neck, base)


def _picture_frame(w, d, h):
    frame = _box((w, 1.5, h), (0, -d / 2 + 0.75, h / 2))
    strut = _hull(
        [
            (-1, -d / 2 + 1.5, h * 0.6),
            (1, -d / 2 + 1.5, h * 0.6),
            (-1, d / 2 - 0.5, 0.0),
            (1, d / 2 - 0.5, 0.0),
            (-1, d / 2, 0.0),
            (1, d / 2, 0.0),
            (-1, d / 2, 0.5),
            (1, d / 2, 0.5),
        ]
    )
    return _union(frame, strut)


def _clock(w, d, h):
    face = _cylinder(min(w, h) / 2, d * 0.6, (0, 0, h / 2), axis="y")
    face.apply_scale((w / min(w, h), 1.0, 1.0))
    feet = [_box((1.5, d, 1.0), (s * w * 0.25, 0, 0.5)) for s in (-1, 1)]
    return _union(face, *feet)


def _scissors(w, d, h):
    loops = []
    for s in (-1, 1):
        ring = _arc(d / 4, h / 2, 0.0, 2 * np.pi - 0.01, segments=20)
        ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
        ring.apply_translation((-w / 2 + d / 4 + h / 2, s * d / 4, h / 2))
        loops.append(ring)
    blade = _hull(
        [
            (-w / 2 + d / 2, -d / 4, 0),
            (-w / 2 + d / 2, d / 4, 0),
            (w / 2, 0, 0),
            (-w / 2 + d / 2, -d / 4, h),
            (-w / 2 + d / 2, d / 4, h),
            (w / 2, 0, h),
        ]
    )
    return _union(*loops, blade)


def _stapler(w, d, h):
    base = _box((w, d, h * 0.3), (0, 0, h * 0.15))
    arm = _hull(
        [
            (-w / 2, -d / 2 + 0.3, h * 0.3),
            (-w / 2, d / 2 - 0.3, h * 0.3),
            (w / 2, -d / 2 + 0.3, h * 0.45),
            (w / 2, d / 2 - 0.3, h * 0.45),
            (-w / 2, -d / 2 + 0.3, h),
            (-w / 2, d / 2 - 0.3, h),
            (w / 2, -d / 2 + 0.3, h * 0.8),
            (w / 2, d / 2 - 0.3, h * 0.8),
        ]
    )
    return _union(base, arm)


# ---------------------------------------------------------------- everyday objects


def _rod(w, d, h):
    """A pen-like rod along x with a conical tip."""
    r = min(d, h) / 2
    m = _revolve([(0.0, 0.0), (r, 0.0), (r, w * 0.85), (0.2 * r, w), (0.0, w)])
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    m.apply_scale((1.0, d / (2 * r), h / (2 * r)))
    return m


def _capsule_x(w, d, h):
    r = min(d, h) / 2
    m = trimesh.creation.capsule(height=max(w - 2 * r, 0.01), radius=r, count=(24, 12))
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    m.apply_scale((1.0, d / (2 * r), h / (2 * r)))
    return m


def _rounded_box(w, d, h):
    """A superellipsoid-ish block (soap, sponge, mouse body): convex hull of rounded corners."""
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    pts = []
    for z, k in ((0.0, 0.8), (h * 0.25, 0.97), (h * 0.75, 0.97), (h, 0.8)):
        x = np.sign(np.cos(t)) * np.abs(np.cos(t)) ** 0.4 * w / 2 * k
        y = np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.4 * d / 2 * k
        pts.append(np.stack([x, y, np.full_like(x, z)], -1))
    return _hull(np.concatenate(pts))


def _dome(w, d, h):
    """Half an ellipsoid on a flat base (computer mouse)."""
    m = _ellipsoid((w / 2, d / 2, h), (0, 0, 0))
    pts = m.vertices[m.vertices[:, 2] >= 0]
    return _hull(np.vstack([pts, pts * (1, 1, 0)]))


def _ellipsoid_category(w, d, h):
    return _ellipsoid((w / 2, d / 2, h / 2), (0, 0, h / 2))


def _apple(w, d, h):
    r = d / 2
    t = np.linspace(0, np.pi, 17)[1:-1]
    body = _revolve(
        [(0.0, h * 0.06), *[(r * np.sin(a), h * 0.85 * (1 - np.cos(a)) / 2) for a in t], (0.0, h * 0.8)]
    )
    stem = _cylinder(0.25, h * 0.2, (0, 0, h * 0.9))
    return _union(body, stem)


def _lemon(w, d, h):
    t = np.linspace(0, np.pi, 16)
    m = _revolve([(d / 2 * np.sin(a) ** 1.3, w / 2 * (1 - np.cos(a))) for a in t])
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    m.apply_translation((-m.bounds[0][0] - w / 2, 0.0, -m.bounds[0][2]))
    m.apply_scale((1.0, 1.0, h / d))
    return m


def _candle(w, d, h):
    return _union(
        _cylinder(d / 2, h * 0.92, (0, 0, h * 0.46)), _cylinder(0.15, h * 0.1, (0, 0, h * 0.95), sections=8)
    )


def _bottle(w, d, h):
    r = d / 2
    return _revolve([(0.0, 0.0), (r, 0.0), (r, h * 0.6), (r * 0.35, h * 0.8), (r * 0.35, h), (0.0, h)])


def _lotion_bottle(w, d, h):
    body = _cylinder(d / 2, h * 0.75, (0, 0, h * 0.375))
    body.apply_scale((w / d, 1.0, 1.0))
    pump = _cylinder(0.6, h * 0.2, (0, 0, h * 0.85))
    head = _box((w * 0.45, 1.2, 1.0), (w * 0.1, 0, h - 0.5))
    return _union(body, pump, head)


def _jar(w, d, h):
    r = d / 2
    return _revolve([(0.0, 0.0), (r, 0.0), (r, h * 0.85), (r * 0.9, h * 0.87), (r * 0.9, h), (0.0, h)])


def _shaker(w, d, h):
    r = d / 2
    return _revolve([(0.0, 0.0), (r, 0.0), (r * 0.85, h * 0.75), (r * 0.6, h), (0.0, h)])


def _perfume(w, d, h):
    return _union(
        _box((w, d, h * 0.7), (0, 0, h * 0.35)), _cylinder(min(w, d) * 0.3, h * 0.3, (0, 0, h * 0.85))
    )


def _spoon(w, d, h):
    handle = _box((w * 0.65, d * 0.25, 0.3), (-w * 0.175, 0, h * 0.6))
    bowl = _ellipsoid((w * 0.18, d / 2, h / 2), (w / 2 - w * 0.18, 0, h / 2))
    return _union(handle, bowl)


def _fork(w, d, h):
    handle = _box((w * 0.6, d * 0.35, h * 0.4), (-w * 0.2, 0, h * 0.5))
    head = _box((w * 0.15, d, h * 0.4), (w * 0.15, 0, h * 0.5))
    tines = [
        _box((w * 0.25, d * 0.15, h * 0.4), (w * 0.375, y, h * 0.5))
        for y in np.linspace(-d * 0.42, d * 0.42, 4)
    ]
    return _union(handle, head, *tines)


def _knife(w, d, h):
    handle = _box((w * 0.4, d * 0.6, h), (-w * 0.3, 0, h / 2))
    blade = _hull(
        [
            (-w * 0.1, -d / 2, 0),
            (-w * 0.1, d / 2, 0),
            (w / 2, -d / 2, 0),
            (-w * 0.1, -d / 2, h * 0.3),
            (-w * 0.1, d / 2, h * 0.3),
            (w / 2, -d / 2, h * 0.3),
            (w * 0.45, d / 2, 0),
        ]
    )
    return _union(handle, blade)


def _chopsticks(w, d, h):
    return _union(*[_capsule_x(w, h, h).apply_translation((0, s * (d / 2 - h / 2), 0)) for s in (-1, 1)])


def _keys(w, d, h):
    ring = _arc(d / 2 - h / 2, h / 2, 0.0, 2 * np.pi - 0.01, segments=20)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    ring.apply_translation((-w / 2 + d / 2, 0, h / 2))
    blade = _box((w - d + 0.5, d * 0.4, h * 0.6), ((d - 0.5) / 2, 0, h * 0.3))
    return _union(ring, blade)


def _toothbrush(w, d, h):
    handle = _capsule_x(w * 0.8, d * 0.6, h * 0.5)
    handle.apply_translation((-w * 0.1, 0, h * 0.25))
    head = _box((w * 0.2, d, h * 0.3), (w * 0.4, 0, h * 0.15))
    bristles = _box((w * 0.15, d * 0.8, h * 0.7), (w * 0.4, 0, h * 0.65))
    return _union(handle, head, bristles)


def _toothpaste(w, d, h):
    t = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    round_end = np.stack([np.full_like(t, -w / 2 + 2.5), d / 2 * np.cos(t), h / 2 + h / 2 * np.sin(t)], -1)
    flat_end = np.array([[w / 2 - 1.0, s * d / 2, h / 2] for s in (-1, 1)])
    cap = _cylinder(h * 0.35, 2.5, (-w / 2 + 1.25, 0, h / 2), axis="x")
    return _union(_hull(np.vstack([round_end, flat_end])), cap)


def _hairbrush(w, d, h):
    handle = _capsule_x(w * 0.55, d * 0.35, h * 0.4)
    handle.apply_translation((-w * 0.22, 0, h * 0.3))
    head = _ellipsoid((w * 0.2, d / 2, h / 2), (w * 0.3, 0, h / 2))
    return _union(handle, head)


def _game_controller(w, d, h):
    body = _ellipsoid((w * 0.3, d * 0.35, h / 2), (0, d * 0.1, h / 2))
    grips = [_ellipsoid((w * 0.2, d * 0.35, h * 0.45), (s * w * 0.3, -d * 0.12, h / 2)) for s in (-1, 1)]
    return _union(body, *grips)


def _cash_register(w, d, h):
    base = _box((w, d, h * 0.4), (0, 0, h * 0.2))
    keypad = _hull(
        [
            (-w / 2, -d / 2, h * 0.4),
            (w / 2, -d / 2, h * 0.4),
            (-w / 2, 0, h * 0.4),
            (w / 2, 0, h * 0.4),
            (-w / 2, 0, h * 0.55),
            (w / 2, 0, h * 0.55),
        ]
    )
    display = _box((w * 0.4, 3.0, h * 0.4), (0, d * 0.3, h * 0.8))
    return _union(base, keypad, display)


def _coffee_maker(w, d, h):
    base = _box((w, d, 3.0), (0, 0, 1.5))
    tower = _box((w, d * 0.4, h), (0, d * 0.3, h / 2))
    carafe = _cylinder(min(w, d) * 0.35, h * 0.4, (0, -d * 0.2, 3.0 + h * 0.2))
    return _union(base, tower, carafe)


def _card_reader(w, d, h):
    return _hull(
        [
            (-w / 2, -d / 2, 0),
            (w / 2, -d / 2, 0),
            (-w / 2, d / 2, 0),
            (w / 2, d / 2, 0),
            (-w / 2, -d / 2, h * 0.4),
            (w / 2, -d / 2, h * 0.4),
            (-w / 2, d / 2, h),
            (w / 2, d / 2, h),
        ]
    )


_SLABS = (
    "book",
    "notebook",
    "magazine",
    "tablet",
    "cutting_board",
    "placemat",
    "napkin",
    "towel",
    "game_console",
    "phone",
    "remote",
    "calculator",
    "sticky_notes",
    "wallet",
    "keyboard",
    "router",
    "tissue_box",
    "toaster",
    "receipt_printer",
    "speaker",
    "comb",
)

PROCEDURAL_BUILDERS: dict[str, Callable[[float, float, float], trimesh.Trimesh]] = {
    "mug": _mug,
    "cup": _cup,
    "teacup": _teacup,
    "glass": _glass,
    "wine_glass": _wine_glass,
    "bowl": _bowl,
    "pot": _pot,
    "basket": _basket,
    "pen_holder": _pen_holder,
    "vase": _vase,
    "plate": _plate,
    "tray": _tray_category,
    "open_box": _open_box,
    "soap_dish": _soap_dish,
    "toothbrush_cup": _pen_holder,
    "jewelry_box": _jewelry_box,
    **{c: _slab for c in _SLABS},
    "laptop": _laptop,
    "saucer": _saucer,
    "coaster": _disc,
    "monitor_stand": _monitor_stand,
    "lamp": _lamp,
    "headphones": _headphones,
    "plant": _plant,
    "teapot": _teapot,
    "kettle": _kettle,
    "monitor": _monitor,
    "television": _monitor,
    "banana": _banana,
    "glasses": _glasses,
    "mirror": _mirror,
    "picture_frame": _picture_frame,
    "clock": _clock,
    "scissors": _scissors,
    "stapler": _stapler,
    "pen": _rod,
    "pencil": _rod,
    "toothbrush": _toothbrush,
    "toothpaste": _toothpaste,
    "soap": _rounded_box,
    "sponge": _rounded_box,
    "hairbrush": _hairbrush,
    "perfume": _perfume,
    "lipstick": _candle,
    "apple": _apple,
    "orange": _ellipsoid_category,
    "lemon": _lemon,
    "candle": _candle,
    "mouse": _dome,
    "game_controller": _game_controller,
    "bottle": _bottle,
    "lotion_bottle": _lotion_bottle,
    "jar": _jar,
    "salt_shaker": _shaker,
    "spoon": _spoon,
    "fork": _fork,
    "knife": _knife,
    "chopsticks": _chopsticks,
    "keys": _keys,
    "cash_register": _cash_register,
    "card_reader": _card_reader,
    "coffee_maker": _coffee_maker,
}


def procedural_mesh(category: str) -> trimesh.Trimesh:
    """The procedural mesh of ``category`` in cm: z up, base on z = 0, sized to the prior's mean."""
    if category not in PROCEDURAL_BUILDERS:
        raise ValueError(f"no procedural mesh for category {category!r}")
    w, d, h = CATEGORY_PRIORS[category].mean_cm
    mesh = PROCEDURAL_BUILDERS[category](w, d, h)
    if not mesh.is_watertight:
        raise RuntimeError(f"procedural {category!r} mesh is not watertight")  # a builder bug
    # centre on the footprint, base on the table plane, extents exactly the prior's mean
    lo, hi = mesh.bounds
    mesh.apply_translation((-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]))
    mesh.apply_scale(np.array((w, d, h)) / mesh.extents)
    return mesh
