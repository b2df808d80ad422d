"""Ruler and angle measurement in the slice views (issue 17).

Tools: *Ruler* (M): drag from one end to the other; *Angle* (A): click the first point, the
vertex, then the second point. Each measurement is drawn on the slice it was made on, with
its value (mm or degrees, ``core.planning.measure``); they are kept with the session and exported
with the points (``measurements.csv`` and Slicer ``measurements.mrk.json``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QColor, QPainter, QPen

from app.actions import add_help_shortcuts
from core.planning.measure import (
    Measurement,
    measurements_from_json,
    measurements_to_json,
    save_measurements,
)

COLOR = QColor(120, 255, 140)
TOOLS = {"ruler": ("Ruler", "M", "Ruler: drag from one end to the other to measure a length"),
         "angle": ("Angle", "A", "Angle: click the first point, the vertex, then the second")}
SHORTCUTS = [("M / A", "Tool: ruler (drag) / angle (three clicks) in a slice")]


class Measurements:
    """The workspace's measurements (plain list, with a change callback for the views)."""

    def __init__(self, changed=lambda: None):
        self.items: list[Measurement] = []
        self.pending: list[np.ndarray] = []      # points of a measurement being drawn
        self.pending_frame = ""
        self._changed = changed

    def add(self, m: Measurement) -> None:
        self.items.append(m)
        self._changed()

    def clear(self) -> None:
        self.items.clear()
        self.pending.clear()
        self._changed()

    def set_items(self, items: list[Measurement]) -> None:
        self.items = list(items)
        self._changed()


def _on_slice(view, frame: str, depth: float) -> bool:
    return frame == view.frame_name and abs(depth - view.depth) <= view._step() / 2


class RulerTool:
    def __init__(self, store: Measurements):
        self.store = store

    def press(self, view, x, y, modifiers) -> None:
        world = view.screen_to_world(x, y)
        self.store.pending = [world, world.copy()]
        self.store.pending_frame = view.frame_name
        self.store._changed()

    def move(self, view, x, y, modifiers) -> None:
        if len(self.store.pending) == 2:
            self.store.pending[1] = view.screen_to_world(x, y)
            self.store._changed()

    def release(self, view, x, y, modifiers) -> None:
        if len(self.store.pending) != 2:
            return
        a, b = self.store.pending[0], view.screen_to_world(x, y)
        self.store.pending = []
        ruler = Measurement("ruler", [a, b], view.frame_name, view.depth)
        if ruler.value > 1e-6:
            self.store.add(ruler)
        else:
            self.store._changed()


class AngleTool:
    def __init__(self, store: Measurements):
        self.store = store

    def press(self, view, x, y, modifiers) -> None:
        world = view.screen_to_world(x, y)
        if self.store.pending_frame != view.frame_name or len(self.store.pending) >= 3:
            self.store.pending = []
        self.store.pending_frame = view.frame_name
        self.store.pending.append(world)
        if len(self.store.pending) == 3:
            points, self.store.pending = self.store.pending, []
            self.store.add(Measurement("angle", points, view.frame_name, view.depth))
        else:
            self.store._changed()

    def move(self, view, x, y, modifiers) -> None:
        pass

    def release(self, view, x, y, modifiers) -> None:
        pass


def paint_measurements(store: Measurements):
    """A ``SliceView.overlays`` painter ``(painter, view)`` for the measurements."""

    def paint(painter: QPainter, view) -> None:
        items = [(m.points, m.label()) for m in store.items if _on_slice(view, m.frame, m.depth)]
        if store.pending and store.pending_frame == view.frame_name:
            items.append((np.array(store.pending), ""))
        for points, label in items:
            xy = view.world_to_screen(points)
            painter.setPen(QPen(COLOR, 1.6))
            painter.drawPolyline([QPointF(x, y) for x, y in xy])
            painter.setBrush(COLOR)
            for x, y in xy:
                painter.drawEllipse(QPointF(x, y), 2.5, 2.5)
            painter.setBrush(Qt.BrushStyle.NoBrush)
            if label:
                anchor = xy[1] if len(xy) == 3 else xy.mean(axis=0)
                view._text(painter, QRectF(anchor[0] + 6, anchor[1] - 18, 90, 18),
                           Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignVCenter,
                           label, COLOR)

    return paint


class MeasurementTools:
    """The window's feature ``"measurements"``: the ruler and angle tools, their painting,
    *View > Clear measurements*, session keys and export; the measurements in ``store``."""

    def __init__(self, window):
        views = list(window.workspace.views.values())
        self.store = store = Measurements(lambda: [v.update() for v in views])
        handlers = {"ruler": RulerTool(store), "angle": AngleTool(store)}
        painter = paint_measurements(store)
        for view in views:
            view.tool_handlers.update(handlers)
            view.overlays.append(painter)
        window.tools.add(TOOLS)
        add_help_shortcuts(SHORTCUTS)
        self.clear = window.registry.add("clear-measurements", "Clear measurements", store.clear,
                                         None, "Remove every ruler and angle")
        window.registry.place("view", "clear-measurements")
        window.sessions.info_providers["measurements"] = lambda: measurements_to_json(store.items)
        window.sessions.info_readers["measurements"] = lambda data: store.set_items(
            measurements_from_json(data))
        def outputs(folder: Path) -> list[Path]:
            return [folder / name for name in ("measurements.csv", "measurements.mrk.json")
                    ] if store.items else []

        window.exports.extra_exports.append(
            (lambda folder: [save_measurements(p, store.items) for p in outputs(folder)], outputs))
