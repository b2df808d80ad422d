"""The builder's pipeline parameters: correspondence reference, alignment, model method and form.

Three group boxes ("2. Correspondence", "3. Alignment", "4. Model"); the model's form is
generated from the estimator's signature (:class:`app.panels.builder_forms.ParameterForm`).
:meth:`PipelineForm.settings` reads them into a :class:`core.build.stages.BuildSettings`, which
gives the stage cache its keys; the widget itself keeps no state besides its editors.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSizePolicy,
    QSpinBox,
    QStackedWidget,
    QVBoxLayout,
    QWidget,
)

from app.panels import builder_engine as engine
from app.panels.builder_engine import MeshEntry
from app.panels.builder_forms import ParameterForm
from core.build.stages import NO_CORRESPONDENCE, BuildSettings


class PipelineForm(QWidget):
    """The correspondence, alignment and model boxes.

    Signals
    -------
    changed()
        Any parameter changed (the stage labels show what a build would rerun).
    """

    changed = Signal()

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self._correspondence_box())
        layout.addWidget(self._alignment_box())
        layout.addWidget(self._model_box())

        self.model_method.currentIndexChanged.connect(self._show_form)
        self.defaults_button.clicked.connect(lambda: self.current_form().reset())
        self.reference_combo.currentTextChanged.connect(
            lambda text: self.n_references.setEnabled(text == "auto"))
        for form in self.forms.values():
            form.changed.connect(self.changed)
        for combo in (self.reference_combo, self.align_method, self.align_transform,
                      self.model_method):
            combo.currentIndexChanged.connect(self.changed)
        self.n_references.valueChanged.connect(self.changed)
        self.mirror_check.toggled.connect(self.changed)

    def _correspondence_box(self) -> QGroupBox:
        self.reference_combo = QComboBox()
        self.reference_combo.setObjectName("reference")
        self.reference_combo.addItems(["auto", NO_CORRESPONDENCE])
        self.reference_combo.setToolTip("Reference mesh whose topology every shape takes. "
                                        "'auto' tries several candidates and keeps the one "
                                        "giving the most compact model. 'none' uses meshes "
                                        "that already share one topology as they are.")
        self.n_references = QSpinBox()
        self.n_references.setObjectName("n_references")
        self.n_references.setRange(1, 20)
        self.n_references.setValue(engine.default_n_references())
        self.n_references.setToolTip("With reference 'auto': how many candidate references "
                                     "to try (each costs one full correspondence run).")
        self.mirror_check = QCheckBox("Leave out mirrored inputs")
        self.mirror_check.setObjectName("mirror_check")
        self.mirror_check.setChecked(True)
        self.mirror_check.setToolTip("Leave out an input whose mirror image fits the others "
                                     "better than any rotation of it (a left/right mix-up). "
                                     "Untick for a population in which a chiral feature takes "
                                     "either sign.")
        box = QGroupBox("2. Correspondence")
        form = QFormLayout(box)
        form.addRow("Reference", self.reference_combo)
        form.addRow("Candidates", self.n_references)
        form.addRow("", self.mirror_check)
        return box

    def _alignment_box(self) -> QGroupBox:
        self.align_method = QComboBox()
        self.align_method.setObjectName("align_method")
        self.align_method.addItems(engine.ALIGN_METHODS)
        self.align_method.setToolTip("sync: transformation synchronisation (all pairwise "
                                     "transforms at once, no reference; CVPR 2015).\n"
                                     "gpa: generalised Procrustes analysis (iterate aligning "
                                     "to the current mean).\nnone: keep the shapes' pose.")
        self.align_transform = QComboBox()
        self.align_transform.setObjectName("align_transform")
        self.align_transform.addItems(engine.TRANSFORMS)
        self.align_transform.setToolTip("Transformation class removed before modelling: "
                                        "similarity (rotation, translation, scale), euclidean/"
                                        "rigid (no scale), affine.")
        box = QGroupBox("3. Alignment")
        form = QFormLayout(box)
        form.addRow("Method", self.align_method)
        form.addRow("Transform", self.align_transform)
        return box

    def _model_box(self) -> QGroupBox:
        self.model_method = QComboBox()
        self.model_method.setObjectName("model_method")
        self.model_forms = QStackedWidget()
        self.forms: dict[str, ParameterForm] = {}
        for name, cls in engine.model_classes().items():
            form = ParameterForm(cls)
            form.setObjectName(f"form_{name}")
            self.forms[name] = form
            self.model_forms.addWidget(form)
            self.model_method.addItem(name)
            self.model_method.setItemData(self.model_method.count() - 1,
                                          engine.method_summary(cls), Qt.ToolTipRole)
        self.model_method.setToolTip("Model-building method; hover the parameters for help.")
        self.defaults_button = QPushButton("Defaults")
        self.defaults_button.setToolTip("Reset this method's parameters to their defaults.")
        box = QGroupBox("4. Model")
        layout = QVBoxLayout(box)
        row = QHBoxLayout()
        row.addWidget(QLabel("Method"))
        row.addWidget(self.model_method, 1)
        row.addWidget(self.defaults_button)
        layout.addLayout(row)
        layout.addWidget(self.model_forms)
        self._show_form(0)
        return box

    def _show_form(self, index: int) -> None:
        """Show one method's form, sized to it: a stack is as tall as its tallest page by
        default, which left a blank gap under the short forms (issue 17, defect 8)."""
        for i in range(self.model_forms.count()):
            page = self.model_forms.widget(i)
            policy = QSizePolicy.Preferred if i == index else QSizePolicy.Ignored
            page.setSizePolicy(policy, policy)
        self.model_forms.setCurrentIndex(index)
        self.model_forms.updateGeometry()

    # -- reading -------------------------------------------------------------------------

    def current_form(self) -> ParameterForm:
        return self.forms[self.model_method.currentText()]

    def reference_choice(self, names: Sequence[str]) -> str | int:
        """"auto", :data:`NO_CORRESPONDENCE`, or the index of the chosen mesh in ``names``."""
        text = self.reference_combo.currentText()
        if text == NO_CORRESPONDENCE:
            return text
        return names.index(text) if text in names else "auto"

    def settings(self, entries: Sequence[MeshEntry]) -> BuildSettings:
        """The build inputs for the usable ``entries``; ValueError for a malformed parameter."""
        return BuildSettings(
            meshes=[e.mesh for e in entries],
            tokens=[(e.path, id(e.mesh)) for e in entries],
            reference=self.reference_choice([e.name for e in entries]),
            n_references=self.n_references.value(),
            mirror_check=self.mirror_check.isChecked(),
            align_method=self.align_method.currentText(),
            align_transform=self.align_transform.currentText(),
            method=self.model_method.currentText(),
            params=self.current_form().values())

    def checked_methods(self, names: Sequence[str]) -> dict[str, dict[str, Any]]:
        """Each of ``names`` with its form's parameters."""
        return {name: self.forms[name].values() for name in names}

    # -- writing -------------------------------------------------------------------------

    def set_reference_names(self, names: Sequence[str]) -> None:
        """Offer ``names`` as references, keeping the current choice when it is still there."""
        current = self.reference_combo.currentText()
        self.reference_combo.blockSignals(True)
        self.reference_combo.clear()
        self.reference_combo.addItems(["auto", NO_CORRESPONDENCE, *names])
        self.reference_combo.setCurrentIndex(max(self.reference_combo.findText(current), 0))
        self.reference_combo.blockSignals(False)

    def show_method(self, method: str, params: dict[str, Any]) -> None:
        """Select ``method`` and fill its form with ``params`` (e.g. from a model file)."""
        if method in self.forms:
            self.model_method.setCurrentText(method)
            self.forms[method].set_values(params)
