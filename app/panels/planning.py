"""The Planning panel: AC-PC landmarks, the active structure's target and trajectory, the
probe's-eye view, how sure the fit is, and the plan export.

Widgets and wiring only: the state is :class:`app.model.planning.PlanningState`; geometry comes from
``core.planning.frames``, the posterior from ``core.reconstruction.uncertainty``, the files from
``core.planning.report``. Points are set where the user last clicked in a slice view (the
crosshair's unsnapped point, :attr:`app.model.state.WorkspaceState.picked`: sub-voxel in the view's
plane), or typed as "x, y, z" (world RAS mm) in their fields, as in frame-based planning
software.
"""

from __future__ import annotations

import re

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QPushButton,
    QSlider,
    QTableWidget,
    QTableWidgetItem,
    QToolButton,
    QVBoxLayout,
    QWidget,
)

from app.model.planning import LANDMARK_LABELS, LANDMARKS, PlanningState
from app.views.plan_overlays import ProbeView
from core.planning.frames import format_acpc
from core.planning.lead import LEAD_TYPES
from core.planning.report import LeadChoice


def _xyz(p) -> str:
    return "not set" if p is None else f"({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f})"


def _field_text(p) -> str:
    return "" if p is None else f"{p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}"


def parse_xyz(text: str) -> np.ndarray | None:
    """World coordinates typed as "x, y, z" (commas, spaces or semicolons; brackets allowed);
    None for an empty field; ValueError for anything else."""
    parts = [p for p in re.split(r"[\s,;()\[\]]+", text.strip()) if p]
    if not parts:
        return None
    try:
        xyz = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise ValueError(f"'{text.strip()}' is not three numbers x, y, z (mm)") from None
    if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
        raise ValueError(f"'{text.strip()}' is not three numbers x, y, z (mm)")
    return xyz


def _coordinate_field(name: str, tip: str) -> QLineEdit:
    field = QLineEdit()
    field.setObjectName(name)
    field.setPlaceholderText("x, y, z mm")
    field.setToolTip(tip + ": type world coordinates (RAS mm) and press Enter")
    # wide enough for "-100.00, -100.00, -100.00": the coordinates are never cut
    field.setMinimumWidth(field.fontMetrics().horizontalAdvance("-100.00, -100.00, -100.00") + 12)
    return field


def _small_button(text: str, tip: str, slot) -> QToolButton:
    button = QToolButton()
    button.setText(text)
    button.setToolTip(tip)
    button.clicked.connect(slot)
    return button


def _spin_box(limit: float, step: float, decimals: int, suffix: str, tip: str) -> QDoubleSpinBox:
    box = QDoubleSpinBox()
    box.setRange(-limit, limit)
    box.setSingleStep(step)
    box.setDecimals(decimals)
    box.setSuffix(suffix)
    box.setToolTip(tip)
    return box


class PlanningPanel(QWidget):
    """See the module docstring. ``message(text)`` reports to the status bar."""

    message = Signal(str)
    uncertainty_toggled = Signal(bool)
    suggest_requested = Signal()
    export_requested = Signal()

    def __init__(self, planning: PlanningState, parent: QWidget | None = None):
        super().__init__(parent)
        self.planning = planning
        self.workspace = planning.workspace
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.addWidget(self._landmark_box())
        layout.addWidget(self._trajectory_box())
        layout.addWidget(self._lead_box())
        layout.addWidget(self._probe_box(), 1)
        layout.addWidget(self._uncertainty_box())
        export = QPushButton("Export plan…")
        export.setToolTip("Report (JSON), structure table (CSV), multi-label map (.seg.nrrd and "
                          "NIfTI + ITK-SNAP labels), meshes and Slicer markups into a folder")
        export.clicked.connect(self.export_requested.emit)
        layout.addWidget(export)
        planning.events.landmarks.connect(self.refresh)
        planning.events.trajectory.connect(lambda s: s is self.workspace.active and self.refresh())
        planning.events.history.connect(self._update_history)
        self.workspace.events.active.connect(self.refresh)
        self.workspace.events.model.connect(self.refresh)
        self.refresh()

    # -- construction ------------------------------------------------------------------------
    def _landmark_box(self) -> QGroupBox:
        box = QGroupBox("AC-PC landmarks")
        grid = QGridLayout(box)
        grid.setColumnStretch(1, 1)
        self.landmark_labels: dict[str, QLineEdit] = {}
        for row, name in enumerate(LANDMARKS):
            label = LANDMARK_LABELS[name]
            grid.addWidget(QLabel(label), row, 0)
            field = _coordinate_field(f"landmark-{name}", label)
            field.editingFinished.connect(lambda n=name, f=field: self._typed_landmark(n, f))
            grid.addWidget(field, row, 1)
            self.landmark_labels[name] = field
            grid.addWidget(_small_button("Set", f"Put {label} where you last clicked",
                                         lambda _=False, n=name: self.set_landmark(n)), row, 2)
            grid.addWidget(_small_button("Go", f"Move the crosshair to {label}",
                                         lambda _=False, n=name: self.go_to(
                                             self.planning.landmarks[n])), row, 3)
        self.frame_label = QLabel()
        self.frame_label.setWordWrap(True)
        grid.addWidget(self.frame_label, len(LANDMARKS), 0, 1, 4)
        row = QHBoxLayout()
        self.undo_button = QPushButton("Undo plan edit")
        self.undo_button.clicked.connect(self.planning.undo)
        self.redo_button = QPushButton("Redo")
        self.redo_button.clicked.connect(self.planning.redo)
        row.addWidget(self.undo_button)
        row.addWidget(self.redo_button)
        grid.addLayout(row, len(LANDMARKS) + 1, 0, 1, 4)
        self._update_history()
        return box

    def _trajectory_box(self) -> QGroupBox:
        box = QGroupBox("Target and trajectory")
        grid = QGridLayout(box)
        self.target_label = QLabel()
        self.target_label.setWordWrap(True)
        grid.addWidget(self.target_label, 0, 0, 1, 2)
        fields = QGridLayout()
        fields.setColumnStretch(1, 1)
        self.target_field = _coordinate_field("target-field", "Target")
        self.target_field.editingFinished.connect(
            lambda: self._typed_point(self.planning.set_target, self.target_field))
        self.entry_field = _coordinate_field("entry-field", "Entry")
        self.entry_field.editingFinished.connect(
            lambda: self._typed_point(self.planning.set_entry, self.entry_field))
        for row, (text, field) in enumerate((("Target", self.target_field),
                                             ("Entry", self.entry_field))):
            fields.addWidget(QLabel(text), row, 0)
            fields.addWidget(field, row, 1)
        grid.addLayout(fields, 1, 0, 1, 2)
        buttons = [("Target here", "Put the target where you last clicked", self.set_target_here),
                   ("Model target", "Back to the target the model defines",
                    lambda: self.planning.set_target(self.workspace.active, None)),
                   ("Entry here", "Put the entry where you last clicked", self.set_entry_here),
                   ("Clear entry", "No trajectory",
                    lambda: self.planning.set_entry(self.workspace.active, None))]
        for i, (text, tip, slot) in enumerate(buttons):
            button = QPushButton(text)
            button.setToolTip(tip)
            button.clicked.connect(slot)
            grid.addWidget(button, 2 + i // 2, i % 2)
        self.trajectory_label = QLabel()
        self.trajectory_label.setObjectName("trajectory-readout")
        self.trajectory_label.setWordWrap(True)
        self.trajectory_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        grid.addWidget(self.trajectory_label, 4, 0, 1, 2)
        self.warnings_label = QLabel()
        self.warnings_label.setObjectName("trajectory-warnings")
        self.warnings_label.setWordWrap(True)
        self.warnings_label.setStyleSheet("color: #e03030; font-weight: bold;")
        grid.addWidget(self.warnings_label, 5, 0, 1, 2)
        return box

    def _lead_box(self) -> QGroupBox:
        box = QGroupBox("Lead")
        grid = QGridLayout(box)
        grid.setColumnStretch(1, 1)
        self.lead_combo = QComboBox()
        self.lead_combo.setObjectName("lead-type")
        self.lead_combo.addItem("No lead", None)
        for key, lead in LEAD_TYPES.items():
            self.lead_combo.addItem(lead.name, key)
        self.lead_combo.setToolTip("The DBS lead on the active structure's trajectory")
        grid.addWidget(QLabel("Type"), 0, 0)
        grid.addWidget(self.lead_combo, 0, 1, 1, 3)
        self.lead_depth = _spin_box(30.0, 0.5, 1, " mm", "Tip past the target along the "
                                    "trajectory (0: tip at the target; negative: short of it)")
        self.lead_rotation = _spin_box(360.0, 15.0, 0, "°", "Directional segments: segment "
                                       "a's angle from anterior, towards the left")
        grid.addWidget(QLabel("Tip depth"), 1, 0)
        grid.addWidget(self.lead_depth, 1, 1)
        grid.addWidget(QLabel("Rotation"), 1, 2)
        grid.addWidget(self.lead_rotation, 1, 3)
        self.lead_combo.currentIndexChanged.connect(self._lead_edited)
        self.lead_depth.editingFinished.connect(self._lead_edited)
        self.lead_rotation.editingFinished.connect(self._lead_edited)
        self.contact_table = QTableWidget(0, 4)
        self.contact_table.setObjectName("contact-table")
        self.contact_table.setHorizontalHeaderLabels(["Contact", "AC-PC mm", "Structure",
                                                      "Dist. mm"])
        self.contact_table.verticalHeader().setVisible(False)
        self.contact_table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        header = self.contact_table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(2, QHeaderView.ResizeMode.Stretch)
        # as tall as its rows (set in refresh): the panel scrolls, not the table
        self.contact_table.setVerticalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.contact_table.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.contact_table.setTextElideMode(Qt.TextElideMode.ElideMiddle)
        grid.addWidget(self.contact_table, 2, 0, 1, 4)
        return box

    def _probe_box(self) -> QGroupBox:
        box = QGroupBox("Probe's-eye view")
        layout = QVBoxLayout(box)
        self.probe = ProbeView(self.planning)
        layout.addWidget(self.probe)
        row = QHBoxLayout()
        row.addWidget(QLabel("Depth"))
        self.depth_slider = QSlider(Qt.Orientation.Horizontal)
        self.depth_slider.setRange(0, 0)
        self.depth_slider.valueChanged.connect(self._on_depth)
        row.addWidget(self.depth_slider, 1)
        layout.addLayout(row)
        return box

    def _uncertainty_box(self) -> QGroupBox:
        box = QGroupBox("How sure is the fit?")
        layout = QVBoxLayout(box)
        self.uncertainty_check = QCheckBox("Colour the surface by its SD (mm)")
        self.uncertainty_check.toggled.connect(self.uncertainty_toggled.emit)
        layout.addWidget(self.uncertainty_check)
        self.uncertainty_label = QLabel("")
        self.uncertainty_label.setWordWrap(True)
        layout.addWidget(self.uncertainty_label)
        suggest = QPushButton("Suggest next slice")
        suggest.setToolTip("Move the crosshair to the slice where a new contour removes the "
                           "most uncertainty")
        suggest.clicked.connect(self.suggest_requested.emit)
        layout.addWidget(suggest)
        return box

    # -- actions -------------------------------------------------------------------------------
    def set_landmark(self, name: str, xyz=None) -> None:
        """AC, PC or the midline point at ``xyz`` (default: where the user last clicked)."""
        self.planning.set_landmark(name, self.workspace.picked if xyz is None else xyz)
        problem = self.planning.frame_problem()
        if problem and all(self.planning.landmarks[n] is not None for n in LANDMARKS):
            self.message.emit(f"AC-PC frame refused: {problem}")

    def set_target_here(self) -> None:
        self.planning.set_target(self.workspace.active, self.workspace.picked)

    def set_entry_here(self) -> None:
        self.planning.set_entry(self.workspace.active, self.workspace.picked)

    def _typed_landmark(self, name: str, field: QLineEdit) -> None:
        self._typed(field, self.planning.landmarks[name],
                    lambda xyz: self.set_landmark(name, xyz) if xyz is not None
                    else self.planning.set_landmark(name, None))

    def _typed_point(self, setter, field: QLineEdit) -> None:
        active = self.workspace.active
        current = (self.planning.targets.get(active.id) if setter == self.planning.set_target
                   else self.planning.entry_of(active))
        self._typed(field, current, lambda xyz: setter(active, xyz))

    def _typed(self, field: QLineEdit, current, apply) -> None:
        """Apply typed coordinates if they changed; a bad entry is said and put back."""
        try:
            xyz = parse_xyz(field.text())
        except ValueError as exc:
            self.message.emit(str(exc))
            self.refresh()
            return
        same = (xyz is None and current is None) or (
            xyz is not None and current is not None and np.allclose(xyz, current, atol=5e-3))
        if not same:
            apply(xyz)

    def _lead_edited(self, *_):
        """The lead widgets changed: one undoable plan edit (nothing if the same)."""
        key = self.lead_combo.currentData()
        choice = None if key is None else LeadChoice(key, self.lead_depth.value(),
                                                     self.lead_rotation.value())
        self.planning.set_lead(self.workspace.active, choice)

    def go_to(self, xyz) -> None:
        if xyz is not None:
            self.workspace.set_crosshair(xyz)

    def _on_depth(self, value: int) -> None:
        traj = self.planning.trajectory_of(self.workspace.active)
        self.probe.set_view(traj, value / 2.0)

    def _update_history(self) -> None:
        self.undo_button.setEnabled(self.planning.can_undo())
        self.redo_button.setEnabled(self.planning.can_redo())

    # -- read-outs -----------------------------------------------------------------------------
    def refresh(self) -> None:
        planning, active = self.planning, self.workspace.active
        frame = planning.frame()
        for name, field in self.landmark_labels.items():
            if not field.hasFocus():
                field.setText(_field_text(planning.landmarks[name]))
        problem = planning.frame_problem()
        self.frame_label.setText(f"AC-PC distance {frame.ac_pc_distance:.1f} mm" if frame
                                 else (problem or "")[:1].upper() + (problem or "")[1:])
        target = planning.target_of(active)
        how = "model default" if planning.target_is_default(active) else "set by you"
        text = f"{active.label}: target {_xyz(target)} ({how})"
        if target is not None and frame is not None:
            text += "\n" + format_acpc(frame.to_acpc(target))
        self.target_label.setText(text)
        for field, value in ((self.target_field, None if planning.target_is_default(active)
                              else target), (self.entry_field, planning.entry_of(active))):
            if not field.hasFocus():
                field.setText(_field_text(value))
        self.target_field.setPlaceholderText(_field_text(target) if target is not None
                                             else "x, y, z mm")
        traj = planning.trajectory_of(active)
        self.trajectory_label.setText(self._trajectory_text(traj, frame))
        length2 = 0 if traj is None else int(round(2 * (traj.length + 10.0)))
        blocked = self.depth_slider.blockSignals(True)
        self.depth_slider.setRange(0, length2)
        if traj is not None and self.depth_slider.value() == 0:
            self.depth_slider.setValue(int(round(2 * traj.length)))
        self.depth_slider.blockSignals(blocked)
        self.probe.set_view(traj, self.depth_slider.value() / 2.0)
        self.warnings_label.setText("\n".join(
            "⚠ " + w["message"][:1].upper() + w["message"][1:]
            for w in planning.warnings_of(active)))
        self._refresh_lead(active, frame)

    def _refresh_lead(self, active, frame) -> None:
        choice = self.planning.lead_of(active)
        widgets = (self.lead_combo, self.lead_depth, self.lead_rotation)
        blocked = [w.blockSignals(True) for w in widgets]
        self.lead_combo.setCurrentIndex(max(0, self.lead_combo.findData(
            None if choice is None else choice.lead)))
        if choice is not None:
            self.lead_depth.setValue(choice.depth_mm)
            self.lead_rotation.setValue(choice.rotation_deg)
        directional = choice is not None and any(n > 1 for n in LEAD_TYPES[choice.lead].levels)
        self.lead_rotation.setEnabled(directional)
        for w, b in zip(widgets, blocked):
            w.blockSignals(b)
        rows = self.planning.contact_rows(active)
        table = self.contact_table
        table.setRowCount(len(rows))
        table.horizontalHeaderItem(1).setText("AC-PC mm" if frame is not None else "World mm")
        for i, row in enumerate(rows):
            xyz = row.get("acpc", row["world"])
            # outside every structure: "outside", the nearest one in the tooltip (and the
            # distance column: positive = outside it)
            where = row["structure"] or ("outside" if row["nearest_structure"] else "—")
            distance = "" if row["distance_mm"] is None else f"{row['distance_mm']:+.1f}"
            for j, text in enumerate((row["contact"], "{:+.1f}, {:+.1f}, {:+.1f}".format(*xyz),
                                      where, distance)):
                item = QTableWidgetItem(text)
                if row["nearest_structure"]:
                    item.setToolTip(f"{'in' if row['structure'] else 'nearest'}: "
                                    f"{row['nearest_structure']}, {distance} mm from its surface")
                table.setItem(i, j, item)
        table.resizeRowsToContents()
        table.setFixedHeight(table.horizontalHeader().height() + 4 +
                             sum(table.rowHeight(i) for i in range(len(rows))) if rows
                             else table.horizontalHeader().height() + 4)

    def _trajectory_text(self, traj, frame) -> str:
        if traj is None:
            return "Set an entry point for a trajectory."
        lines = [f"Length {traj.length:.1f} mm"]
        if frame is not None:
            a = traj.angles(frame)
            lines.append(f"Ring {a['ring_deg']:.1f}°, arc {a['arc_deg']:.1f}°, "
                         f"{a['midsagittal_angle_deg']:.1f}° from the midsagittal plane")
        for s in self.workspace.structures:
            vertices = s.surface_vertices()
            if vertices is None:
                continue
            for enter, leave in traj.segments_inside(vertices, s.model.faces, 10.0):
                lines.append(f"{s.label}: {enter:.1f} → {leave:.1f} mm from the entry")
        return "\n".join(lines)

    def show_uncertainty(self, mean_sd: float, max_sd: float, target_radius: float | None,
                         notes: list[str] = ()) -> None:
        """The read-out; ``notes``: what is uncertain and why (``FitPosterior.notes``)."""
        text = f"Surface SD: mean {mean_sd:.2f} mm, max {max_sd:.2f} mm"
        if target_radius is not None:
            text += f"; target within ±{target_radius:.2f} mm (2 SD)"
        self.uncertainty_label.setText("; ".join([text, *notes]))

    def set_depth_mm(self, depth: float) -> None:
        self.depth_slider.setValue(int(round(2 * depth)))

    @property
    def depth_mm(self) -> float:
        return self.depth_slider.value() / 2.0
