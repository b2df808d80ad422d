"""Left-button tools of the slice views for correcting a result by hand.

- :class:`BrushTool` paints the active structure's label map (or erases it: the eraser, or
  Ctrl with the brush): a round brush of ``radius_mm`` on the slice, one slice thick, in
  strokes that join the mouse positions (``core.geometry.labelmap.brush_voxels``). A stroke is one undo
  step; the edits are kept apart from the model's result (``Structure.edits``), so refits keep
  them, sessions store them and exports mark them.
- :class:`MoveTool` moves the model by hand: drag = translate in the slice, Ctrl+drag = rotate
  about the slice normal through the model's centre, Shift+drag = scale about the centre
  (``core.registration.handles.drag_transform``). A drag is one undo step; the new pose becomes the
  placement the pose prior of the next fit is centred on.

Each tool implements ``press/move/release(view, x, y, modifiers)`` for
:attr:`app.views.slice_view.SliceView.tool_handlers`.
"""

from __future__ import annotations

import math

import numpy as np
from PySide6.QtCore import Qt

from core.geometry.labelmap import ManualEdits, brush_voxels
from core.registration.handles import drag_transform


def _editable(view) -> object | None:
    """The active structure if it can be edited here, else None (with a message)."""
    s = view.state.active
    if s.locked or not s.visible:
        view.message.emit(f"{s.label} is {'locked' if s.locked else 'hidden'}: unlock or show "
                          "it in the structure list to edit it")
        return None
    return s


class BrushTool:
    """Brush (``erase=False``) or eraser on the active structure's label map."""

    def __init__(self, erase: bool = False, radius_mm: float = 2.0):
        self.erase = erase
        self.radius_mm = float(radius_mm)
        self._last: np.ndarray | None = None
        self._erasing = erase

    def press(self, view, x: float, y: float, modifiers) -> None:
        self._last = None
        self._erasing = self.erase != bool(modifiers & Qt.KeyboardModifier.ControlModifier)
        self._dab(view, view.screen_to_world(x, y), first=True)

    def move(self, view, x: float, y: float, modifiers) -> None:
        if self._last is not None:
            self._dab(view, view.screen_to_world(x, y), first=False)

    def release(self, view, x: float, y: float, modifiers) -> None:
        self._last = None

    def _dab(self, view, world: np.ndarray, first: bool) -> None:
        volume = view.state.volume
        s = _editable(view) if first else view.state.active
        if volume is None or s is None:
            return
        # join the previous and the current position with dabs half a radius apart
        start = world if self._last is None else self._last
        steps = max(1, int(math.ceil(math.dist(start, world) / max(self.radius_mm / 2, 0.1))))
        centres = start + (world - start) * (np.arange(1, steps + 1) / steps)[:, None]
        if self._last is None:
            centres = world[None]
        voxels = np.concatenate([brush_voxels(volume.shape, volume.affine, c, view.frame.n,
                                              self.radius_mm, view._step()) for c in centres])
        self._last = world
        edits = s.edits if s.edits is not None and s.edits.shape == volume.shape else \
            ManualEdits(volume.shape)
        new = edits.paint(voxels, erase=self._erasing)
        if first or not np.array_equal(new.added, edits.added) or \
                not np.array_equal(new.removed, edits.removed):
            s.set_edits(new, checkpoint=first)


class MoveTool:
    """Translate / rotate / scale the active structure's model by dragging in a slice."""

    def __init__(self):
        self._drag: dict | None = None

    @staticmethod
    def kind(modifiers) -> str:
        if modifiers & Qt.KeyboardModifier.ControlModifier:
            return "rotate"
        if modifiers & Qt.KeyboardModifier.ShiftModifier:
            return "scale"
        return "translate"

    def press(self, view, x: float, y: float, modifiers) -> None:
        s = _editable(view)
        if s is None or s.model is None:
            self._drag = None
            return
        s.checkpoint()
        vertices = s.surface_vertices()
        self._drag = {"structure": s, "kind": self.kind(modifiers), "pose": s.pose.copy(),
                      "start": view.screen_to_world(x, y), "center": vertices.mean(axis=0)}

    def move(self, view, x: float, y: float, modifiers) -> None:
        drag = self._drag
        if drag is None:
            return
        m = drag_transform(drag["kind"], drag["start"], view.screen_to_world(x, y),
                           drag["center"], view.frame.n)
        drag["structure"].set_pose(m @ drag["pose"], checkpoint=False, edited=False)

    def release(self, view, x: float, y: float, modifiers) -> None:
        drag, self._drag = self._drag, None
        if drag is not None:  # the final pose: now the fit may follow (edited)
            m = drag_transform(drag["kind"], drag["start"], view.screen_to_world(x, y),
                               drag["center"], view.frame.n)
            drag["structure"].set_pose(m @ drag["pose"], checkpoint=False, edited=True)
