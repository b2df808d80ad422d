"""The 3D view: the model surface (semi-transparent), contour points and the three slice planes.

A pyvistaqt ``QtInteractor`` (VTK in a QOpenGLWidget; needs a real OpenGL context, e.g. Xvfb
with the xcb platform when headless). The three orthogonal slices through the crosshair are
drawn as textured planes, as in 3D Slicer's 3D view. Updates from the state are coalesced by a
short single-shot timer so that scrolling or refits never queue several renders.
"""

from __future__ import annotations

import time

import numpy as np
import pyvista as pv
from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QVBoxLayout, QWidget
from pyvistaqt import QtInteractor

from app.convert import face_camera_to, points_polydata, surface_polydata
from app.state import FRAME_NAMES, SegmentationState
from core.planes import FRAMES, window_to_uint8

PLANE_OPACITY = 0.75  # slice planes in 3D: the image stays readable, the surface shows through

SURFACE_COLOR = (1.0, 0.67, 0.0)
MAX_DEFER_S = 0.5
POINT_COLOR = (0.0, 0.9, 1.0)


class VolumeView(QWidget):
    """3D view bound to a :class:`SegmentationState`."""

    def __init__(self, state: SegmentationState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.plotter = QtInteractor(self, auto_update=False)
        layout.addWidget(self.plotter.interactor)
        self.plotter.set_background((0.08, 0.08, 0.12), top=(0.25, 0.27, 0.33))
        self.plotter.add_axes(xlabel="R", ylabel="A", zlabel="S", line_width=2)
        self._surface_actor = None
        self._surface_mesh: pv.PolyData | None = None
        self._points_actor = None
        self._points_mesh: pv.PolyData | None = None
        self._plane_keys: dict[str, tuple] = {}
        self.defer = lambda: False      # e.g. "a refit is running": postpone non-urgent renders
        self._pending_since: float | None = None
        self._factor: int | None = None
        self._surface_style_changed = False
        self._plane_actors: dict[str, object] = {}
        self._plane_meshes: dict[str, pv.PolyData] = {}
        self._dirty: set[str] = set()
        self._camera_set = False
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(60)
        self._timer.timeout.connect(self._flush)
        state.image_changed.connect(lambda: self._mark("planes", "camera"))
        state.crosshair_changed.connect(lambda: self._mark("planes"))
        state.window_changed.connect(lambda: self._mark("planes"))
        state.model_changed.connect(self._on_model)
        state.surface_changed.connect(lambda: self._mark("surface"))
        state.points_changed.connect(lambda: self._mark("points"))
        self._mark("planes", "surface", "points", "camera")

    def _on_model(self) -> None:
        self._factor = None
        self._surface_style_changed = True
        self._mark("surface", "camera")

    def _mark(self, *what: str) -> None:
        """Schedule an update: debounced (a burst of scroll steps renders once at its end),
        but never postponed by more than MAX_DEFER_S."""
        now = time.perf_counter()
        if self._pending_since is None:
            self._pending_since = now
        self._dirty.update(what)
        if now - self._pending_since < MAX_DEFER_S or not self._timer.isActive():
            self._timer.start()

    def flush(self) -> None:
        """Apply pending updates and render now (tests, screenshots)."""
        self._timer.stop()
        self._pending_since = -1e9          # no deferral
        self._flush()

    def _flush(self) -> None:
        if getattr(self.plotter, "_closed", False):
            return
        # A render on a software GL stack costs tens of ms and holds the GIL: while a refit is
        # running, wait for its result (at most MAX_DEFER_S) instead of rendering twice.
        waited = time.perf_counter() - (self._pending_since or time.perf_counter())
        if self.defer() and waited < MAX_DEFER_S:
            self._timer.start()
            return
        dirty, self._dirty = self._dirty, set()
        self._pending_since = None
        if "planes" in dirty:
            self._update_planes()
        if "surface" in dirty:
            self._update_surface()
        if "points" in dirty:
            self._update_points()
        if "camera" in dirty or not self._camera_set:
            self.reset_camera()
        self.plotter.render()

    def _update_planes(self) -> None:
        state = self.state
        if state.sampler is None:
            return
        for name in FRAME_NAMES:
            frame = FRAMES[name]
            key = (frame.depth(state.crosshair), state.window, state.level, id(state.sampler))
            if self._plane_keys.get(name) == key:
                continue
            self._plane_keys[name] = key
            sl = state.sampler.sample(frame, frame.depth(state.crosshair))
            grey = window_to_uint8(sl.data, state.window, state.level)
            left, right, top, bottom = sl.extent()
            corners_uv = np.array([[left, bottom], [right, bottom], [right, top], [left, top]])
            corners = frame.to_world(np.column_stack([corners_uv, np.full(4, sl.depth)]))
            mesh = self._plane_meshes.get(name)
            if mesh is None:
                mesh = pv.PolyData(corners, faces=np.array([4, 0, 1, 2, 3]))
                mesh.active_texture_coordinates = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)
                self._plane_meshes[name] = mesh
            else:
                mesh.points = corners
            # texture rows go bottom-up: flip the top-down slice image
            texture = pv.Texture(np.ascontiguousarray(grey[::-1]))
            texture.interpolate = True
            actor = self._plane_actors.get(name)
            if actor is None:
                self._plane_actors[name] = self.plotter.add_mesh(
                    mesh, texture=texture, lighting=False, opacity=PLANE_OPACITY, name=f"plane-{name}",
                    reset_camera=False)
            else:
                actor.texture = texture

    def show_factor(self, index: int | None) -> None:
        """Colour the surface by how far factor ``index`` moves each vertex (None: plain).

        With a local-support model (SPLOCS, LSF, Varimax) this shows the one region that a
        factor slider moves.
        """
        index = None if index is None or index < 0 else int(index)
        if index == self._factor:
            return
        self._factor = index
        self._surface_style_changed = True
        self._mark("surface")

    def _update_surface(self) -> None:
        vertices = self.state.surface_vertices()
        model = self.state.model
        if vertices is None:
            if self._surface_actor is not None:
                self.plotter.remove_actor(self._surface_actor)
                self._surface_actor, self._surface_mesh = None, None
            return
        if self._factor is not None and self._factor >= model.n_factors:
            self._factor = None
        same_mesh = self._surface_mesh is not None and self._surface_mesh.n_points == len(vertices)
        if same_mesh and not self._surface_style_changed:
            self._surface_mesh.points = vertices
            self._surface_mesh.compute_normals(inplace=True, cell_normals=False, split_vertices=False)
            return
        self._surface_style_changed = False
        self._surface_mesh = surface_polydata(vertices, model.faces)
        if self._factor is None:
            self._surface_actor = self.plotter.add_mesh(
                self._surface_mesh, color=SURFACE_COLOR, opacity=0.65, smooth_shading=True,
                name="surface", reset_camera=False, specular=0.3)
        else:
            sd = float(np.sqrt(model.coef_var[self._factor]))
            self._surface_mesh["factor displacement (mm per SD)"] = \
                sd * np.linalg.norm(model.factors[self._factor], axis=1)
            self._surface_actor = self.plotter.add_mesh(
                self._surface_mesh, scalars="factor displacement (mm per SD)", cmap="plasma",
                clim=[0.0, max(float(self._surface_mesh["factor displacement (mm per SD)"].max()), 1e-6)],
                opacity=1.0, smooth_shading=True, name="surface", reset_camera=False,
                scalar_bar_args={"title": f"F{self._factor + 1} mm/SD", "vertical": True,
                                 "position_x": 0.84, "position_y": 0.1, "height": 0.6,
                                 "width": 0.07, "color": "white", "fmt": "%.1f"})
            # turn the view to the factor's region (it may face away from the camera), and let
            # the slice planes, which may stand in front of it, fade while it is shown
            face_camera_to(self.plotter, vertices, model.faces,
                           int(np.argmax(self._surface_mesh["factor displacement (mm per SD)"])))
        if self._factor is None:
            for name in list(self.plotter.scalar_bars.keys()):
                self.plotter.remove_scalar_bar(name)
        for actor in self._plane_actors.values():
            actor.prop.opacity = PLANE_OPACITY if self._factor is None else 0.2

    def _update_points(self) -> None:
        pts = self.state.points
        if len(pts) == 0:
            if self._points_actor is not None:
                self.plotter.remove_actor(self._points_actor)
                self._points_actor, self._points_mesh = None, None
            return
        if self._points_actor is not None and self._points_mesh is not None:
            self._points_mesh.copy_from(points_polydata(pts.xyz))
            return
        self._points_mesh = points_polydata(pts.xyz)
        self._points_actor = self.plotter.add_mesh(
            self._points_mesh, color=POINT_COLOR, point_size=9,
            render_points_as_spheres=True, name="points", reset_camera=False)

    def reset_camera(self) -> None:
        """Look at the model (or the image) from anterior-left-superior."""
        vertices = self.state.surface_vertices()
        if vertices is not None:
            center = vertices.mean(axis=0)
            radius = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
            distance = max(radius * 2.8, 90.0)
        elif self.state.volume is not None:
            lo, hi = self.state.volume.world_bounds()
            center, distance = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) * 1.6
        else:
            return
        direction = np.array([-0.55, 0.75, 0.45])
        direction /= np.linalg.norm(direction)
        self.plotter.camera_position = [tuple(center + distance * direction), tuple(center), (0, 0, 1)]
        self.plotter.reset_camera_clipping_range()
        self._camera_set = True

    def screenshot(self) -> np.ndarray:
        self.flush()
        return self.plotter.screenshot(return_img=True)

    def close(self) -> bool:  # noqa: D102
        self._timer.stop()
        self.plotter.close()
        return super().close()
