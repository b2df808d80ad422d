"""The 3D view: the model surface (semi-transparent), contour points and the three slice planes.

A pyvistaqt ``QtInteractor`` (VTK in a QOpenGLWidget; needs a real OpenGL context, e.g. Xvfb
with the xcb platform when headless). The three orthogonal slices through the crosshair are
drawn as textured planes, as in 3D Slicer's 3D view. Updates from the state are coalesced by a
short single-shot timer so that scrolling or refits never queue several renders: a slice move
renders RENDER_DELAY_MS later (after the slice views' own repaint), other changes (a point, its
refit's surface) COALESCE_MS later so that an edit and its refit render once; during a burst
(scrolling) renders are throttled to one per max(MIN_RENDER_INTERVAL_S, twice the last
render's time), so the 3D view follows the slices without taking the GUI thread.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pyvista as pv
from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QVBoxLayout, QWidget
from pyvistaqt import QtInteractor

from app.convert import face_camera_to, points_polydata, surface_polydata
from app.model.state import FRAME_NAMES, Structure, WorkspaceState
from core.geometry.planes import FRAMES, window_to_uint8

PLANE_OPACITY = 0.75  # slice planes in 3D: the image stays readable, the surface shows through

SURFACE_COLOR = (1.0, 0.67, 0.0)      # the first structure's colour (orange)
SURFACE_OPACITY = 0.65
INACTIVE_OPACITY = 0.3                # the other structures are dimmed
VIEW_DIRECTION = np.array([-0.55, 0.75, 0.45]) / math.sqrt(0.55**2 + 0.75**2 + 0.45**2)
FACTOR_SCALARS = "factor displacement (mm per SD)"
MAX_DEFER_S = 0.5
MIN_CAMERA_DISTANCE = 90.0    # mm: a small structure is seen with its surroundings
RENDER_DELAY_MS = 10          # lets the slice views paint first (they are the user's focus)
COALESCE_MS = 60              # an edit and the refit it starts: one render
MIN_RENDER_INTERVAL_S = 0.05
SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "software rasterizer")
POINT_COLOR = (0.0, 0.9, 1.0)


class VolumeView(QWidget):
    """3D view bound to a :class:`WorkspaceState`: one surface per visible structure."""

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.plotter = QtInteractor(self, auto_update=False)
        layout.addWidget(self.plotter.interactor)
        self.plotter.set_background((0.08, 0.08, 0.12), top=(0.25, 0.27, 0.33))
        from app.views.orientation import add_orientation_cube

        self.orientation_widget = add_orientation_cube(self.plotter)   # labelled R/L A/P S/I
        self.show_planes = True         # View menu toggles (app.panels.navigation)
        self.show_points = True
        # structure id -> (actor, mesh, style) with style = (colour, opacity, factor)
        self._surfaces: dict[int, tuple[object, pv.PolyData, tuple]] = {}
        self._points_actor = None
        self._points_mesh: pv.PolyData | None = None
        self._plane_keys: dict[str, tuple] = {}
        self.defer = lambda: False      # e.g. "a refit is running": postpone non-urgent renders
        # what the planes show: a cache key of the display settings and the grey image of a
        # slice (the second image's tools put their blend or checkerboard here)
        self.plane_key = lambda: (state.window, state.level)
        self.plane_grey = lambda frame, sl: window_to_uint8(sl.data, state.window, state.level)
        self._pending_since: float | None = None
        self._factor: int | None = None
        self._plane_actors: dict[str, object] = {}
        self._plane_meshes: dict[str, pv.PolyData] = {}
        self._dirty: set[str] = set()
        self._dirty_surfaces: set[int] = set()
        self._new_models: set[int] = set()     # structures whose mesh must be rebuilt
        self._notes: dict[str, str] = {}       # corner notes shown (orientation, plausibility)
        self._camera_set = False
        self.frame_points = lambda: None   # more points the camera frames (the plan's)
        # named extra meshes (trajectory, targets, ellipsoids): name -> (mesh or None, style)
        self._overlays: dict[str, tuple[pv.PolyData | None, dict]] = {}
        self._overlay_actors: dict[str, tuple] = {}   # name -> (actor, its mesh, style)
        self._scalars: tuple[np.ndarray, str] | None = None   # colour map on the active surface
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(RENDER_DELAY_MS)
        self._timer.timeout.connect(self._flush)
        self._last_render = (-1e9, 0.0)        # (end time, duration) of the last render
        for event in ("StartEvent", "EndEvent"):
            self.plotter.ren_win.AddObserver(event, self._on_render)
        self._gl_checked = False
        events = state.events
        events.image.connect(self._on_image)
        events.crosshair.connect(self._on_planes)
        events.window.connect(self._on_planes)
        events.structure_changed.connect(self._on_structure)
        events.structures.connect(self._on_structures)
        events.active.connect(self._on_active)
        events.fit_info.connect(self._on_fit_info)
        self._mark("planes", "surface", "points", "camera")

    @property
    def _surface_mesh(self) -> pv.PolyData | None:
        """The active structure's surface mesh (None if it has none shown)."""
        entry = self._surfaces.get(self.state.active.id)
        return None if entry is None else entry[1]

    def _on_image(self) -> None:
        known = self.state.orientation_known
        self._set_note("orientation", "" if known else "Orientation unknown: left/right may be "
                       "swapped", "upper_left")
        self._mark("planes", "camera")

    def _on_planes(self) -> None:
        self._mark("planes")

    def _on_structures(self) -> None:
        self._mark("surface", "points")

    def _on_active(self) -> None:
        self._factor = None
        self._mark("surface", "points")

    def _on_fit_info(self) -> None:
        warnings = self.state.active.fit_info.warnings
        self._set_note("plausibility", "Implausible fit: " + "; ".join(warnings) if warnings else "",
                       "lower_right")

    def _set_note(self, name: str, text: str, position: str) -> None:
        """A red note in a corner; only touched when it changes (no render here: the timer
        renders, so a refit's repaint of the slices is not delayed by the 3D view)."""
        if self._notes.get(name, "") == text:
            return
        self._notes[name] = text
        self.plotter.add_text(text, position=position, font_size=8, color="red", name=name,
                              render=False)
        self._mark()

    def _on_structure(self, structure: Structure, what: str) -> None:
        if what == "model":
            if structure is self.state.active:
                self._factor = None
            self._new_models.add(structure.id)
            self._dirty_surfaces.add(structure.id)
            self._mark("camera" if structure is self.state.active else "surface")
        elif what in ("surface", "properties"):
            self._dirty_surfaces.add(structure.id)
            self._mark("points" if what == "properties" else "surface")
        elif what == "points" and structure is self.state.active:
            self._mark("points")

    def _mark(self, *what: str) -> None:
        """Schedule an update: RENDER_DELAY_MS (slice planes) or COALESCE_MS (anything else)
        from now, or later when the throttle allows the next render (a burst of scroll steps
        renders at a steady rate, showing the latest slice); a pending render due sooner
        takes this change along."""
        now = time.perf_counter()
        if self._pending_since is None:
            self._pending_since = now
        self._dirty.update(what)
        end, duration = self._last_render
        ready = end + max(MIN_RENDER_INTERVAL_S, 2.0 * duration)
        delay = RENDER_DELAY_MS if set(what) <= {"planes"} else COALESCE_MS
        delay = max(delay, int(1000 * (ready - now)))
        if self._timer.isActive() and self._timer.remainingTime() <= delay:
            return                              # the pending render will include this
        self._timer.start(delay)

    def flush(self) -> None:
        """Apply pending updates and render now (tests, screenshots)."""
        self._timer.stop()
        self._pending_since = -1e9          # no deferral
        self._flush(now=True)

    def _on_render(self, _obj, event: str) -> None:
        """VTK's Start/EndEvent of the render window: the duration of every render, wherever
        it is started (the widget's paint, a screenshot), for the throttle of ``_mark``."""
        now = time.perf_counter()
        if event == "StartEvent":
            self._render_started = now
        else:
            self._last_render = (now, now - getattr(self, "_render_started", now))

    def _flush(self, now: bool = False) -> None:
        if getattr(self.plotter, "_closed", False):
            return
        # A render on a software GL stack costs tens of ms and holds the GIL: while a refit is
        # running, wait for its result (at most MAX_DEFER_S) instead of rendering twice.
        waited = time.perf_counter() - (self._pending_since or time.perf_counter())
        if self.defer() and waited < MAX_DEFER_S:
            self._timer.start(RENDER_DELAY_MS)
            return
        dirty, self._dirty = self._dirty, set()
        self._pending_since = None
        if "planes" in dirty:
            self._update_planes()
        if "surface" in dirty or "camera" in dirty or self._dirty_surfaces:
            self._update_surfaces()
        if "points" in dirty:
            self._update_points()
        if "overlays" in dirty:
            self._update_overlays()
        if "camera" in dirty or not self._camera_set:
            self.reset_camera()
        self.apply_visibility()
        if not self._gl_checked:                # the OpenGL context exists by now
            self._gl_checked = _no_multisampling_in_software(self.plotter)
        self._present(now)

    def _present(self, now: bool = False) -> None:
        """Render the scene once. pyvistaqt's widget renders in its paint (its paintGL always
        renders, since pyvista changes the scene without telling it), so ``plotter.render()``
        renders here and again in that paint: ~25-60 ms twice on a software GL stack. Unless
        ``now``, ask for the paint instead: one render, in the same window composition as the
        slice views' repaint."""
        if now:
            self.plotter.render()
            return
        self.plotter._rendered = True       # what QtInteractor.render() records (pyvista reads it)
        self.plotter.interactor.update()

    def apply_visibility(self) -> None:
        """Show or hide the slice planes and the contour points (``show_planes/points``)."""
        for actor in self._plane_actors.values():
            actor.SetVisibility(self.show_planes)
        if self._points_actor is not None:
            self._points_actor.SetVisibility(self.show_points)

    def _update_planes(self) -> None:
        state = self.state
        if state.sampler is None:
            return
        for name in FRAME_NAMES:
            frame = FRAMES[name]
            key = (frame.depth(state.crosshair), id(state.sampler), self.plane_key())
            if self._plane_keys.get(name) == key:
                continue
            self._plane_keys[name] = key
            sl = state.sampler.sample(frame, frame.depth(state.crosshair))
            grey = self.plane_grey(frame, sl)
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
                    reset_camera=False, render=False)
            else:
                actor.texture = texture

    def show_factor(self, index: int | None) -> None:
        """Colour the active surface by how far factor ``index`` moves each vertex (None: plain).

        With a local-support model (SPLOCS, LSF, Varimax) this shows the one region that a
        factor slider moves.
        """
        index = None if index is None or index < 0 else int(index)
        if index == self._factor:
            return
        self._factor = index
        self._dirty_surfaces.add(self.state.active.id)
        self._mark("surface")

    def show_scalars(self, values: np.ndarray | None, title: str = "") -> None:
        """Colour the active surface by per-vertex ``values`` (N,) (None: plain colour);
        a factor shown by :meth:`show_factor` takes precedence."""
        self._scalars = None if values is None else (np.asarray(values, dtype=np.float64), title)
        self._dirty_surfaces.add(self.state.active.id)
        self._mark("surface")

    def set_overlay(self, name: str, mesh: pv.PolyData | None, **style) -> None:
        """Show a named extra mesh with ``add_mesh`` keyword ``style`` (None removes it)."""
        self._overlays[name] = (mesh, style)
        self._mark("overlays")

    def _update_overlays(self) -> None:
        """Add, move or remove the named extra meshes; a mesh of the same style and size is
        copied into the existing actor's mesh (no new actor per update)."""
        for name, (mesh, style) in list(self._overlays.items()):
            shown = self._overlay_actors.get(name)
            if mesh is None:
                if shown is not None:
                    self.plotter.remove_actor(shown[0], render=False)
                    del self._overlay_actors[name]
                del self._overlays[name]
                continue
            if shown is not None and shown[2] == style and shown[1].n_points == mesh.n_points \
                    and shown[1].n_cells == mesh.n_cells:
                shown[1].copy_from(mesh)
                continue
            if shown is not None:
                self.plotter.remove_actor(shown[0], render=False)
            copy = mesh.copy()
            actor = self.plotter.add_mesh(copy, name=f"overlay-{name}", reset_camera=False,
                                          render=False, **style)
            self._overlay_actors[name] = (actor, copy, dict(style))

    def _update_surfaces(self) -> None:
        """Add, restyle, move or remove each structure's surface actor."""
        active = self.state.active
        model = active.model
        if self._factor is not None and (model is None or self._factor >= model.n_factors):
            self._factor = None
        present = {s.id for s in self.state.structures}
        for sid in [sid for sid in self._surfaces if sid not in present]:
            self.plotter.remove_actor(self._surfaces.pop(sid)[0], render=False)
        dirty, self._dirty_surfaces = self._dirty_surfaces, set()
        rebuild, self._new_models = self._new_models, set()
        for s in self.state.structures:
            vertices = s.surface_vertices()
            entry = self._surfaces.get(s.id)
            if vertices is None or not s.visible:
                if entry is not None:
                    self.plotter.remove_actor(self._surfaces.pop(s.id)[0], render=False)
                continue
            scalars = self._scalars if (s is active and self._factor is None) else None
            style = (s.color, s is active, self._factor if s is active else None,
                     None if scalars is None else id(scalars[0]))
            if entry is not None and entry[2] == style and s.id not in rebuild:
                if s.id in dirty:
                    entry[1].points = vertices
                    entry[1].compute_normals(inplace=True, cell_normals=False, split_vertices=False)
                continue
            self._surfaces[s.id] = self._add_surface(s, vertices, style)
        if self._factor is None and self._scalars is None:
            for name in list(self.plotter.scalar_bars.keys()):
                self.plotter.remove_scalar_bar(name, render=False)
        for actor in self._plane_actors.values():
            actor.prop.opacity = PLANE_OPACITY if self._factor is None else 0.2

    def _add_surface(self, s: Structure, vertices: np.ndarray, style: tuple) -> tuple:
        color, is_active, factor, scalars = style
        mesh = surface_polydata(vertices, s.model.faces)
        name = f"surface-{s.id}"
        if factor is None and scalars is not None and len(self._scalars[0]) == len(vertices):
            values, title = self._scalars
            mesh["values"] = values
            actor = self.plotter.add_mesh(
                mesh, scalars="values", cmap="viridis", clim=[0.0, max(float(values.max()), 1e-6)],
                opacity=1.0, smooth_shading=True, name=name, reset_camera=False, render=False,
                scalar_bar_args={"title": title, "vertical": True, "position_x": 0.84,
                                 "position_y": 0.1, "height": 0.6, "width": 0.07,
                                 "color": "white", "fmt": "%.2f"})
            return actor, mesh, style
        if factor is None:
            actor = self.plotter.add_mesh(
                mesh, color=tuple(c / 255 for c in color), smooth_shading=True, name=name,
                opacity=SURFACE_OPACITY if is_active else INACTIVE_OPACITY,
                reset_camera=False, render=False, specular=0.3)
            return actor, mesh, style
        mesh[FACTOR_SCALARS] = s.factor_displacement(factor)
        actor = self.plotter.add_mesh(
            mesh, scalars=FACTOR_SCALARS, cmap="plasma",
            clim=[0.0, max(float(mesh[FACTOR_SCALARS].max()), 1e-6)],
            opacity=1.0, smooth_shading=True, name=name, reset_camera=False, render=False,
            scalar_bar_args={"title": f"F{factor + 1} mm/SD", "vertical": True,
                             "position_x": 0.84, "position_y": 0.1, "height": 0.6,
                             "width": 0.07, "color": "white", "fmt": "%.1f"})
        # turn the view to the factor's region (it may face away from the camera), and let
        # the slice planes, which may stand in front of it, fade while it is shown
        face_camera_to(self.plotter, vertices, s.model.faces, int(np.argmax(mesh[FACTOR_SCALARS])))
        return actor, mesh, style

    def _update_points(self) -> None:
        pts = self.state.active.points
        if len(pts) == 0 or not self.state.active.visible:
            if self._points_actor is not None:
                self.plotter.remove_actor(self._points_actor, render=False)
                self._points_actor, self._points_mesh = None, None
            return
        if self._points_actor is not None and self._points_mesh is not None:
            self._points_mesh.copy_from(points_polydata(pts.xyz))
            return
        self._points_mesh = points_polydata(pts.xyz)
        self._points_actor = self.plotter.add_mesh(
            self._points_mesh, color=POINT_COLOR, point_size=9,
            render_points_as_spheres=True, name="points", reset_camera=False, render=False)

    def reframe(self) -> None:
        """Frame the scene again (e.g. a trajectory was planned)."""
        self._mark("camera")

    def framed_points(self) -> np.ndarray | None:
        """What the camera frames: every shown structure and :attr:`frame_points` (the plan's
        targets and entries), or None when there is none of these."""
        parts = [s.surface_vertices() for s in self.state.structures
                 if s.visible and s.model is not None]
        extra = self.frame_points()
        if extra is not None and len(extra):
            parts.append(np.asarray(extra, dtype=np.float64).reshape(-1, 3))
        return np.vstack(parts) if parts else None

    def reset_camera(self) -> None:
        """Look at the structures and the planned trajectories (or the image) from
        anterior-left-superior, all of them in the frame (VTK's ResetCamera on their bounds:
        the bounding sphere fits the view angle), never closer than MIN_CAMERA_DISTANCE."""
        points = self.framed_points()
        if points is not None:
            lo, hi = points.min(axis=0), points.max(axis=0)
            center = (lo + hi) / 2
            self.plotter.camera_position = [tuple(center + 100.0 * VIEW_DIRECTION),
                                            tuple(center), (0, 0, 1)]
            self.plotter.renderer.ResetCamera(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
            camera = self.plotter.camera
            if camera.distance < MIN_CAMERA_DISTANCE:
                camera.position = tuple(center + MIN_CAMERA_DISTANCE * VIEW_DIRECTION)
            self.plotter.reset_camera_clipping_range()
            self._camera_set = True
            return
        if self.state.volume is not None:
            lo, hi = self.state.volume.world_bounds()
            center, distance = (lo + hi) / 2, math.dist(hi, lo) * 1.6
        else:
            return
        self.plotter.camera_position = [tuple(center + distance * VIEW_DIRECTION), tuple(center),
                                        (0, 0, 1)]
        self.plotter.reset_camera_clipping_range()
        self._camera_set = True

    def screenshot(self) -> np.ndarray:
        self.flush()
        return self.plotter.screenshot(return_img=True)

    def close(self) -> bool:  # noqa: D102
        self._timer.stop()
        self.plotter.close()
        return super().close()


def _no_multisampling_in_software(plotter) -> bool:
    """4x multisampling doubles or triples a render on a software OpenGL stack (Mesa
    llvmpipe: ~60 -> ~25 ms for this scene); there the 3D view renders without it.
    True once the OpenGL renderer could be asked."""
    try:
        report = plotter.ren_win.ReportCapabilities().lower()
    except Exception:  # noqa: BLE001 - no context yet: ask again at the next render
        return False
    if "renderer string" not in report:
        return False
    if any(name in report for name in SOFTWARE_GL):
        plotter.ren_win.SetMultiSamples(0)
    return True
