"""Headless renders of a scene: front and perspective views as PNG, on any CPU machine.

Why a software rasteriser: the views must render from a plain ``pip install`` on a machine with
no display. pyrender needs an OpenGL context — OSMesa (``libOSMesa``, a system library pip
cannot install) or EGL (``libEGL`` + a Mesa/NVIDIA driver, also system libraries); MuJoCo's
renderer needs the same contexts. So the renderer here is a vectorised numpy z-buffer
rasteriser: the real meshes of every object (the asset library's procedural/primitive meshes
scaled to the object's size and yaw), a wooden table slab with the placement zone marked,
perspective projection, flat Lambert shading from a key and a fill light plus ambient, shadows
from a key-light shadow map, and 2× supersampling. docs/eval.md has the details and timings.

Views use MesaTask's camera directions (from the scene toward the camera, z up):
front (0, −1, 0.6), perspective (−0.7, −0.7, 0.7).
"""

from __future__ import annotations

import colorsys
import functools
import hashlib
import io
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import trimesh

from physcene.files import write_atomic
from physcene.scene import Scene

__all__ = ["VIEWS", "png_bytes", "render_comparison", "render_image", "render_views", "scene_meshes"]

VIEWS = {"front": (0.0, -1.0, 0.6), "perspective": (-0.7, -0.7, 0.7), "top": (0.0, -0.05, 1.0)}
_FOV_DEG = 40.0
_KEY_LIGHT = np.array([-0.35, -0.55, 1.0])  # direction toward the light
_FILL_LIGHT = np.array([0.6, 0.3, 0.5])
_AMBIENT = 0.32
_TABLE_COLOR = np.array([0.62, 0.47, 0.32])
_ZONE_COLOR = np.array([0.74, 0.60, 0.44])
_RESTRICTED_COLOR = np.array([0.35, 0.38, 0.42])
_TABLE_MARGIN_CM = 12.0
_TABLE_THICKNESS_CM = 4.0


def _category_color(category: str) -> np.ndarray:
    """A stable pastel colour per category (hash -> hue)."""
    h = int(hashlib.md5(category.encode()).hexdigest()[:8], 16)
    hue = (h % 360) / 360.0
    return np.array(colorsys.hsv_to_rgb(hue, 0.45 + 0.2 * ((h >> 9) % 3) / 2, 0.85))


@functools.lru_cache(maxsize=4)
def _primitive_mesh(kind: str) -> trimesh.Trimesh:
    from physcene.assets import primitive_asset

    return primitive_asset(kind).mesh


def _object_mesh(category: str, library) -> trimesh.Trimesh:
    """The category's mesh in the asset frame [-1, 1]^3 (a box when no asset has a mesh)."""
    if library is not None:
        try:
            asset = library.resolve(category).asset
        except (KeyError, ValueError) as exc:  # the render goes on; the object is drawn as its box
            warnings.warn(f"render: no asset for {category!r} ({exc}); drawn as a box", RuntimeWarning,
                          stacklevel=2)
        else:
            if asset.mesh is not None:
                return asset.mesh
    return _primitive_mesh("box")


def _default_library():
    try:
        from physcene.assets import default_library
    except ImportError:  # the asset library predates default_library(): primitives only
        return None
    return default_library()


def scene_meshes(scene: Scene, library=None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """World-space triangle meshes: the table slab, the zone and restricted-zone marks, and every
    object. Each entry is (vertices (V, 3) cm, faces (F, 3) int, rgb (3,) in [0, 1])."""
    library = _default_library() if library is None else library
    z = scene.zone
    parts = []
    m = _TABLE_MARGIN_CM
    slab = trimesh.creation.box(extents=(z.width + 2 * m, z.depth + 2 * m, _TABLE_THICKNESS_CM))
    slab.apply_translation((z.center[0], z.center[1], -0.5 * _TABLE_THICKNESS_CM - 0.05))
    parts.append((np.asarray(slab.vertices), np.asarray(slab.faces), _TABLE_COLOR))
    marks = [(z, _ZONE_COLOR, 0.0)] + [(r, _RESTRICTED_COLOR, 0.01) for r in scene.restricted_zones]
    for rect, color, lift in marks:
        v = np.array([[rect.xmin, rect.ymin, lift], [rect.xmax, rect.ymin, lift],
                      [rect.xmax, rect.ymax, lift], [rect.xmin, rect.ymax, lift]])
        parts.append((v, np.array([[0, 1, 2], [0, 2, 3]]), color))
    for o in scene.objects:
        mesh = _object_mesh(o.category, library)
        v = np.asarray(mesh.vertices, dtype=np.float64) * (0.5 * np.asarray(o.size))  # (V, 3) cm
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        v = v @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) + np.asarray(o.center)
        parts.append((v, np.asarray(mesh.faces), _category_color(o.category)))
    return parts


_BIG_TRIANGLE_PX = 4096


def _barycentric(t: np.ndarray, cx: np.ndarray, cy: np.ndarray, area) -> np.ndarray:
    """Barycentric coordinates (n, 3) of pixel centres (cx, cy) in triangles t (n or 1, 3, 2)."""
    w0 = (t[:, 1, 0] - cx) * (t[:, 2, 1] - cy) - (t[:, 2, 0] - cx) * (t[:, 1, 1] - cy)
    w1 = (t[:, 2, 0] - cx) * (t[:, 0, 1] - cy) - (t[:, 0, 0] - cx) * (t[:, 2, 1] - cy)
    w2 = (t[:, 0, 0] - cx) * (t[:, 1, 1] - cy) - (t[:, 1, 0] - cx) * (t[:, 0, 1] - cy)
    return np.stack([w0, w1, w2], axis=1) / np.reshape(area, (-1, 1))


def _interp_depth(b: np.ndarray, zt: np.ndarray, perspective: bool) -> np.ndarray:
    """Depth at barycentric b (n, 3) from vertex depths zt (n or 1, 3); 1/z-interpolated in
    perspective (screen-space linear interpolation of depth is wrong there)."""
    if perspective:
        return 1.0 / (b / zt).sum(axis=1)
    return (b * zt).sum(axis=1)


def _rasterize(xy: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int,
               perspective: bool, chunk_fragments: int = 3_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer rasterisation of triangles given screen positions.

    xy (V, 2) pixel coordinates, depth (V,) > 0, faces (F, 3). With ``perspective`` depth is
    interpolated as 1/z (perspective-correct). Returns (depth buffer (H, W) with inf where empty,
    face index buffer (H, W) int with −1 where empty).
    """
    zbuf = np.full(height * width, np.inf)
    fbuf = np.full(height * width, -1, dtype=np.int64)
    tri = xy[faces]  # (F, 3, 2)
    tz = depth[faces]  # (F, 3)
    x0 = np.clip(np.floor(tri[..., 0].min(1)), 0, width - 1).astype(np.int64)
    x1 = np.clip(np.ceil(tri[..., 0].max(1)), 0, width - 1).astype(np.int64)
    y0 = np.clip(np.floor(tri[..., 1].min(1)), 0, height - 1).astype(np.int64)
    y1 = np.clip(np.ceil(tri[..., 1].max(1)), 0, height - 1).astype(np.int64)
    area = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
            - (tri[:, 2, 0] - tri[:, 0, 0]) * (tri[:, 1, 1] - tri[:, 0, 1]))
    onscreen = ((tri[..., 0].max(1) >= 0) & (tri[..., 0].min(1) < width) & (tri[..., 1].max(1) >= 0)
                & (tri[..., 1].min(1) < height) & (np.abs(area) > 1e-9) & (tz.min(1) > 1e-6))
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    counts = bw * bh
    # Big triangles (the table, large faces) are filled one by one on their bounding box; the
    # many small ones are expanded into candidate fragments together and resolved by sorting.
    big = np.nonzero(onscreen & (counts > _BIG_TRIANGLE_PX))[0]
    for i in big:
        gx, gy = np.meshgrid(np.arange(x0[i], x1[i] + 1) + 0.5, np.arange(y0[i], y1[i] + 1) + 0.5)
        b = _barycentric(tri[i][None], gx.ravel(), gy.ravel(), area[i])
        inside = (b >= 0).all(axis=1)
        d = _interp_depth(b[inside], tz[i][None], perspective)
        px = (gx.ravel()[inside] - 0.5).astype(np.int64)
        pid = (gy.ravel()[inside] - 0.5).astype(np.int64) * width + px
        closer = d < zbuf[pid]
        zbuf[pid[closer]] = d[closer]
        fbuf[pid[closer]] = i
    idx = np.nonzero(onscreen & (counts <= _BIG_TRIANGLE_PX))[0]
    start = 0
    while start < len(idx):
        csum = np.cumsum(counts[idx[start:]])
        stop = start + max(1, int(np.searchsorted(csum, chunk_fragments)))
        sel = idx[start:stop]
        start = stop
        n = counts[sel]
        f = np.repeat(sel, n)  # triangle of each candidate fragment
        off = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        px = x0[f] + off % bw[f]
        py = y0[f] + off // bw[f]
        b = _barycentric(tri[f], px + 0.5, py + 0.5, area[f])
        keep = (b >= 0).all(axis=1)
        f, px, py, b = f[keep], px[keep], py[keep], b[keep]
        d = _interp_depth(b, tz[f], perspective)
        pid = py * width + px
        order = np.lexsort((d, pid))
        pid, d, f = pid[order], d[order], f[order]
        first = np.ones(len(pid), dtype=bool)
        first[1:] = pid[1:] != pid[:-1]
        pid, d, f = pid[first], d[first], f[first]
        closer = d < zbuf[pid]
        zbuf[pid[closer]] = d[closer]
        fbuf[pid[closer]] = f[closer]
    return zbuf.reshape(height, width), fbuf.reshape(height, width)


def _camera(scene: Scene, vertices: np.ndarray, direction, aspect: float):
    """Eye, orthonormal basis (right, up, forward) and distance framing every vertex."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    lo, hi = vertices.min(0), vertices.max(0)
    target = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    fov = math.radians(_FOV_DEG)
    fov_min = min(fov, 2 * math.atan(math.tan(fov / 2) * aspect))
    dist = radius / math.sin(fov_min / 2) * 0.8
    eye = target + d * dist
    forward = -d
    up_world = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up_world)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return eye, right, up, forward


def _shadow_mask(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, light: np.ndarray,
                 resolution: int = 1024) -> np.ndarray:
    """True for each world point (N, 3) that the key light does not reach (orthographic shadow map)."""
    lz = light / np.linalg.norm(light)
    lx = np.cross(lz, [0.0, 0.0, 1.0] if abs(lz[2]) < 0.99 else [1.0, 0.0, 0.0])
    lx /= np.linalg.norm(lx)
    ly = np.cross(lz, lx)
    proj = np.stack([vertices @ lx, vertices @ ly], axis=1)
    lo, hi = proj.min(0), proj.max(0)
    scale = (resolution - 1) / max(float((hi - lo).max()), 1e-6)
    depth_v = -(vertices @ lz)  # distance from the light plane, larger = farther from the light
    depth_v = depth_v - depth_v.min() + 1.0
    zbuf, _ = _rasterize((proj - lo) * scale, depth_v, faces, resolution, resolution, perspective=False)
    pp = (np.stack([points @ lx, points @ ly], axis=1) - lo) * scale
    ix = np.clip(pp[:, 0].astype(np.int64), 0, resolution - 1)
    iy = np.clip(pp[:, 1].astype(np.int64), 0, resolution - 1)
    dp = -(points @ lz) - (-(vertices @ lz)).min() + 1.0
    bias = 0.6 + 1.5 / scale  # cm: flat faces must not shadow themselves
    return dp > zbuf[iy, ix] + bias


def render_image(scene: Scene, view: str | tuple = "perspective", size: tuple[int, int] = (640, 480),
                 library=None, shadows: bool = True, supersample: int = 2, labels: bool = False,
                 pairs: Sequence[tuple[str, str, float]] = ()) -> np.ndarray:
    """One view of ``scene`` as an (H, W, 3) uint8 image. ``view`` is a name of :data:`VIEWS` or a
    direction (x, y, z) from the scene toward the camera; ``size`` is (width, height) px.

    ``labels`` writes each object's instance id above it; ``pairs`` (id a, id b, depth cm), e.g. the
    engine's ``Score.pairs``, are drawn as red lines between the two objects with the depth on them."""
    if isinstance(view, str) and view not in VIEWS:
        raise ValueError(f"unknown view {view!r}; known: {sorted(VIEWS)}")
    direction = VIEWS[view] if isinstance(view, str) else view
    width, height = int(size[0]) * supersample, int(size[1]) * supersample
    parts = scene_meshes(scene, library)
    verts, faces, colors, offset = [], [], [], 0
    for v, f, c in parts:
        verts.append(v)
        faces.append(f + offset)
        colors.append(np.repeat(c[None], len(f), axis=0))
        offset += len(v)
    V = np.concatenate(verts)  # (V, 3) cm
    F = np.concatenate(faces)  # (F, 3)
    C = np.concatenate(colors)  # (F, 3)
    eye, right, up, forward = _camera(scene, V, direction, width / height)
    rel = V - eye
    cam = np.stack([rel @ right, rel @ up, rel @ forward], axis=1)
    fpx = 0.5 * height / math.tan(math.radians(_FOV_DEG) / 2)
    z = np.maximum(cam[:, 2], 1e-6)
    xy = np.stack([0.5 * width + fpx * cam[:, 0] / z, 0.5 * height - fpx * cam[:, 1] / z], axis=1)
    zbuf, fbuf = _rasterize(xy, cam[:, 2], F, width, height, perspective=True)

    # Background: a soft vertical gradient.
    t = np.linspace(0.0, 1.0, height)[:, None, None]
    img = (1 - t) * np.array([0.93, 0.95, 0.98]) + t * np.array([0.80, 0.82, 0.86])
    img = np.broadcast_to(img, (height, width, 3)).copy()
    hit = fbuf >= 0
    f = fbuf[hit]
    tri = V[F[f]]  # (n, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    facing = np.einsum("ij,ij->i", normal, eye - tri.mean(axis=1))
    normal[facing < 0] *= -1  # two-sided: meshes from different sources wind differently
    key = _KEY_LIGHT / np.linalg.norm(_KEY_LIGHT)
    fill = _FILL_LIGHT / np.linalg.norm(_FILL_LIGHT)
    k = np.clip(normal @ key, 0.0, None)
    if shadows:
        py, px = np.nonzero(hit)
        ray = (((px + 0.5 - 0.5 * width) / fpx)[:, None] * right
               - ((py + 0.5 - 0.5 * height) / fpx)[:, None] * up)
        world = eye + zbuf[hit][:, None] * (ray + forward)
        shadow_res = int(np.clip(max(width, height), 256, 1024))  # about one texel per pixel
        k = np.where(_shadow_mask(world, V, F, key, resolution=shadow_res), 0.0, k)
    light = _AMBIENT + 0.62 * k + 0.22 * np.clip(normal @ fill, 0.0, None)
    img[hit] = np.clip(C[f] * light[:, None], 0.0, 1.0)
    img = (img * 255.0 + 0.5).astype(np.uint8)
    if supersample > 1:
        img = img.reshape(height // supersample, supersample, width // supersample, supersample, 3)
        img = img.mean(axis=(1, 3)).round().astype(np.uint8)
    if labels or pairs:
        def project(points: np.ndarray) -> np.ndarray:  # world cm -> output pixels
            rel = np.atleast_2d(points) - eye
            c = np.stack([rel @ right, rel @ up, np.maximum(rel @ forward, 1e-6)], axis=1)
            px = np.stack([0.5 * width + fpx * c[:, 0] / c[:, 2], 0.5 * height - fpx * c[:, 1] / c[:, 2]], 1)
            return px / supersample

        img = _annotate(img, scene, project, labels, pairs)
    return img


def _font(size: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def _annotate(img: np.ndarray, scene: Scene, project, labels: bool, pairs) -> np.ndarray:
    """Object ids above the objects and penetrating pairs with their depth, drawn with PIL."""
    from PIL import Image, ImageDraw

    out = Image.fromarray(img).convert("RGBA")
    layer = Image.new("RGBA", out.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    font = _font(max(11, img.shape[0] // 40))
    by_id = scene.by_id()
    centre = {o.instance_id: np.asarray(o.center, dtype=np.float64) for o in scene.objects}

    def tag(xy, text: str, fill, ink) -> None:
        box = draw.textbbox((0, 0), text, font=font)
        w, h = box[2] - box[0], box[3] - box[1]
        x, y = float(xy[0]) - w / 2, float(xy[1]) - h - 4
        draw.rounded_rectangle((x - 3, y - 2, x + w + 3, y + h + 4), radius=3, fill=fill)
        draw.text((x - box[0], y - box[1]), text, font=font, fill=ink)

    # labels first: a pair's depth is drawn over any label it meets
    if labels:
        for oid, o in by_id.items():
            top = centre[oid] + np.array([0.0, 0.0, 0.5 * o.size[2]])
            tag(project(top)[0], oid, (255, 255, 255, 200), (20, 20, 20, 255))
    for a, b, depth in pairs:
        if a not in centre or b not in centre:
            continue
        ends = project(np.stack([centre[a], centre[b]]))
        width = max(2, img.shape[0] // 240)
        draw.line([tuple(ends[0]), tuple(ends[1])], fill=(220, 30, 30, 255), width=width)
        text = f"{depth:.2f} cm" if depth >= 0.005 else "< 0.01 cm"
        tag(ends.mean(0), text, (220, 30, 30, 230), (255, 255, 255, 255))
    return np.asarray(Image.alpha_composite(out, layer).convert("RGB"))


def render_comparison(scenes: Mapping[str, Scene], view: str | tuple = "perspective",
                      size: tuple[int, int] = (800, 600), labels: bool = False,
                      pairs: Mapping[str, Sequence[tuple[str, str, float]]] | None = None,
                      library=None) -> np.ndarray:
    """Variants of one scene side by side (reference vs TTO, generator A vs B): one ``size`` panel
    per entry of ``scenes``, titled with its name, its penetrating pairs and the deepest one, the
    pairs drawn with their depth. ``pairs`` per name; scored with a CPU engine when not given."""
    from PIL import Image, ImageDraw

    if not scenes:
        raise ValueError("render_comparison needs at least one scene")
    if pairs is None:
        from physcene.physics import PhysicsEngine  # Warp: loaded only when depths are asked for

        score = PhysicsEngine(device="cpu").score(list(scenes.values()))
        pairs = {}
        for k, (name, scene) in enumerate(scenes.items()):
            ids = scene.ids()
            pairs[name] = [(ids[i], ids[j], float(d)) for i, j, d in score.pairs[k]]
    font_px = max(14, size[1] // 28)
    font = _font(font_px)
    title_h, gap = 2 * font_px + 16, 8
    sheet = Image.new("RGB", (len(scenes) * size[0] + (len(scenes) - 1) * gap, size[1] + title_h), "white")
    for k, (name, scene) in enumerate(scenes.items()):
        found = sorted(pairs.get(name, ()), key=lambda p: -p[2])
        panel = render_image(scene, view, size=size, library=library, labels=labels, pairs=found)
        x = k * (size[0] + gap)
        sheet.paste(Image.fromarray(panel), (x, title_h))
        # each title on its own strip: a long one is cut at its panel's edge, never runs into the next
        title = Image.new("RGB", (size[0], title_h), "white")
        draw = ImageDraw.Draw(title)
        plural = "s" if len(found) > 1 else ""
        verdict = (f"{len(found)} penetrating pair{plural}, deepest {found[0][2]:.2f} cm" if found
                   else "no penetrating pair")
        draw.text((8, 4), name, font=font, fill=(20, 20, 20))
        draw.text((8, 8 + font_px), verdict, font=font, fill=(200, 30, 30) if found else (30, 130, 60))
        sheet.paste(title, (x, 0))
    return np.asarray(sheet)


def png_bytes(image: np.ndarray) -> bytes:
    """PNG encoding of an (H, W, 3) uint8 image."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(image, dtype=np.uint8)).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def render_views(scene: Scene, out_dir, views=("front", "perspective"), size: tuple[int, int] = (640, 480),
                 prefix: str = "", library=None, labels: bool = False) -> dict[str, Path]:
    """Write ``<prefix><view>.png`` for each view into ``out_dir`` (object ids written on them with
    ``labels``); returns view -> path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for view in views:
        path = out / f"{prefix}{view}.png"
        write_atomic(path, png_bytes(render_image(scene, view, size=size, library=library, labels=labels)))
        paths[view] = path
    return paths
