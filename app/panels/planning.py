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
from PySide6.QtWidgets import (QCheckBox, QGridLayout, QGroupBox, QHBoxLayout, QLabel,
                               QLineEdit, QPushButton, QSlider, QToolButton, QVBoxLayout,
                               QWidget)

from app.model.planning import LANDMARK_LABELS, LANDMARKS, PlanningState
from app.views.plan_overlays import ProbeView
from core.planning.frames import format_acpc


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

    def show_uncertainty(self, mean_sd: float, max_sd: float, target_radius: float | None) -> None:
        text = f"Surface SD: mean {mean_sd:.2f} mm, max {max_sd:.2f} mm"
        if target_radius is not None:
            text += f"; target within ±{target_radius:.2f} mm (2 SD)"
        self.uncertainty_label.setText(text)

    def set_depth_mm(self, depth: float) -> None:
        self.depth_slider.setValue(int(round(2 * depth)))

    @property
    def depth_mm(self) -> float:
        return self.depth_slider.value() / 2.0
