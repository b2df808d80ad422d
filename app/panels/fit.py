"""Fit settings and result: method, pose, prior weight, automatic refit; residual, iterations."""

from __future__ import annotations

import math

from PySide6.QtCore import Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from app.model.state import WorkspaceState
from core.reconstruction.fit import PRIOR_WEIGHT

METHODS = (("gmm-aniso", "GMM, anisotropic (slides along surface)"),
           ("gmm-iso", "GMM, isotropic"),
           ("icp", "ICP (nearest vertex)"))
POSES = (("similarity", "Similarity (rotate, shift, scale)"),
         ("rigid", "Rigid (rotate, shift)"),
         ("none", "None (shape only)"))


class FitPanel(QWidget):
    """Settings of the live refit and a read-out of the last one."""

    settings_changed = Signal()
    refit_requested = Signal()

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        form = QFormLayout()
        self.method = QComboBox()
        for key, text in METHODS:
            self.method.addItem(text, key)
        self.pose = QComboBox()
        for key, text in POSES:
            self.pose.addItem(text, key)
        self.prior = QDoubleSpinBox()
        self.prior.setRange(0.0, 1000.0)
        self.prior.setDecimals(2)
        self.prior.setSingleStep(0.25)
        self.prior.setValue(PRIOR_WEIGHT)
        self.prior.setToolTip("Weight of the Gaussian shape prior "
                              "(0 = none; larger = closer to the mean shape)")
        for combo in (self.method, self.pose):      # long item texts must not widen the panel
            combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
            combo.setMinimumContentsLength(14)
        form.addRow("Method", self.method)
        form.addRow("Pose", self.pose)
        form.addRow("Prior weight", self.prior)
        self.pose_spread = QDoubleSpinBox()  # recon: the pose prior's spread (issue 11)
        self.pose_spread.setRange(0.0, 100.0)
        self.pose_spread.setDecimals(1)
        self.pose_spread.setSingleStep(0.5)
        self.pose_spread.setValue(1.0)
        self.pose_spread.setSpecialValueText("off")
        self.pose_spread.setSuffix(" x")
        self.pose_spread.setToolTip("Spread of the pose prior around your placement (Place here), "
                                    "times the default (3 deg, 1 mm, 3 % scale); larger lets the "
                                    "fit move the model further, off = no pose prior")
        form.addRow("Pose prior spread", self.pose_spread)
        layout.addLayout(form)
        row = QHBoxLayout()
        self.auto = QCheckBox("Refit on every edit")
        self.auto.setChecked(True)
        self.refit_button = QPushButton("Refit now")
        row.addWidget(self.auto)
        row.addStretch(1)
        row.addWidget(self.refit_button)
        layout.addLayout(row)
        self.result = QLabel()          # shown in the side panel's drawing bar (app.panels.side)
        self.result.setObjectName("fit-result")
        self.result.setWordWrap(True)
        layout.addStretch(1)
        for widget in (self.method, self.pose):
            widget.currentIndexChanged.connect(self.settings_changed)
        self.prior.valueChanged.connect(self.settings_changed)
        self.pose_spread.valueChanged.connect(self.settings_changed)
        self.refit_button.clicked.connect(self.refit_requested)
        state.events.fit_info.connect(self._show)
        self._show()

    @property
    def settings(self) -> dict:
        return {"method": self.method.currentData(), "pose": self.pose.currentData(),
                "prior_weight": float(self.prior.value()),
                "pose_spread": float(self.pose_spread.value())}

    def set_settings(self, method: str | None = None, pose: str | None = None,
                     prior_weight: float | None = None, pose_spread: float | None = None) -> None:
        for combo, key in ((self.method, method), (self.pose, pose)):
            if key is not None:
                index = combo.findData(key)
                if index < 0:
                    raise ValueError(f"unknown fit option '{key}'")
                combo.setCurrentIndex(index)
        if prior_weight is not None:
            self.prior.setValue(float(prior_weight))
        if pose_spread is not None:
            self.pose_spread.setValue(float(pose_spread))

    def _show(self) -> None:
        info = self.state.active.fit_info
        lines = []
        if info.kind != "fit" and not math.isnan(info.residual_mm):
            source = "restored from the session" if info.kind == "restored" else "after your edit"
            lines.append(f"<b>Residual</b> {info.residual_mm:.2f} mm ({source})")
        if info.n_iter:
            residual = "–" if math.isnan(info.residual_mm) else f"{info.residual_mm:.2f} mm"
            lines.append(f"<b>Residual</b> {residual} &nbsp; <b>Iterations</b> {info.n_iter}")
            state = "converged" if info.converged else "stopped"
            if info.warnings:
                state = "implausible fit" + (" (converged)" if info.converged else "")
            lines.append(f"{state}: {info.stop_reason}" if info.stop_reason else state)
        if info.warnings:
            lines.append("<span style='color:#c0392b'><b>Check this fit:</b> "
                         + "; ".join(info.warnings) + ".</span>")
            if not math.isnan(info.seconds):
                lines.append(f"fit {1000 * info.fit_seconds:.0f} ms, "
                             f"edit to display {1000 * info.seconds:.0f} ms")
        if info.out_of_date:
            lines.append("<span style='color:#d35400'><b>Out of date:</b> the points changed "
                         "since this fit. Press <i>Refit now</i>.</span>")
        if info.message:
            color = "#c0392b" if info.level == "error" else "#7f8c8d"
            lines.append(f"<span style='color:{color}'>{info.message}</span>")
        if not lines:
            lines.append("No fit yet: draw contour points in a slice view.")
        self.result.setText("<br>".join(lines))
