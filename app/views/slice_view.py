"""One orthogonal slice view (axial, coronal or sagittal) painted with QPainter.

The slice is resampled in world coordinates by ``core.geometry.planes.SliceSampler`` and drawn as a
QImage; overlays (crosshair, the model's cross-section contours, contour points, orientation
letters, slice position) are painted on top in screen space. A view transform maps in-plane
world coordinates (U, V) in mm to widget pixels::

    x = width / 2 + (U - center_u) * scale,   y = height / 2 - (V - center_v) * scale

so that a click converts exactly to a world point ``U u + V v + depth n``.

Mouse: left button = the active tool (navigate: move the crosshair; draw: add contour points
along a click or drag, Ctrl+click deletes the nearest point; window/level: drag), Shift+left
drag = window/level in any tool, right drag = zoom, middle drag = pan, wheel = next/previous
slice, Ctrl+wheel = zoom. Keys: Page Up/Down and Up/Down arrows step slices.
"""

from __future__ import annotations

import math

import numpy as np
from PySide6.QtCore import QRectF, Qt, Signal
from PySide6.QtGui import QColor, QFont, QImage, QPainter
from PySide6.QtWidgets import QSizePolicy, QWidget

from app.model.state import FRAME_NAMES, Structure, WorkspaceState
from app.views import slice_points
from app.views.slice_overlays import (  # noqa: F401
    CONTOUR_COLOR,
    POINT_COLOR,
    VIEW_COLORS,
    label_layout,
    outlined_text,
    paint_contours,
    paint_crosshair,
    paint_labels,
    paint_points,
)
from core.geometry.planes import FRAMES, SliceImage, window_to_uint8
from core.geometry.slicing import intersect_plane

TOOLS = ("navigate", "draw", "window")
DRAW_SPACING_MM = 1.5


class SliceView(QWidget):
    """A slice of the current image on one world-aligned frame; see the module docstring."""

    hovered = Signal(object)          # world point (3,) under the cursor, or None
    activated = Signal(str)           # this view got the user's attention (frame name)
    message = Signal(str)

    def __init__(self, state: WorkspaceState, frame_name: str, parent: QWidget | None = None):
        super().__init__(parent)
        if frame_name not in FRAME_NAMES:
            raise ValueError(f"unknown view '{frame_name}', expected one of {FRAME_NAMES}")
        self.state = state
        self.frame_name = frame_name
        self.frame = FRAMES[frame_name]
        self.frame_index = FRAME_NAMES.index(frame_name)
        self.tool = "navigate"
        self.zoom = 1.0                       # relative to "fit the image in the widget"
        self.center: np.ndarray | None = None  # (U, V) at the widget centre, None = image centre
        self._slice: SliceImage | None = None
        self._qimage: QImage | None = None
        self._segments: dict[int, np.ndarray | None] = {}   # structure id -> (S, 2, 2) (U, V)
        self._drag: dict | None = None
        self._labels: tuple | None = None      # (key, label_layout) of the last paint
        # extra painters (trajectories, measurements...): callables (painter, view), called
        # after the contours, in screen space (use view.world_to_screen)
        self.overlays: list = []
        # Extensions (app.panels.editing): layers drawn over the image, under the contours
        # (``layer.paint(view, painter)``: the label fill), and extra left-button tools by
        # name (``handler.press/move/release(view, x, y, modifiers)``).
        self.layers: list = []
        self.tool_handlers: dict = {}
        self.show_outline = True
        self.colormap: np.ndarray | None = None   # (256, 3) uint8 lookup table; None = grey
        self.setMinimumSize(160, 160)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.setMouseTracking(True)
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.setAttribute(Qt.WidgetAttribute.WA_OpaquePaintEvent)
        events = state.events
        events.image.connect(self._on_image)
        events.crosshair.connect(self._on_crosshair)
        events.window.connect(self._on_window)
        events.structure_changed.connect(self._on_structure)
        events.structures.connect(self._on_surface)
        events.active.connect(self.update)
        if state.volume is not None:
            self._on_image()

    # -- data ------------------------------------------------------------------------------
    @property
    def depth(self) -> float:
        return float(self.frame.depth(self.state.crosshair))

    def _on_image(self) -> None:
        self.zoom, self.center = 1.0, None
        self._resample()
        self._on_surface()

    def _on_crosshair(self) -> None:
        if self._slice is None or abs(self._slice.depth - self.depth) > 1e-6:
            self._resample()
            self._recompute_contours()
        self.update()

    def _on_window(self) -> None:
        self._rebuild_image()
        self.update()

    def _on_surface(self) -> None:
        self._recompute_contours()
        self.update()

    def _on_structure(self, structure: Structure, what: str) -> None:
        if what in ("surface", "model"):
            self._recompute_contours(structure)
            self.update()
        elif what in ("points", "properties"):
            self.update()

    @property
    def _segments_uv(self) -> np.ndarray | None:
        """The active structure's cross-section segments (S, 2, 2) in (U, V), or None."""
        return self._segments.get(self.state.active.id)

    def _resample(self) -> None:
        if self.state.sampler is None:
            self._slice, self._qimage = None, None
            return
        self._depth_range = self.state.sampler.depth_range(self.frame)
        self._slice = self.state.sampler.sample(self.frame, self.depth)
        self._rebuild_image()

    def _rebuild_image(self) -> None:
        if self._slice is None:
            return
        grey = window_to_uint8(self._slice.data, self.state.window, self.state.level)
        grey = np.ascontiguousarray(grey)
        h, w = grey.shape
        if self.colormap is not None:       # image colour map (app.panels.navigation)
            rgb = np.ascontiguousarray(self.colormap[grey])
            self._qimage = QImage(rgb.data, w, h, 3 * w, QImage.Format.Format_RGB888).convertToFormat(
                QImage.Format.Format_RGB32)
            return
        image = QImage(grey.data, w, h, w, QImage.Format.Format_Grayscale8)
        # own the pixels (grey goes out of scope); RGB32 is blitted without per-paint conversion
        self._qimage = image.convertToFormat(QImage.Format.Format_RGB32)

    def _recompute_contours(self, structure: Structure | None = None) -> None:
        """Cross-sections of one structure's surface with this slice (all if None)."""
        structures = self.state.structures if structure is None else [structure]
        if structure is None:
            self._segments = {}
        n = np.asarray(self.frame.n)
        for s in structures:
            vertices = s.surface_vertices()
            if vertices is None:
                self._segments[s.id] = None
                continue
            segments = intersect_plane(vertices, s.model.faces, self.depth * n, n)
            self._segments[s.id] = (segments @ self.frame.axes[:2].T) if len(segments) else None

    # -- view transform ----------------------------------------------------------------------
    def _base(self) -> tuple[float, np.ndarray]:
        """Scale (px/mm) and centre (U, V) of the current view."""
        if self._slice is None:
            return 1.0, np.zeros(2)
        left, right, top, bottom = self._slice.extent()
        fit = min(self.width() / max(right - left, 1e-6), self.height() / max(top - bottom, 1e-6))
        center = (self.center if self.center is not None
                  else np.array([(left + right) / 2, (top + bottom) / 2]))
        return fit * 0.98 * self.zoom, center

    def plane_to_screen(self, uv: np.ndarray) -> np.ndarray:
        """In-plane (U, V) mm (..., 2) -> widget pixel coordinates (x, y) (..., 2)."""
        scale, center = self._base()
        uv = np.asarray(uv, dtype=np.float64)
        x = self.width() / 2 + (uv[..., 0] - center[0]) * scale
        y = self.height() / 2 - (uv[..., 1] - center[1]) * scale
        return np.stack([x, y], axis=-1)

    def screen_to_plane(self, xy: np.ndarray) -> np.ndarray:
        scale, center = self._base()
        xy = np.asarray(xy, dtype=np.float64)
        u = center[0] + (xy[..., 0] - self.width() / 2) / scale
        v = center[1] - (xy[..., 1] - self.height() / 2) / scale
        return np.stack([u, v], axis=-1)

    def screen_to_world(self, x: float, y: float) -> np.ndarray:
        """World point (3,) on this slice under widget pixel (x, y)."""
        u, v = self.screen_to_plane(np.array([x, y], dtype=np.float64))
        return self.frame.to_world(np.array([u, v, self.depth]))

    def world_to_screen(self, xyz: np.ndarray) -> np.ndarray:
        """Widget pixel (x, y) of world point(s) (..., 3) projected on this slice."""
        return self.plane_to_screen(self.frame.to_plane(xyz)[..., :2])

    def zoom_at(self, x: float, y: float, factor: float) -> None:
        """Zoom by ``factor`` keeping the point under widget pixel (x, y) where it is."""
        before = self.screen_to_plane(np.array([x, y], dtype=np.float64))
        self.zoom = float(np.clip(self.zoom * factor, 0.2, 40))
        scale, center = self._base()
        after = self.screen_to_plane(np.array([x, y], dtype=np.float64))
        self.center = center + (before - after)
        self.update()

    def reset_view(self) -> None:
        self.zoom, self.center = 1.0, None
        self.update()

    # -- painting ----------------------------------------------------------------------------
    def paintEvent(self, event) -> None:  # noqa: N802 - Qt API
        painter = QPainter(self)
        painter.fillRect(self.rect(), QColor(0, 0, 0))
        if self._slice is None or self._qimage is None:
            painter.setPen(QColor(160, 160, 160))
            painter.drawText(self.rect(), Qt.AlignmentFlag.AlignCenter, "No image")
            painter.end()
            return
        left, right, top, bottom = self._slice.extent()
        (x0, y0), (x1, y1) = self.plane_to_screen(np.array([[left, top], [right, bottom]]))
        painter.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform, False)
        painter.drawImage(QRectF(x0, y0, x1 - x0, y1 - y0), self._qimage)
        for layer in self.layers:
            layer.paint(self, painter)
        paint_crosshair(self, painter)
        painter.setRenderHint(QPainter.RenderHint.Antialiasing, True)
        paint_points(self, painter)
        paint_contours(self, painter)
        for overlay in self.overlays:
            overlay(painter, self)
        paint_labels(self, painter)
        painter.end()

    _text = staticmethod(outlined_text)     # for other overlays (measurements)

    def label_layout(self) -> dict[str, tuple[QRectF, str, QColor, QFont]]:
        """Where each overlay text goes (see :func:`label_layout`); cached until the view's
        size, slice, window/level or the image's orientation status change."""
        key = (self.width(), self.height(), round(self.depth, 6), self.state.window,
               self.state.level, self.state.orientation_known, id(self.state.sampler))
        if self._labels is None or self._labels[0] != key:
            self._labels = (key, label_layout(self))
        return self._labels[1]

    def _step(self) -> float:
        return self.state.sampler.step(self.frame) if self.state.sampler else 1.0

    # -- interaction -------------------------------------------------------------------------
    def set_tool(self, tool: str) -> None:
        if tool in self.tool_handlers:
            self.tool = tool
            self.setCursor(Qt.CursorShape.CrossCursor)
            return
        if tool not in TOOLS:
            raise ValueError(f"unknown tool '{tool}', expected one of {TOOLS}")
        self.tool = tool
        self.setCursor(Qt.CursorShape.CrossCursor if tool == "draw" else Qt.CursorShape.ArrowCursor)

    def _event_xy(self, event) -> tuple[float, float]:
        p = event.position()
        return float(p.x()), float(p.y())

    def mousePressEvent(self, event) -> None:  # noqa: N802
        if self._slice is None:
            return
        self.activated.emit(self.frame_name)
        x, y = self._event_xy(event)
        button, mods = event.button(), event.modifiers()
        if button == Qt.MouseButton.LeftButton and self.tool in self.tool_handlers:
            self._drag = {"kind": "tool", "handler": self.tool_handlers[self.tool]}
            self._drag["handler"].press(self, x, y, mods)
        elif button == Qt.MouseButton.LeftButton:
            if mods & Qt.KeyboardModifier.ShiftModifier or self.tool == "window":
                self._drag = {"kind": "window", "xy": (x, y), "wl": (self.state.window, self.state.level)}
            elif self.tool == "draw":
                if mods & Qt.KeyboardModifier.ControlModifier:
                    self.delete_point_near(x, y)
                else:
                    self._drag = {"kind": "draw", "last": self.add_point_at(x, y, checkpoint=True)}
            else:
                self._drag = {"kind": "navigate"}
                self.state.set_crosshair(self.screen_to_world(x, y))
        elif button == Qt.MouseButton.RightButton:
            self._drag = {"kind": "zoom", "xy": (x, y), "zoom": self.zoom}
        elif button == Qt.MouseButton.MiddleButton:
            self._drag = {"kind": "pan", "xy": (x, y), "center": self._base()[1].copy()}

    def mouseMoveEvent(self, event) -> None:  # noqa: N802
        x, y = self._event_xy(event)
        if self._slice is not None:
            self.hovered.emit(self.screen_to_world(x, y))
        drag = self._drag
        if drag is None:
            return
        kind = drag["kind"]
        if kind == "tool":
            drag["handler"].move(self, x, y, event.modifiers())
        elif kind == "navigate":
            self.state.set_crosshair(self.screen_to_world(x, y))
        elif kind == "draw":
            world = self.screen_to_world(x, y)
            if drag["last"] is None or math.dist(world, drag["last"]) >= DRAW_SPACING_MM:
                drag["last"] = self.add_point_at(x, y, checkpoint=drag["last"] is None,
                                                 stroke="click" if drag["last"] is None else "drag")
        elif kind == "window":
            dx, dy = x - drag["xy"][0], y - drag["xy"][1]
            window0, level0 = drag["wl"]
            span = max(self.state.data_range[1] - self.state.data_range[0], 1e-6)
            self.state.set_window(max(window0 + dx * span / 400, span / 1000), level0 - dy * span / 400)
        elif kind == "zoom":
            dy = y - drag["xy"][1]
            self.zoom = float(np.clip(drag["zoom"] * np.exp(-dy / 150), 0.2, 40))
            self.update()
        elif kind == "pan":
            scale, _ = self._base()
            dx, dy = x - drag["xy"][0], y - drag["xy"][1]
            self.center = drag["center"] - np.array([dx, -dy]) / scale
            self.update()

    def mouseReleaseEvent(self, event) -> None:  # noqa: N802
        drag, self._drag = self._drag, None
        if drag is not None and drag["kind"] == "tool":
            drag["handler"].release(self, *self._event_xy(event), event.modifiers())

    def leaveEvent(self, event) -> None:  # noqa: N802
        self.hovered.emit(None)

    def wheelEvent(self, event) -> None:  # noqa: N802
        delta = event.angleDelta().y()
        if delta == 0:
            return
        if event.modifiers() & Qt.KeyboardModifier.ControlModifier:
            self.zoom_at(*self._event_xy(event), 1.15 if delta > 0 else 1 / 1.15)
        else:
            self.state.step_slice(self.frame_name, 1 if delta > 0 else -1)

    def keyPressEvent(self, event) -> None:  # noqa: N802
        key = event.key()
        if key in (Qt.Key.Key_PageUp, Qt.Key.Key_Up):
            self.state.step_slice(self.frame_name, 1)
        elif key in (Qt.Key.Key_PageDown, Qt.Key.Key_Down):
            self.state.step_slice(self.frame_name, -1)
        else:
            super().keyPressEvent(event)

    def focusInEvent(self, event) -> None:  # noqa: N802
        self.activated.emit(self.frame_name)
        self.update()
        super().focusInEvent(event)

    def focusOutEvent(self, event) -> None:  # noqa: N802
        self.update()
        super().focusOutEvent(event)

    # -- contour points (app.views.slice_points) ------------------------------------------
    def add_point_at(self, x: float, y: float, checkpoint: bool = True,
                     stroke: str = "click") -> np.ndarray | None:
        """Add a contour point on this slice under widget pixel (x, y); returns it (world)."""
        return slice_points.add_point_at(self, x, y, checkpoint, stroke)

    def points_here(self) -> np.ndarray:
        return slice_points.points_here(self)

    def point_near(self, x: float, y: float, radius_px: float = 8.0) -> int | None:
        return slice_points.point_near(self, x, y, radius_px)

    def delete_point_near(self, x: float, y: float) -> bool:
        return slice_points.delete_point_near(self, x, y)
