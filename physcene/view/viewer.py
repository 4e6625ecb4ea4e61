"""The viser scene of ``physcene view``: asset meshes on the table, the placement zone, penetrating
pairs in red with their depth, floating objects in orange, the scene graph's edges, a scene picker
and a variant switch (before/after, method A/B).

Everything is drawn in metres with +z up (the export's frame, :mod:`physcene.export`), so the
viewer and the exported GLB / MJCF / USD agree. viser is the ``[view]`` extra.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np
import viser

from physcene.export.models import CM, ExportConfig, category_color, table_box, visual_meshes
from physcene.scene import Scene
from physcene.view.findings import RELATIONS, SceneFindings, find
from physcene.view.sources import ViewItem

__all__ = ["SceneViewer", "depth_text"]

PAIR_RGB = (230, 40, 40)
FLOATING_RGB = (255, 150, 0)
ZONE_RGB = (40, 170, 80)
RESTRICTED_RGB = (200, 40, 40)
EDGE_RGB = {"in": (40, 90, 230), "on": (20, 160, 60), "near": (130, 130, 130)}


def depth_text(depth_cm: float) -> str:
    """A pair's depth as written on the scene: two decimals, or the order of a contact's noise."""
    return f"{depth_cm:.2f} cm" if depth_cm >= 0.005 else f"{depth_cm:.0e} cm (touching)"


def _wxyz(yaw: float) -> tuple[float, float, float, float]:
    return (float(np.cos(0.5 * yaw)), 0.0, 0.0, float(np.sin(0.5 * yaw)))


def _rectangle(xmin: float, xmax: float, ymin: float, ymax: float, z: float) -> np.ndarray:
    c = np.array([[xmin, ymin, z], [xmax, ymin, z], [xmax, ymax, z], [xmin, ymax, z]])
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)  # (4, 2, 3) segments


class SceneViewer:
    """A viser server showing ``items``; :meth:`show` switches scene and variant.

    ``findings`` (penetrating pairs, floating objects, graph edges) are computed once per scene
    variant, lazily, with ``engine`` (a CPU :class:`~physcene.physics.PhysicsEngine` by default).
    """

    def __init__(self, items: Sequence[ViewItem], *, host: str = "127.0.0.1", port: int = 8080,
                 library=None, engine=None, export_config: ExportConfig | None = None):
        if not items:
            raise ValueError("SceneViewer needs at least one scene")
        self.items = list(items)
        self.library, self.engine = library, engine
        self.export_config = export_config or ExportConfig.load()
        self._findings: dict[tuple[int, str], SceneFindings] = {}
        self._lock = threading.Lock()
        self.server = viser.ViserServer(host=host, port=port, label="physcene view", verbose=False)
        self.server.scene.set_up_direction("+z")
        self.nodes: dict[str, object] = {}
        """Scene node name -> viser handle of what is drawn now."""
        self._build_gui()
        self.show(0, next(iter(self.items[0].variants)))

    # GUI -------------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        labels = [f"{k + 1}: {it.label}" for k, it in enumerate(self.items)]
        self._picker = gui.add_dropdown("Scene", labels, initial_value=labels[0],
                                        visible=len(labels) > 1)
        self._variant = gui.add_dropdown("Variant", list(self.items[0].variants),
                                         visible=len(self.items[0].variants) > 1)
        with gui.add_folder("Show"):
            # near edges connect every table-level object: off at first, they crowd the picture
            self._toggles = {r: gui.add_checkbox(f"'{r}' edges", initial_value=r != "near")
                             for r in RELATIONS}
            self._labels = gui.add_checkbox("object labels", initial_value=False)
            self._depths = gui.add_checkbox("pair depths", initial_value=True)
        self._summary = gui.add_markdown("")

        @self._picker.on_update
        def _(_event) -> None:
            k = labels.index(self._picker.value)
            names = list(self.items[k].variants)
            self._variant.options = names
            self._variant.visible = len(names) > 1
            variant = self._variant.value if self._variant.value in names else names[0]
            self.show(k, variant)

        @self._variant.on_update
        def _(_event) -> None:
            self.show(labels.index(self._picker.value), self._variant.value)

        for relation, box in self._toggles.items():
            box.on_update(lambda _e, r=relation: self._set_visible(f"/edges/{r}/", self._toggles[r].value))
        self._labels.on_update(lambda _e: self._set_visible("/labels/", self._labels.value))
        self._depths.on_update(lambda _e: self._set_visible("/pairs/", self._depths.value))

    def _set_visible(self, prefix: str, visible: bool) -> None:
        for name, handle in self.nodes.items():
            if name.startswith(prefix):
                handle.visible = visible

    # Scene -----------------------------------------------------------------------------------
    def findings(self, index: int, variant: str) -> SceneFindings:
        key = (index, variant)
        if key not in self._findings:
            self._findings[key] = find([self.items[index].variants[variant]], self.engine)[0]
        return self._findings[key]

    def show(self, index: int, variant: str) -> None:
        """Draw scene ``index`` as ``variant`` (replacing what was drawn)."""
        with self._lock:
            scene = self.items[index].variants[variant]
            found = self.findings(index, variant)
            for handle in self.nodes.values():
                handle.remove()
            self.nodes = {}
            self._draw(scene, found)
            self._summary.content = self._markdown(self.items[index].label, variant, found)

    def _add(self, name: str, handle) -> None:
        self.nodes[name] = handle

    def _draw(self, scene: Scene, found: SceneFindings) -> None:
        add = self.server.scene
        centre, half = table_box(scene, self.export_config)
        self._add("/table", add.add_box("/table", color=(150, 110, 70), dimensions=tuple(2 * half),
                                        position=tuple(centre)))
        z = 0.001  # a millimetre above the top: the outline is not lost in the table's faces
        zone = scene.zone
        self._add("/zone", add.add_line_segments(
            "/zone", CM * _rectangle(zone.xmin, zone.xmax, zone.ymin, zone.ymax, z / CM), ZONE_RGB,
            thickness=0.004))
        for k, r in enumerate(scene.restricted_zones):
            self._add(f"/restricted/{k}", add.add_line_segments(
                f"/restricted/{k}", CM * _rectangle(r.xmin, r.xmax, r.ymin, r.ymax, z / CM), RESTRICTED_RGB,
                thickness=0.004))
        in_pair = {i for a, b, _ in found.pairs for i in (a, b)}
        floating = set(found.floating)
        centres = {}
        for obj, name, _, mesh in visual_meshes(scene, library=self.library):
            colour = tuple(category_color(obj.category)[:3])
            if obj.instance_id in in_pair:
                colour = PAIR_RGB
            elif obj.instance_id in floating:
                colour = FLOATING_RGB
            centre_m = CM * np.asarray(obj.center, dtype=np.float64)
            centres[obj.instance_id] = centre_m
            node = f"/objects/{name}"
            self._add(node, add.add_mesh_simple(
                node, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32), color=colour,
                opacity=0.75 if obj.instance_id in in_pair else None, position=tuple(centre_m),
                wxyz=_wxyz(obj.yaw), side="double"))
            top = centre_m + np.array([0.0, 0.0, 0.5 * CM * obj.size[2] + 0.01])
            self._add(f"/labels/{name}", add.add_label(
                f"/labels/{name}", obj.instance_id, position=tuple(top), visible=self._labels.value,
                anchor="bottom-center"))
            if obj.instance_id in floating:
                self._add(f"/floating/{name}", add.add_label(
                    f"/floating/{name}", f"floating: {obj.instance_id}", position=tuple(top + [0, 0, 0.03]),
                    anchor="bottom-center"))
        for k, (a, b, depth) in enumerate(found.pairs):
            seg = np.array([[centres[a], centres[b]]])
            self._add(f"/pairs/{k}/line", add.add_line_segments(
                f"/pairs/{k}/line", seg, PAIR_RGB, thickness=0.004, visible=self._depths.value))
            mid = 0.5 * (centres[a] + centres[b]) + np.array([0.0, 0.0, 0.05])
            self._add(f"/pairs/{k}/depth", add.add_label(
                f"/pairs/{k}/depth", f"{a} ~ {b}: {depth_text(depth)}", position=tuple(mid),
                visible=self._depths.value, anchor="bottom-center"))
        for relation in RELATIONS:
            segs = [[centres[c], centres[p]] for c, p, r in found.edges if r == relation]
            if segs:
                name = f"/edges/{relation}/lines"
                self._add(name, add.add_line_segments(
                    name, np.asarray(segs), EDGE_RGB[relation], thickness=0.003,
                    visible=self._toggles[relation].value))
        # the camera looks at the zone from the front, above the near edge
        cx, cy = (CM * v for v in zone.center)
        span = CM * max(zone.width, zone.depth)
        self.server.initial_camera.look_at = (cx, cy, 0.0)
        self.server.initial_camera.position = (cx, cy - 1.1 * span, 0.75 * span)

    @staticmethod
    def _markdown(label: str, variant: str, found: SceneFindings) -> str:
        lines = [f"**{label}** ({variant})", ""]
        if found.pairs:
            lines.append("Penetrating pairs (depth):")
            lines += [f"- {a} ~ {b}: {depth_text(d)}" for a, b, d in found.pairs]
        else:
            lines.append("No penetrating pair.")
        lines.append("")
        lines.append("Floating: " + (", ".join(found.floating) if found.floating else "none"))
        return "\n".join(lines)

    def stop(self) -> None:
        self.server.stop()
