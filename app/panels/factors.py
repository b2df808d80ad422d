"""Deformation factor sliders: one per factor, over +-3 standard deviations of its coefficient.

Moving a slider sets that coefficient to ``value * sqrt(coef_var[m])`` and redraws the surface
(no refit: this is the manual edit). With a local-support model (SPLOCS, LSF, Varimax) each
slider moves one region only. The sliders follow the state when a refit changes the
coefficients (signals blocked while doing so, so there is no feedback loop). One slider drag
is one undo step.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QGridLayout, QLabel, QPushButton, QScrollArea, QSlider, QVBoxLayout, QWidget

from app.model.state import WorkspaceState

STEPS_PER_SD = 100
MAX_SD = 3.0


class FactorsPanel(QWidget):
    """Sliders for the coefficients of the current model.

    ``factor_touched(index)`` is emitted when a slider is pressed or moved (-1 after Reset),
    so that the 3D view can show the region that factor moves.
    """

    factor_touched = Signal(int)

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        self.sliders: list[QSlider] = []
        self.value_labels: list[QLabel] = []
        self.share_labels: list[QLabel] = []     # each factor's explained share (issue 17, 4)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        self.summary = QLabel("No model loaded")
        self.summary.setWordWrap(True)
        layout.addWidget(self.summary)
        self.scroll = QScrollArea()
        self.scroll.setWidgetResizable(True)
        self.container = QWidget()
        self.grid = QGridLayout(self.container)
        self.grid.setContentsMargins(0, 0, 0, 0)
        self.grid.setVerticalSpacing(2)
        self.scroll.setWidget(self.container)
        layout.addWidget(self.scroll, 1)
        self.reset_button = QPushButton("Reset to mean shape")
        self.reset_button.setToolTip("Set every coefficient to 0 (undoable)")
        self.reset_button.clicked.connect(self.reset)
        layout.addWidget(self.reset_button)
        state.events.model.connect(self._rebuild)
        state.events.surface.connect(self._sync)
        self._rebuild()

    def _rebuild(self) -> None:
        while self.grid.count():
            item = self.grid.takeAt(0)
            if item.widget() is not None:
                item.widget().deleteLater()
        self.sliders, self.value_labels, self.share_labels = [], [], []
        model = self.state.active.model
        if model is None:
            self.summary.setText("No model loaded")
            self.reset_button.setEnabled(False)
            return
        self.reset_button.setEnabled(True)
        share = model.explained_variance_share()          # the builder's read-out (core)
        of_what = ("of the training shapes' variance"
                   if "explained_variance_ratio" in model.info else "of the model's variance")
        head = (f"{model.method.upper()} model: {model.n_factors} factors, "
                f"{model.n_vertices} vertices")
        if "explained_variance_ratio" in model.info:
            self.summary.setText(f"{head}; together they explain {100 * float(share.sum()):.1f}% "
                                 f"{of_what}. Sliders span \u00b13 SD; the percentage is each "
                                 "factor's share.")
        else:
            self.summary.setText(f"{head}. Sliders span \u00b13 SD; the percentage is each "
                                 "factor's share of the model's own variance (this file does "
                                 "not store the training shapes' variance).")
        for m in range(model.n_factors):
            name = QLabel(f"{m + 1}")
            tip = (f"Factor {m + 1}: explains {100 * share[m]:.1f}% {of_what}; "
                   f"SD {np.sqrt(model.coef_var[m]):.3g}")
            name.setToolTip(tip)
            explained = QLabel(f"{100 * share[m]:.1f}%")
            explained.setObjectName(f"factor-share-{m}")
            explained.setToolTip(tip)
            explained.setMinimumWidth(40)
            explained.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
            slider = QSlider(Qt.Orientation.Horizontal)
            slider.setRange(int(-MAX_SD * STEPS_PER_SD), int(MAX_SD * STEPS_PER_SD))
            slider.setPageStep(STEPS_PER_SD // 2)
            slider.setObjectName(f"factor-{m}")
            slider.valueChanged.connect(lambda value, m=m: self._on_slider(m, value))
            slider.sliderPressed.connect(self.state.active.checkpoint)
            slider.sliderPressed.connect(lambda m=m: self.factor_touched.emit(m))
            value = QLabel("+0.00")
            value.setMinimumWidth(44)
            value.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
            self.grid.addWidget(name, m, 0)
            self.grid.addWidget(slider, m, 1)
            self.grid.addWidget(value, m, 2)
            self.grid.addWidget(explained, m, 3)
            self.sliders.append(slider)
            self.value_labels.append(value)
            self.share_labels.append(explained)
        self.grid.setRowStretch(model.n_factors, 1)
        self._sync()

    def _sync(self) -> None:
        model, coef = self.state.active.model, self.state.active.coef
        if model is None or coef is None or len(self.sliders) != model.n_factors:
            return
        sd_values = coef / np.sqrt(model.coef_var)
        for slider, label, value in zip(self.sliders, self.value_labels, sd_values):
            slider.blockSignals(True)
            slider.setValue(int(round(np.clip(value, -MAX_SD, MAX_SD) * STEPS_PER_SD)))
            slider.blockSignals(False)
            label.setText(f"{value:+.2f}")

    def _on_slider(self, index: int, value: int) -> None:
        model = self.state.active.model
        if model is None:
            return
        slider = self.sliders[index]
        if not slider.isSliderDown():
            self.state.active.checkpoint()      # keyboard/page steps: one undo step each
        sd = value / STEPS_PER_SD
        self.value_labels[index].setText(f"{sd:+.2f}")
        self.factor_touched.emit(index)
        self.state.active.set_coefficient(index, sd * float(np.sqrt(model.coef_var[index])))

    def describe(self, index: int) -> str:
        """What factor ``index`` does, for the status bar."""
        move = self.state.active.factor_displacement(index)
        share = float(np.mean(move > 0.1 * move.max())) if move.max() > 0 else 0.0
        return (f"Factor {index + 1}: moves {100 * share:.0f}% of the surface "
                f"(up to {move.max():.1f} mm per SD)")

    def set_factor_sd(self, index: int, sd: float) -> None:
        """Set factor ``index`` to ``sd`` standard deviations (as a slider move would)."""
        self.sliders[index].setValue(int(round(sd * STEPS_PER_SD)))

    def reset(self) -> None:
        if self.state.active.model is None:
            return
        self.state.active.reset_coefficients()
        self.factor_touched.emit(-1)
