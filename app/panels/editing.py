"""The "Label map" side-panel box and the tools that edit a result by hand (issue 17).

:class:`Editing` (the window's feature ``"editing"``) adds, without the window knowing
their details:

- the filled label overlay on every slice view (:class:`app.views.label_overlay.LabelOverlay`)
  with its display options (fill, outline, opacity) in a side-panel box;
- the volume of the active structure's label map (mm^3, with the voxel count and the manual
  edits) always visible in the status bar;
- three tools in the tool group: Brush (B), Eraser (X) and Move model (G)
  (:mod:`app.views.edit_tools`), with the brush radius and *Clear edits* in the box.
"""

from __future__ import annotations

from PySide6.QtCore import Qt, QTimer
from PySide6.QtWidgets import (
    QCheckBox,
    QDoubleSpinBox,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSlider,
    QVBoxLayout,
    QWidget,
)

from app.actions import add_help_shortcuts
from app.views.edit_tools import BrushTool, MoveTool
from app.views.label_overlay import LabelOverlay

TOOLS = {"brush": ("Brush", "B", "Brush: drag to paint the label map by hand (Ctrl: erase)"),
         "eraser": ("Eraser", "X", "Eraser: drag to erase the label map by hand (Ctrl: paint)"),
         "move": ("Move model", "G", "Move model: drag = translate, Ctrl+drag = rotate, "
                                     "Shift+drag = scale (about the model's centre)")}
SHORTCUTS = [("B / X", "Tool: brush / eraser on the label map (Ctrl: the other one)"),
             ("G", "Tool: move the model (drag translate, Ctrl rotate, Shift scale)")]


def volume_text(overlay: LabelOverlay) -> str:
    """"Caudate: 4,118 mm³ (4118 voxels, +29/−3 by hand)" for the active structure."""
    s = overlay.state.active
    cached = overlay.label_map(s) if (s.model is not None or s.edits) else None
    if cached is None:
        return "Volume: —"
    text = f"{s.label}: {cached.volume_mm3:,.0f} mm³ ({cached.voxels} voxels"
    if cached.edits:
        text += f", +{len(cached.edits.added)}/−{len(cached.edits.removed)} by hand"
    return text + ")"


class VolumeReadout(QLabel):
    """The active structure's label-map volume, refreshed after each change (coalesced)."""

    def __init__(self, overlay: LabelOverlay, parent: QWidget | None = None):
        super().__init__("Volume: —", parent)
        self.setObjectName("volume_readout")
        self.setToolTip("Volume of the active structure's label map as exported: voxels "
                        "inside the fitted surface, with the manual brush/eraser edits.")
        self.overlay = overlay
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.setInterval(0)
        self._timer.timeout.connect(self.refresh)
        events = overlay.state.events
        for event in (events.image, events.active, events.structures):
            event.connect(self.schedule)
        events.structure_changed.connect(self._on_structure)

    def _on_structure(self, structure, what: str) -> None:
        if what in ("surface", "model", "edits", "properties"):
            self.schedule()

    def schedule(self, *_) -> None:
        self._timer.start()

    def refresh(self) -> None:
        self.setText(volume_text(self.overlay))


class LabelPanel(QWidget):
    """Fill / outline / opacity of the label overlay, the edit tools and the brush radius."""

    def __init__(self, window, overlay: LabelOverlay, brush: BrushTool, eraser: BrushTool):
        super().__init__(window)
        self.overlay = overlay
        self.brushes = (brush, eraser)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        row = QHBoxLayout()
        self.fill = QCheckBox("Fill")
        self.fill.setChecked(overlay.fill)
        self.fill.setToolTip("Show the label map filled (what is exported).")
        self.outline = QCheckBox("Outline")
        self.outline.setChecked(overlay.outline)
        self.outline.setToolTip("Show the model surface's cross-section outline.")
        self.opacity = QSlider(Qt.Orientation.Horizontal)
        self.opacity.setObjectName("label_opacity")
        self.opacity.setRange(0, 100)
        self.opacity.setValue(int(round(100 * overlay.opacity)))
        self.opacity.setToolTip("Opacity of the filled label map.")
        row.addWidget(self.fill)
        row.addWidget(self.outline)
        row.addWidget(QLabel("Opacity"))
        row.addWidget(self.opacity, 1)
        layout.addLayout(row)
        row = QHBoxLayout()
        self.tool_buttons = {}
        for tool in TOOLS:
            action = window.tools.actions[tool]
            button = QPushButton(action.text())
            button.setCheckable(True)
            button.setToolTip(action.toolTip())
            button.clicked.connect(action.trigger)
            action.toggled.connect(button.setChecked)
            row.addWidget(button)
            self.tool_buttons[tool] = button
        layout.addLayout(row)
        row = QHBoxLayout()
        row.addWidget(QLabel("Brush radius"))
        self.radius = QDoubleSpinBox()
        self.radius.setObjectName("brush_radius")
        self.radius.setRange(0.1, 50.0)
        self.radius.setSingleStep(0.5)
        self.radius.setSuffix(" mm")
        self.radius.setValue(brush.radius_mm)
        row.addWidget(self.radius, 1)
        self.clear = QPushButton("Clear edits")
        self.clear.setToolTip("Remove every manual edit of the active structure (undoable).")
        row.addWidget(self.clear)
        layout.addLayout(row)
        self.volume = VolumeReadout(overlay)
        self.volume.setWordWrap(True)
        layout.addWidget(self.volume)

        self.fill.toggled.connect(overlay.set_fill)
        self.outline.toggled.connect(overlay.set_outline)
        self.opacity.valueChanged.connect(lambda v: overlay.set_opacity(v / 100))
        self.radius.valueChanged.connect(self._set_radius)
        self.clear.clicked.connect(self._clear_edits)
        overlay.events.display.connect(self._follow)

    def _set_radius(self, value: float) -> None:
        for tool in self.brushes:
            tool.radius_mm = float(value)

    def _clear_edits(self) -> None:
        s = self.overlay.state.active
        if s.edits:
            s.set_edits(None)

    def _follow(self) -> None:
        for widget, value in ((self.fill, self.overlay.fill), (self.outline, self.overlay.outline)):
            widget.blockSignals(True)
            widget.setChecked(value)
            widget.blockSignals(False)
        self.opacity.blockSignals(True)
        self.opacity.setValue(int(round(100 * self.overlay.opacity)))
        self.opacity.blockSignals(False)


class Editing:
    """The window's feature ``"editing"``: the label ``overlay`` on every slice view, its side
    panel box (``panel``), the status bar's ``volume_label`` and the brush, eraser and move
    tools (see the module docstring)."""

    def __init__(self, window):
        self.overlay = overlay = LabelOverlay(window.state)
        brush, eraser, move = BrushTool(), BrushTool(erase=True), MoveTool()
        handlers = {"brush": brush, "eraser": eraser, "move": move}
        for view in window.workspace.views.values():
            view.layers.append(overlay)
            view.tool_handlers.update(handlers)
        window.tools.add(TOOLS, menu_before="view.tools-end")
        add_help_shortcuts(SHORTCUTS)
        self.panel = LabelPanel(window, overlay, brush, eraser)
        box = QGroupBox("Label map")
        box_layout = QVBoxLayout(box)
        box_layout.setContentsMargins(2, 2, 2, 2)
        box_layout.addWidget(self.panel)
        window.side_dock.panel.layout().insertWidget(1, box)
        window.side_dock.boxes["Label map"] = box
        self.volume_label = VolumeReadout(overlay)
        window.statusBar().addPermanentWidget(self.volume_label)
        window.tabs.segment_shown.connect(self.volume_label.setVisible)   # not in the Build tab
        views = list(window.workspace.views.values())
        overlay.events.display.connect(lambda: [v.update() for v in views])
        window.state.events.structure_changed.connect(
            lambda s, what: [v.update() for v in views] if what == "edits" else None)
        window.state.events.image.connect(lambda: _drop_stale_edits(window.state))
        window.sessions.info_providers["manual_edits"] = lambda: edits_document(window.state)
        window.sessions.info_readers["manual_edits"] = lambda doc: apply_edits_document(
            window.state, doc)


def edits_document(state) -> dict:
    """The structures' manual edits for a session file: {structure index: edits JSON}."""
    return {str(i): s.edits.to_json() for i, s in enumerate(state.structures) if s.edits}


def apply_edits_document(state, document: dict | None) -> None:
    """Restore :func:`edits_document` (no undo step); ValueError for edits on another grid."""
    from core.geometry.labelmap import ManualEdits

    shape = None if state.volume is None else state.volume.shape
    for i, s in enumerate(state.structures):
        data = (document or {}).get(str(i))
        edits = None if data is None else ManualEdits.from_json(data, shape)
        if edits is not s.edits:
            s.set_edits(edits, checkpoint=False)


def _drop_stale_edits(state) -> None:
    """Edits painted on another image's grid do not apply to the new one."""
    shape = None if state.volume is None else state.volume.shape
    for s in state.structures:
        if s.edits is not None and s.edits.shape != shape:
            s.set_edits(None, checkpoint=False)
