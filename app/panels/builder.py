"""The model-builder workspace: from a folder of training meshes to a shape model.

Left, the steps in order: training meshes (a folder, files, or drag and drop; listed with their
vertex counts and the problems found when loading), the pipeline parameters (correspondence
reference, alignment method and transform type, model method with a form generated from the
estimator's signature), Build / Cancel with a progress bar, evaluation, save and "Use for
segmentation". Right, the views: training meshes (overlaid or in a grid; as loaded,
corresponded or aligned), factors (mean coloured by the selected factor's magnitude, slider
from -3 to +3 SD), random samples, and the evaluation table and boxplots.

Design (cf. 3D Slicer's Widget/Logic split): the computation is ``core.pipeline``'s stage
functions (correspond -> align -> fit model) and ``core.evaluation``; this module only
orchestrates them. Each stage runs in an :class:`app.workers.Worker`; its result is cached with
the key of the inputs it was computed from, so pressing Build again reruns only the stages
whose inputs changed (changing the model's parameters does not redo the correspondence).
Cancel raises ``core.progress.Cancelled`` from the stage's progress callback; completed stages
stay cached.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (
    QAbstractItemView,
    QButtonGroup,
    QCheckBox,
    QComboBox,
    QFileDialog,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QProgressBar,
    QPushButton,
    QRadioButton,
    QScrollArea,
    QSpinBox,
    QSplitter,
    QStackedWidget,
    QTabWidget,
    QTreeWidget,
    QTreeWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.panels import builder_engine as engine
from app.panels.builder_eval import EvaluationView
from app.panels.builder_forms import ParameterForm
from app.panels.builder_views import FactorView, MeshesView, SamplesView
from app.workers import Worker
from core.io import MESH_SUFFIXES, expand_mesh_paths

STAGES = ("correspondence", "alignment", "model")
STAGE_TITLES = {"load": "Loading meshes", "correspondence": "Correspondence",
                "alignment": "Alignment", "model": "Model", "evaluation": "Evaluation"}


@dataclass
class CachedStage:
    """A completed pipeline stage: its result, the key of its inputs, and its duration."""

    key: tuple
    result: Any
    seconds: float


@dataclass
class BuilderState:
    """Everything the builder knows, apart from widgets (kept as plain data for tests)."""

    entries: list[engine.MeshEntry] = field(default_factory=list)
    stages: dict[str, CachedStage] = field(default_factory=dict)
    model: Any = None  # core.shape_model.ShapeModel
    model_key: tuple | None = None
    saved_path: str | None = None
    saved_key: tuple | None = None
    evaluation: dict[str, Any] = field(default_factory=dict)


class BuilderPanel(QWidget):
    """The "Build model" workspace.

    Signals
    -------
    use_for_segmentation(str)
        Path of the saved model file the user wants to segment with.
    model_built(object)
        The new :class:`core.shape_model.ShapeModel` after a build.
    busy_changed(bool)
        A worker started (True) or the panel became idle (False).
    """

    use_for_segmentation = Signal(str)
    model_built = Signal(object)
    busy_changed = Signal(bool)
    status_changed = Signal(str)

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = BuilderState()
        self._worker: Worker | None = None
        self._worker_stage: str | None = None
        self._worker_started = 0.0
        self._plan: list[str] = []
        self._closed = False
        self._meshes_drawn: tuple | None = None
        self.setAcceptDrops(True)
        self._build_widgets()
        self._update_buttons()

    # ======================================================================================
    # Widgets
    # ======================================================================================

    def _build_widgets(self) -> None:
        # --- training meshes ------------------------------------------------------------
        self.add_folder_button = QPushButton("Add folder…")
        self.add_folder_button.setToolTip("Add every mesh file (" + " ".join(MESH_SUFFIXES)
                                          + ") of a folder. You can also drop files or "
                                            "folders onto this panel.")
        self.add_files_button = QPushButton("Add files…")
        self.add_files_button.setToolTip("Add mesh files.")
        self.add_labels_button = QPushButton("Add label maps…")
        self.add_labels_button.setToolTip("Add one label of label maps (by number or name) as "
                                          "closed training surfaces (core.mesh_labels).")
        self.remove_button = QPushButton("Remove")
        self.remove_button.setToolTip("Remove the selected meshes from the list.")
        self.clear_button = QPushButton("Clear")
        self.clear_button.setToolTip("Remove all meshes.")
        self.mesh_list = QTreeWidget()
        self.mesh_list.setObjectName("mesh_list")
        self.mesh_list.setColumnCount(4)
        self.mesh_list.setHeaderLabels(["Mesh", "Vertices", "Fit (mm)", "Problems"])
        self.mesh_list.headerItem().setToolTip(
            2, "After correspondence: symmetric mean surface distance between the corresponded "
               "mesh (reference topology) and the original mesh.")
        self.mesh_list.setRootIsDecorated(False)
        self.mesh_list.setSelectionMode(QAbstractItemView.ExtendedSelection)
        self.mesh_list.header().setSectionResizeMode(0, QHeaderView.ResizeToContents)
        self.mesh_list.header().setSectionResizeMode(1, QHeaderView.ResizeToContents)
        self.mesh_list.header().setSectionResizeMode(2, QHeaderView.ResizeToContents)
        self.mesh_list.setToolTip("Training meshes. Untick a mesh to leave it out; meshes "
                                  "that failed to load cannot be used.")
        self.mesh_summary = QLabel("No meshes. Add a folder of training meshes.")
        self.mesh_summary.setWordWrap(True)
        buttons = QHBoxLayout()
        for b in (self.add_folder_button, self.add_files_button, self.add_labels_button,
                  self.remove_button, self.clear_button):
            buttons.addWidget(b)
        meshes_box = QGroupBox("1. Training meshes")
        box_layout = QVBoxLayout(meshes_box)
        box_layout.addLayout(buttons)
        box_layout.addWidget(self.mesh_list, 1)
        box_layout.addWidget(self.mesh_summary)

        # --- correspondence ---------------------------------------------------------------
        self.reference_combo = QComboBox()
        self.reference_combo.setObjectName("reference")
        self.reference_combo.addItems(["auto", engine.NO_CORRESPONDENCE])
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
        corr_box = QGroupBox("2. Correspondence")
        corr_form = QFormLayout(corr_box)
        corr_form.addRow("Reference", self.reference_combo)
        corr_form.addRow("Candidates", self.n_references)

        # --- alignment --------------------------------------------------------------------
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
        align_box = QGroupBox("3. Alignment")
        align_form = QFormLayout(align_box)
        align_form.addRow("Method", self.align_method)
        align_form.addRow("Transform", self.align_transform)

        # --- model --------------------------------------------------------------------------
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
        model_box = QGroupBox("4. Model")
        model_layout = QVBoxLayout(model_box)
        row = QHBoxLayout()
        row.addWidget(QLabel("Method"))
        row.addWidget(self.model_method, 1)
        row.addWidget(self.defaults_button)
        model_layout.addLayout(row)
        model_layout.addWidget(self.model_forms)

        # --- run ----------------------------------------------------------------------------
        self.build_button = QPushButton("Build model")
        self.build_button.setObjectName("build")
        self.build_button.setToolTip("Run the stages whose inputs changed (completed stages "
                                     "are reused).")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setObjectName("cancel")
        self.cancel_button.setToolTip("Stop the running step (within about a second). "
                                      "Completed stages are kept.")
        self.progress_bar = QProgressBar()
        self.progress_bar.setRange(0, 1000)
        self.progress_bar.setTextVisible(True)
        self.progress_bar.setFormat("")
        self.status_label = QLabel("")
        self.status_label.setObjectName("status")
        self.status_label.setWordWrap(True)
        self.status_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.stage_labels = {s: QLabel("—") for s in STAGES}
        run_box = QGroupBox("5. Build")
        run_layout = QVBoxLayout(run_box)
        row = QHBoxLayout()
        row.addWidget(self.build_button, 1)
        row.addWidget(self.cancel_button)
        run_layout.addLayout(row)
        run_layout.addWidget(self.progress_bar)
        stage_form = QFormLayout()
        for s in STAGES:
            stage_form.addRow(STAGE_TITLES[s], self.stage_labels[s])
        run_layout.addLayout(stage_form)
        run_layout.addWidget(self.status_label)

        # --- evaluate / save ------------------------------------------------------------------
        self.eval_checks: dict[str, QCheckBox] = {}
        eval_box = QGroupBox("6. Evaluate and save")
        eval_layout = QVBoxLayout(eval_box)
        row = QHBoxLayout()
        for name in self.forms:
            check = QCheckBox(name)
            check.setToolTip(f"Evaluate {name} with the parameters of its form above.")
            self.eval_checks[name] = check
            row.addWidget(check)
        row.addStretch(1)
        eval_layout.addLayout(row)
        self.evaluate_button = QPushButton("Evaluate")
        self.evaluate_button.setObjectName("evaluate")
        self.evaluate_button.setToolTip("Reconstruction, generalisation (leave one out), "
                                        "specificity and sparse reconstruction of the ticked "
                                        "methods on the aligned training shapes.")
        self.save_button = QPushButton("Save model…")
        self.save_button.setObjectName("save")
        self.open_button = QPushButton("Open model…")
        self.open_button.setToolTip("Inspect a saved model file (factors, samples).")
        self.use_button = QPushButton("Use for segmentation")
        self.use_button.setObjectName("use_for_segmentation")
        self.use_button.setToolTip("Save the model if needed and load it into the "
                                   "segmentation workspace.")
        row = QHBoxLayout()
        row.addWidget(self.evaluate_button)
        row.addWidget(self.save_button)
        row.addWidget(self.open_button)
        eval_layout.addLayout(row)
        eval_layout.addWidget(self.use_button)

        controls = QWidget()
        controls_layout = QVBoxLayout(controls)
        controls_layout.setContentsMargins(4, 4, 4, 4)
        for box in (meshes_box, corr_box, align_box, model_box, run_box, eval_box):
            controls_layout.addWidget(box)
        controls_layout.setStretchFactor(meshes_box, 1)
        scroll = QScrollArea()
        scroll.setWidget(controls)
        scroll.setWidgetResizable(True)
        scroll.setMinimumWidth(340)

        # --- views ----------------------------------------------------------------------------
        self.meshes_view = MeshesView()
        self.show_overlay = QRadioButton("Overlaid")
        self.show_grid = QRadioButton("Grid")
        self.show_overlay.setChecked(True)
        self._layout_group = QButtonGroup(self)
        self._layout_group.addButton(self.show_overlay)
        self._layout_group.addButton(self.show_grid)
        self.show_which = QComboBox()
        self.show_which.setObjectName("show_which")
        self.show_which.addItems(["as loaded", "corresponded", "aligned"])
        self.show_which.setToolTip("Which version of the training shapes to show.")
        meshes_tab = QWidget()
        tab_layout = QVBoxLayout(meshes_tab)
        tab_layout.setContentsMargins(2, 2, 2, 2)
        row = QHBoxLayout()
        row.addWidget(self.show_overlay)
        row.addWidget(self.show_grid)
        row.addWidget(QLabel("Shapes"))
        row.addWidget(self.show_which)
        row.addStretch(1)
        tab_layout.addLayout(row)
        tab_layout.addWidget(self.meshes_view, 1)
        self.factor_view = FactorView()
        self.samples_view = SamplesView()
        self.evaluation_view = EvaluationView()
        self.tabs = QTabWidget()
        self.tabs.addTab(meshes_tab, "Training meshes")
        self.tabs.addTab(self.factor_view, "Factors")
        self.tabs.addTab(self.samples_view, "Samples")
        self.tabs.addTab(self.evaluation_view, "Evaluation")

        splitter = QSplitter(Qt.Horizontal)
        splitter.addWidget(scroll)
        splitter.addWidget(self.tabs)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([380, 800])
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(splitter)

        # --- connections --------------------------------------------------------------------
        self.add_folder_button.clicked.connect(self._ask_folder)
        self.add_files_button.clicked.connect(self._ask_files)
        self.add_labels_button.clicked.connect(self._ask_label_maps)
        self.remove_button.clicked.connect(self.remove_selected)
        self.clear_button.clicked.connect(self.clear_meshes)
        self.mesh_list.itemChanged.connect(self._on_item_changed)
        self.model_method.currentIndexChanged.connect(self.model_forms.setCurrentIndex)
        self.model_method.currentIndexChanged.connect(self._refresh_stage_labels)
        self.defaults_button.clicked.connect(lambda: self.current_form().reset())
        for form in self.forms.values():
            form.changed.connect(self._refresh_stage_labels)
        for combo in (self.reference_combo, self.align_method, self.align_transform):
            combo.currentIndexChanged.connect(self._refresh_stage_labels)
        self.n_references.valueChanged.connect(self._refresh_stage_labels)
        self.reference_combo.currentTextChanged.connect(
            lambda text: self.n_references.setEnabled(text == "auto"))
        self.build_button.clicked.connect(self.build)
        self.cancel_button.clicked.connect(self.cancel)
        self.evaluate_button.clicked.connect(self.evaluate)
        self.save_button.clicked.connect(self._ask_save)
        self.open_button.clicked.connect(self._ask_open)
        self.use_button.clicked.connect(self._use_for_segmentation)
        self.show_overlay.toggled.connect(self._refresh_meshes_view)
        self.show_which.currentIndexChanged.connect(self._refresh_meshes_view)
        self.tabs.currentChanged.connect(self._on_tab_changed)

    # ======================================================================================
    # Parameters and keys
    # ======================================================================================

    def current_form(self) -> ParameterForm:
        return self.forms[self.model_method.currentText()]

    def usable_entries(self) -> list[engine.MeshEntry]:
        return [e for e in self.state.entries if e.mesh is not None and e.included]

    def _reference_choice(self) -> str | int:
        text = self.reference_combo.currentText()
        if text == "auto" or not text:
            return "auto"
        if text == engine.NO_CORRESPONDENCE:
            return text
        names = [e.name for e in self.usable_entries()]
        return names.index(text) if text in names else "auto"

    def stage_keys(self) -> dict[str, tuple]:
        """The input key of each stage under the current settings (a stage is up to date when
        its cached key equals this one). Raises ValueError for a malformed parameter."""
        training = tuple((e.path, id(e.mesh)) for e in self.usable_entries())
        reference = self._reference_choice()
        corr = (training, reference, self.n_references.value() if reference == "auto" else 0)
        align = (corr, self.align_method.currentText(), self.align_transform.currentText())
        method = self.model_method.currentText()
        params = self.current_form().values()
        model = (align, method, tuple(sorted((k, repr(v)) for k, v in params.items())))
        return {"correspondence": corr, "alignment": align, "model": model}

    def stale_stages(self) -> list[str]:
        """The stages a Build would run now, in order."""
        keys = self.stage_keys()
        for i, stage in enumerate(STAGES):
            cached = self.state.stages.get(stage)
            if cached is None or cached.key != keys[stage]:
                return list(STAGES[i:])
        return []

    # ======================================================================================
    # Loading meshes
    # ======================================================================================

    def _ask_folder(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Folder of training meshes")
        if folder:
            self.add_paths([folder])

    def _ask_files(self) -> None:
        pattern = "Meshes (" + " ".join(f"*{s}" for s in MESH_SUFFIXES) + ")"
        files, _ = QFileDialog.getOpenFileNames(self, "Training meshes", "", pattern)
        if files:
            self.add_paths(files)

    def _ask_label_maps(self) -> None:
        from PySide6.QtWidgets import QInputDialog

        files, _ = QFileDialog.getOpenFileNames(
            self, "Label maps", "", "Label maps (*.nii *.nii.gz *.nrrd *.nhdr *.mha *.mhd *.mgz)")
        if not files:
            return
        label, ok = QInputDialog.getText(self, "Label", "Label number or name "
                                         "(e.g. 11 or Left-Caudate, or a Slicer segment name):")
        if ok and label.strip():
            self._start_worker("load", engine.load_label_entries, files, label.strip())

    def dragEnterEvent(self, event) -> None:  # noqa: N802 - Qt API
        if event.mimeData().hasUrls() and not self.is_busy:
            event.acceptProposedAction()

    def dropEvent(self, event) -> None:  # noqa: N802 - Qt API
        paths = [u.toLocalFile() for u in event.mimeData().urls() if u.isLocalFile()]
        if paths:
            self.add_paths(paths)
            event.acceptProposedAction()

    def add_paths(self, paths: list[str | Path]) -> None:
        """Load mesh files and folders (of mesh files) in a worker and add them to the list."""
        files = expand_mesh_paths(paths)
        known = {e.path for e in self.state.entries}
        files = [f for f in files if str(f) not in known]
        if not files:
            self._set_status("No new mesh files found (" + " ".join(MESH_SUFFIXES) + ").")
            return
        self._start_worker("load", engine.load_entries, files)

    def _on_loaded(self, entries: list[engine.MeshEntry]) -> None:
        self.state.entries.extend(entries)
        failed = sum(e.mesh is None for e in entries)
        self._set_status(f"Loaded {len(entries) - failed} meshes"
                         + (f"; {failed} could not be read (see the list)" if failed else "."))
        self._refresh_mesh_list()
        self._refresh_meshes_view()

    def remove_selected(self) -> None:
        rows = sorted({self.mesh_list.indexOfTopLevelItem(i) for i in self.mesh_list.selectedItems()},
                      reverse=True)
        for row in rows:
            del self.state.entries[row]
        self._refresh_mesh_list()
        self._refresh_meshes_view()

    def clear_meshes(self) -> None:
        self.state.entries.clear()
        self._refresh_mesh_list()
        self._refresh_meshes_view()

    def _refresh_mesh_list(self) -> None:
        self.mesh_list.blockSignals(True)
        self.mesh_list.clear()
        fits, failures = self._correspondence_by_mesh()
        for entry in self.state.entries:
            problems = list(entry.problems)
            if entry.included and entry.name in failures:
                problems.insert(0, failures[entry.name])
            fit = fits.get(entry.name) if entry.included else None
            item = QTreeWidgetItem([entry.name, "" if entry.mesh is None else
                                    str(entry.mesh.n_vertices),
                                    "" if fit is None else f"{fit:.2f}", "; ".join(problems)])
            item.setToolTip(0, entry.path)
            item.setToolTip(3, "\n".join(problems))
            if entry.mesh is None:
                item.setFlags(item.flags() & ~Qt.ItemIsUserCheckable)
                for c in range(4):
                    item.setForeground(c, QColor("#b00020"))
            else:
                item.setFlags(item.flags() | Qt.ItemIsUserCheckable)
                item.setCheckState(0, Qt.Checked if entry.included else Qt.Unchecked)
                if problems:
                    item.setForeground(3, QColor("#a05a00"))
            self.mesh_list.addTopLevelItem(item)
        self.mesh_list.blockSignals(False)
        usable = self.usable_entries()
        if not self.state.entries:
            self.mesh_summary.setText("No meshes. Add a folder of training meshes.")
        else:
            counts = sorted({e.mesh.n_vertices for e in usable})
            span = (f"{counts[0]}–{counts[-1]}" if len(counts) > 1 else
                    str(counts[0])) if counts else "—"
            bad = sum(e.mesh is None for e in self.state.entries)
            self.mesh_summary.setText(f"{len(usable)} of {len(self.state.entries)} meshes used, "
                                      f"{span} vertices" + (f"; {bad} unreadable" if bad else ""))
        current = self.reference_combo.currentText()
        self.reference_combo.blockSignals(True)
        self.reference_combo.clear()
        self.reference_combo.addItems(["auto", engine.NO_CORRESPONDENCE])
        self.reference_combo.addItems([e.name for e in usable])
        index = self.reference_combo.findText(current)
        self.reference_combo.setCurrentIndex(max(index, 0))
        self.reference_combo.blockSignals(False)
        self._refresh_stage_labels()
        self._update_buttons()

    def _correspondence_by_mesh(self) -> tuple[dict[str, float], dict[str, str]]:
        """Residual (mm) and failure reason per mesh name from the cached correspondence."""
        cached = self.state.stages.get("correspondence")
        if cached is None:
            return {}, {}
        corr = cached.result
        fits = {m.name: r for m, r in zip(corr.meshes, corr.residuals_mm)
                if m is not None and r is not None}
        return fits, dict(corr.failures)

    def _on_item_changed(self, item: QTreeWidgetItem, column: int) -> None:
        row = self.mesh_list.indexOfTopLevelItem(item)
        if 0 <= row < len(self.state.entries) and column == 0:
            entry = self.state.entries[row]
            if entry.mesh is not None:
                entry.included = item.checkState(0) == Qt.Checked
                # Rebuild the list after this signal returns: clearing it here would delete the
                # item whose itemChanged is being delivered (a use-after-free crash).
                QTimer.singleShot(0, self, self._refresh_after_inclusion_change)

    def _refresh_after_inclusion_change(self) -> None:
        self._refresh_mesh_list()
        self._refresh_meshes_view()

    # ======================================================================================
    # Pipeline
    # ======================================================================================

    @property
    def is_busy(self) -> bool:
        return self._worker is not None

    def build(self) -> None:
        """Run the stale stages one after another, each in its worker."""
        if self.is_busy:
            return
        if len(self.usable_entries()) < 3:
            self._set_status("Need at least 3 readable training meshes.", error=True)
            return
        try:
            plan = self.stale_stages()
        except ValueError as exc:
            self._set_status(str(exc), error=True)
            return
        if not plan:
            self._set_status("Model is up to date (nothing changed since the last build).")
            return
        self._plan = plan
        self._build_started = time.monotonic()
        self._run_next_stage()

    def _run_next_stage(self) -> None:
        if not self._plan:
            return
        stage = self._plan[0]
        keys = self.stage_keys()
        if stage == "correspondence":
            meshes = [e.mesh for e in self.usable_entries()]
            self._start_worker(stage, engine.run_correspondence, meshes,
                               reference=self._reference_choice(),
                               n_references=self.n_references.value(), key=keys[stage])
        elif stage == "alignment":
            self._start_worker(stage, engine.run_alignment,
                               self.state.stages["correspondence"].result,
                               method=self.align_method.currentText(),
                               transform=self.align_transform.currentText(), key=keys[stage])
        else:
            self._start_worker(stage, engine.run_model,
                               self.state.stages["correspondence"].result,
                               self.state.stages["alignment"].result,
                               method=self.model_method.currentText(),
                               params=self.current_form().values(), key=keys[stage])

    def _on_stage_done(self, stage: str, result: Any, key: tuple, seconds: float) -> None:
        self.state.stages[stage] = CachedStage(key, result, seconds)
        # later stages computed from an older input are no longer valid
        for later in STAGES[STAGES.index(stage) + 1:]:
            cached = self.state.stages.get(later)
            if cached is not None and cached.key[0] != key:
                del self.state.stages[later]
        if self._plan and self._plan[0] == stage:
            self._plan.pop(0)
        if stage == "correspondence":
            self._refresh_mesh_list()
        if stage == "correspondence" and result.failures:
            failed = ", ".join(f"{n} ({r})" for n, r in result.failures.items())
            self._set_status(f"Correspondence failed for: {failed}", error=True)
        if stage == "model":
            corr = self.state.stages["correspondence"].result
            residuals = [r for r in corr.residuals_mm if r is not None]
            result.info.setdefault("timings", {}).update(
                {f"{s}_seconds": round(self.state.stages[s].seconds, 3) for s in STAGES})
            result.info["correspondence"] = {
                "reference": corr.reference_name,
                "mean_residual_mm": float(np.mean(residuals)) if residuals else None,
                "failures": dict(corr.failures)}
            self._set_model(result, key)
            total = time.monotonic() - getattr(self, "_build_started", time.monotonic())
            self._set_status(f"Model built: {result.method}, {result.n_factors} factors, "
                             f"{result.n_vertices} vertices ({total:.1f} s).")
            self.model_built.emit(result)
        self._refresh_stage_labels()
        self._refresh_meshes_view()

    def _set_model(self, model, key: tuple | None) -> None:
        self.state.model = model
        self.state.model_key = key
        if model is None:
            self.factor_view.set_model(None)
            self.samples_view.set_model(None)
        else:
            title = (f"{model.method}: {model.n_factors} factors on {model.n_vertices} vertices"
                     f", {len(model.source_meshes)} training shapes. Colour: displacement of "
                     f"each vertex at 1 SD of the selected factor.")
            if self.factor_view.isVisible() or self.factor_view.view.created:
                self.factor_view.set_model(model.mean, model.factors, model.coef_var,
                                           model.faces, title)
            else:
                self._factor_view_pending = (model, title)
            self.samples_view.set_model(model, seed=0)
        self._update_buttons()

    def show_model(self, model) -> None:
        """Display ``model`` (a ShapeModel) in the factor and sample views."""
        self._factor_view_pending = None
        self._set_model(model, None)
        title = (f"{model.method}: {model.n_factors} factors on {model.n_vertices} vertices.")
        self.factor_view.set_model(model.mean, model.factors, model.coef_var, model.faces, title)

    def _on_tab_changed(self, index: int) -> None:
        widget = self.tabs.widget(index)
        pending = getattr(self, "_factor_view_pending", None)
        if widget is self.factor_view and pending is not None:
            self._factor_view_pending = None
            model, title = pending
            self.factor_view.set_model(model.mean, model.factors, model.coef_var,
                                       model.faces, title)
        elif widget is self.samples_view and self.samples_view.samples is None and \
                self.state.model is not None:
            self.samples_view.draw()
        elif widget is self.meshes_view.parentWidget():
            self._refresh_meshes_view()

    def cancel(self) -> None:
        """Stop the running worker at its next progress report."""
        if self._worker is not None:
            self._plan = []
            self._cancel_requested_at = time.monotonic()
            self._worker.cancel()
            self._set_status("Cancelling…")

    def _refresh_stage_labels(self, *_: Any) -> None:
        try:
            keys = self.stage_keys()
        except ValueError:
            keys = {}
        for stage in STAGES:
            cached = self.state.stages.get(stage)
            label = self.stage_labels[stage]
            if self._worker_stage == stage:
                label.setText("running…")
            elif cached is None:
                label.setText("not run")
            elif cached.key == keys.get(stage):
                label.setText(f"done ({cached.seconds:.1f} s)")
            else:
                label.setText(f"out of date (done in {cached.seconds:.1f} s)")

    # ======================================================================================
    # Evaluation
    # ======================================================================================

    def evaluate(self) -> None:
        """Evaluate the ticked methods (with their forms' parameters) on the aligned shapes."""
        if self.is_busy:
            return
        aligned = self.state.stages.get("alignment")
        try:
            keys = self.stage_keys()
        except ValueError as exc:
            self._set_status(str(exc), error=True)
            return
        if aligned is None or aligned.key != keys["alignment"]:
            self._set_status("Build the model first (evaluation uses the aligned shapes).",
                             error=True)
            return
        methods = {name: self.forms[name].values() for name, check in self.eval_checks.items()
                   if check.isChecked()}
        if not methods:
            methods = {self.model_method.currentText(): self.current_form().values()}
            self.eval_checks[self.model_method.currentText()].setChecked(True)
        self._start_worker("evaluation", engine.run_evaluation,
                           self.state.stages["correspondence"].result, aligned.result, methods)

    def _on_evaluated(self, results: dict[str, Any]) -> None:
        self.state.evaluation = results
        model = self.state.model
        if model is not None and model.method in results and \
                self.state.model_key is not None and self.state.model_key == \
                self.state.stages.get("model", CachedStage((), None, 0)).key and \
                self.forms[model.method].values() == model.params:
            from core.evaluation import summary_rows

            model.info["evaluation"] = summary_rows({model.method: results[model.method]})[0]
            self.state.saved_key = None  # the file on disk lacks the evaluation
        self.evaluation_view.set_results(results)
        self.tabs.setCurrentWidget(self.evaluation_view)
        self._set_status(f"Evaluated {', '.join(results)}.")

    # ======================================================================================
    # Save, open, use
    # ======================================================================================

    def save_model(self, path: str | Path) -> str:
        """Save the current model to ``path`` (atomic); returns the path written."""
        from core.io import save_model

        if self.state.model is None:
            raise ValueError("no model to save: build one first")
        path = str(path)
        save_model(path, self.state.model)
        self.state.saved_path = path
        self.state.saved_key = id(self.state.model)
        self._set_status(f"Saved {path}")
        return path

    def open_model(self, path: str | Path) -> None:
        """Load a model file for inspection."""
        from core.io import load_model

        model = load_model(path)
        if model.method in self.forms:  # show how it was built
            self.model_method.setCurrentText(model.method)
            self.forms[model.method].set_values(model.params)
        self.show_model(model)
        self.state.saved_path = str(path)
        self.state.saved_key = id(model)
        self.tabs.setCurrentWidget(self.factor_view)
        self._set_status(f"Opened {path}")

    def _ask_save(self) -> str | None:
        if self.state.model is None:
            return None
        start = self.state.saved_path or f"{self.state.model.method}_model.npz"
        path, _ = QFileDialog.getSaveFileName(self, "Save shape model", start,
                                              "Shape model (*.npz)")
        if not path:
            return None
        if not path.endswith(".npz"):
            path += ".npz"
        try:
            return self.save_model(path)
        except (ValueError, OSError) as exc:
            self._set_status(f"Could not save: {exc}", error=True)
            return None

    def _ask_open(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open shape model", "",
                                              "Shape model (*.npz)")
        if path:
            try:
                self.open_model(path)
            except (ValueError, OSError) as exc:
                self._set_status(str(exc), error=True)

    def _use_for_segmentation(self) -> None:
        if self.state.model is None:
            return
        path = self.state.saved_path
        if path is None or self.state.saved_key != id(self.state.model):
            path = self._ask_save()
        if path:
            self.use_for_segmentation.emit(path)

    # ======================================================================================
    # Workers
    # ======================================================================================

    def _start_worker(self, stage: str, fn, *args, key: tuple | None = None, **kwargs) -> None:
        worker = Worker(fn, *args, **kwargs)
        worker.stage, worker.key = stage, key
        self._worker = worker
        self._worker_stage = stage
        self._worker_started = time.monotonic()
        # bound methods of this GUI-thread object: the calls are queued to the GUI thread
        worker.progress.connect(self._on_progress)
        worker.succeeded.connect(self._on_succeeded)
        worker.failed.connect(self._on_failed)
        worker.cancelled.connect(self._on_cancelled)
        worker.done.connect(self._on_worker_done)
        self.progress_bar.setValue(0)
        self.progress_bar.setFormat(f"{STAGE_TITLES[stage]}: %p%")
        self._set_status(f"{STAGE_TITLES[stage]}…")
        self._refresh_stage_labels()
        self._update_buttons()
        self.busy_changed.emit(True)
        worker.start()

    def _on_progress(self, fraction: float, message: str) -> None:
        if self.sender() is not self._worker:
            return
        self.progress_bar.setValue(int(round(1000 * fraction)))
        if message:
            self.status_label.setStyleSheet("")
            self.status_label.setText(f"{STAGE_TITLES[self._worker_stage]}: {message}")

    def _on_succeeded(self, result: Any) -> None:
        worker = self.sender()
        if self._closed or worker is not self._worker:
            return
        stage, key = worker.stage, worker.key
        seconds = time.monotonic() - self._worker_started
        if stage == "load":
            self._on_loaded(result)
        elif stage == "evaluation":
            self._on_evaluated(result)
        else:
            self._on_stage_done(stage, result, key, seconds)

    def _on_failed(self, message: str) -> None:
        worker = self.sender()
        if worker is not self._worker:
            return
        self._plan = []
        self._set_status(f"{STAGE_TITLES[worker.stage]} failed: {message}", error=True)

    def _on_cancelled(self) -> None:
        worker = self.sender()
        if worker is not self._worker:
            return
        stage = worker.stage
        self._plan = []
        self.last_cancel_latency = time.monotonic() - getattr(self, "_cancel_requested_at",
                                                               time.monotonic())
        self._set_status(f"{STAGE_TITLES[stage]} cancelled. Completed stages are kept.")

    def _on_worker_done(self) -> None:
        worker = self._worker
        if worker is None or self.sender() is not worker:
            return
        worker.wait()
        self._worker = None
        self._worker_stage = None
        self.progress_bar.setFormat("%p%" if not worker.was_cancelled else "cancelled")
        if not worker.was_cancelled and worker.error is None:
            self.progress_bar.setValue(1000)
        self._refresh_stage_labels()
        if self._plan and not self._closed:
            self._run_next_stage()
            return
        self._update_buttons()
        self.busy_changed.emit(False)

    def _update_buttons(self) -> None:
        busy = self.is_busy
        have_meshes = len(self.usable_entries()) >= 3
        have_model = self.state.model is not None
        for w in (self.add_folder_button, self.add_files_button, self.add_labels_button,
                  self.remove_button, self.clear_button, self.mesh_list, self.open_button):
            w.setEnabled(not busy)
        self.build_button.setEnabled(not busy and have_meshes)
        self.cancel_button.setEnabled(busy)
        self.evaluate_button.setEnabled(not busy and "alignment" in self.state.stages)
        self.save_button.setEnabled(not busy and have_model)
        self.use_button.setEnabled(not busy and have_model)

    def _set_status(self, text: str, error: bool = False) -> None:
        self.status_label.setStyleSheet("color: #b00020;" if error else "")
        self.status_label.setText(text)
        self.status_changed.emit(text)

    # ======================================================================================
    # Meshes view
    # ======================================================================================

    def _refresh_meshes_view(self, *_: Any) -> None:
        if self._closed or self.meshes_view.creating:
            return
        if not self.meshes_view.isVisible() and not self.meshes_view.created:
            return
        which = self.show_which.currentText()
        layout = "overlay" if self.show_overlay.isChecked() else "grid"
        meshes: list[tuple[str, np.ndarray, np.ndarray]] = []
        if which == "as loaded":
            meshes = [(e.name, e.mesh.vertices, e.mesh.faces) for e in self.usable_entries()]
        else:
            corr = self.state.stages.get("correspondence")
            align = self.state.stages.get("alignment")
            if which == "corresponded" and corr is not None:
                meshes = engine.corresponded_meshes(corr.result)
            elif which == "aligned" and align is not None and corr is not None:
                meshes = engine.aligned_meshes(corr.result, align.result)
        signature = (which, layout, tuple(id(m[1]) for m in meshes))
        if signature == self._meshes_drawn:
            return  # nothing new to draw (rendering costs ~0.1-1 s with software OpenGL)
        self._meshes_drawn = signature
        self.meshes_view.show_meshes(meshes, layout=layout)

    def showEvent(self, event) -> None:  # noqa: N802 - Qt API
        super().showEvent(event)
        # Deferred: the first OpenGL view re-creates the native window, which sends show events
        # again while that view is being built.
        if self.tabs.currentIndex() == 0 and not self.meshes_view.created and \
                self.state.entries:
            QTimer.singleShot(0, self._refresh_meshes_view)

    # ======================================================================================
    # Closing
    # ======================================================================================

    def close_views(self, wait_ms: int = 5000) -> None:
        """Cancel any worker, wait for it, and close the 3D views (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._plan = []
        worker = self._worker
        if worker is not None:
            worker.cancel()
            worker.wait(wait_ms)
        self._worker = None
        for view in (self.meshes_view, self.factor_view.view, self.samples_view.view):
            view.close_view()
        self.evaluation_view.close_figure()

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt API
        self.close_views()
        super().closeEvent(event)
