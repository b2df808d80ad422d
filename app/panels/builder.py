"""The model-builder workspace: from a folder of training meshes to a shape model.

Left, the steps in order: training meshes (:mod:`app.panels.builder_meshes`), the pipeline
parameters (:mod:`app.panels.builder_pipeline`), Build / Cancel with a progress bar
(:mod:`app.panels.builder_runner`), evaluation, save and "Use for segmentation"
(:mod:`app.panels.builder_eval`). Right, the views (:mod:`app.panels.builder_views`):
training meshes, factors, random samples, and the evaluation table and boxplots.

Design (cf. 3D Slicer's Widget/Logic split): the computation and the stage cache are
:mod:`core.build.stages` (``StagedBuild``: correspond -> align -> fit model, each stage kept with the
key of its inputs, so a Build reruns only the stages whose inputs changed) and
``core.evaluation``; this module wires the parts together. Each stage runs in a worker; Cancel
raises ``core.runtime.progress.Cancelled`` from its progress callback and completed stages stay cached.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtWidgets import QScrollArea, QSplitter, QVBoxLayout, QWidget

from app.panels import builder_engine as engine
from app.panels.builder_eval import EvaluateBox
from app.panels.builder_forms import ParameterForm
from app.panels.builder_meshes import MeshListBox
from app.panels.builder_pipeline import PipelineForm
from app.panels.builder_runner import STAGE_TITLES, RunBox, StageRunner
from app.panels.builder_state import BuilderState
from app.panels.builder_views import BuilderViews
from core.build.stages import STAGES, run_evaluation
from core.io import MESH_SUFFIXES, expand_mesh_paths

__all__ = ["BuilderPanel", "BuilderState", "STAGES", "STAGE_TITLES"]


class BuilderPanel(QWidget):
    """The "Build model" workspace.

    Signals
    -------
    use_for_segmentation(str)
        Path of the saved model file the user wants to segment with.
    model_built(object)
        The new :class:`core.models.shape_model.ShapeModel` after a build.
    busy_changed(bool)
        A worker started (True) or the panel became idle (False).
    status_changed(str)
    """

    use_for_segmentation = Signal(str)
    model_built = Signal(object)
    busy_changed = Signal(bool)
    status_changed = Signal(str)

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = BuilderState()
        self.runner = StageRunner(self)
        self.meshes_box = MeshListBox()
        self.pipeline = PipelineForm()
        self.run_box = RunBox()
        self.eval_box = EvaluateBox(list(self.pipeline.forms))
        self.tabs = BuilderViews(self.state.meshes_for)
        self._closed = False
        self.setAcceptDrops(True)
        self._layout()
        self._expose_parts()
        self._connect()
        self._refresh_stage_labels()
        self._update_buttons()

    def _layout(self) -> None:
        controls = QWidget()
        controls_layout = QVBoxLayout(controls)
        controls_layout.setContentsMargins(4, 4, 4, 4)
        for box in (self.meshes_box, self.pipeline, self.run_box, self.eval_box):
            controls_layout.addWidget(box)
        controls_layout.setStretchFactor(self.meshes_box, 1)
        scroll = QScrollArea()
        scroll.setWidget(controls)
        scroll.setWidgetResizable(True)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        scroll.setMinimumWidth(controls.minimumSizeHint().width()
                               + scroll.verticalScrollBar().sizeHint().width() + 4)
        splitter = QSplitter(Qt.Horizontal)
        splitter.addWidget(scroll)
        splitter.addWidget(self.tabs)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([380, 800])
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(splitter)

    def _expose_parts(self) -> None:
        """The parts' main widgets under the panel's names (tests and the window use them)."""
        form, run, ev, tabs = self.pipeline, self.run_box, self.eval_box, self.tabs
        self.mesh_list = self.meshes_box.tree
        self.reference_combo, self.n_references = form.reference_combo, form.n_references
        self.align_method, self.model_method, self.forms = form.align_method, \
            form.model_method, form.forms
        self.build_button, self.cancel_button = run.build_button, run.cancel_button
        self.progress_bar, self.status_label = run.progress_bar, run.status_label
        self.stage_labels = run.stage_labels
        self.eval_checks, self.evaluate_button, self.use_button = ev.checks, \
            ev.evaluate_button, ev.use_button
        self.factor_view, self.samples_view = tabs.factor_view, tabs.samples_view
        self.evaluation_view = tabs.evaluation_view

    def _connect(self) -> None:
        self.meshes_box.paths_requested.connect(self.add_paths)
        self.meshes_box.label_maps_requested.connect(self.add_label_maps)
        self.meshes_box.remove_requested.connect(self._remove_rows)
        self.meshes_box.clear_requested.connect(self.clear_meshes)
        self.meshes_box.inclusion_changed.connect(self._on_inclusion_changed)
        self.pipeline.changed.connect(self._refresh_stage_labels)
        self.build_button.clicked.connect(self.build)
        self.cancel_button.clicked.connect(self.cancel)
        self.evaluate_button.clicked.connect(self.evaluate)
        self.eval_box.save_button.clicked.connect(self._ask_save)
        self.eval_box.open_button.clicked.connect(self._ask_open)
        self.use_button.clicked.connect(self._use_for_segmentation)
        self.eval_box.message.connect(self._set_status)
        runner = self.runner
        runner.started.connect(self._on_job_started)
        runner.progress.connect(self.run_box.job_progress)
        runner.succeeded.connect(self._on_succeeded)
        runner.failed.connect(lambda stage, message: self._set_status(
            f"{STAGE_TITLES[stage]} failed: {message}", error=True))
        runner.cancelled.connect(lambda stage: self._set_status(
            f"{STAGE_TITLES[stage]} cancelled. Completed stages are kept."))
        runner.idle.connect(self._on_idle)
        runner.busy_changed.connect(self.busy_changed)

    # -- settings and the stage cache --------------------------------------------------------

    @property
    def is_busy(self) -> bool:
        return self.runner.busy

    @property
    def _worker(self):
        return self.runner.worker

    @property
    def _worker_stage(self) -> str | None:
        return self.runner.stage

    @property
    def last_cancel_latency(self) -> float | None:
        return self.runner.last_cancel_latency

    def current_form(self) -> ParameterForm:
        return self.pipeline.current_form()

    def usable_entries(self) -> list[engine.MeshEntry]:
        return self.state.usable_entries()

    def settings(self):
        """The current :class:`core.build.stages.BuildSettings` (ValueError: malformed parameter)."""
        return self.pipeline.settings(self.usable_entries())

    def stage_keys(self) -> dict[str, tuple]:
        """The input key of each stage under the current settings."""
        return self.settings().keys()

    def stale_stages(self) -> list[str]:
        """The stages a Build would run now, in order."""
        return self.state.stages.plan(self.stage_keys())

    def _refresh_stage_labels(self, *_: Any) -> None:
        try:
            keys = self.stage_keys()
        except ValueError:
            keys = None
        cache = self.state.stages
        self.run_box.show_stages(cache.status(keys), {s: cache[s].seconds for s in cache},
                                 self.runner.stage)

    # -- training meshes ---------------------------------------------------------------------

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
        self.runner.run("load", engine.load_entries, files)

    def add_label_maps(self, paths: list[str | Path], label: str | int,
                       n_vertices: int = 2000) -> None:
        """One label of each label map as a training surface, in a worker (Cancel works)."""
        self.runner.run("labels", engine.load_label_entries, [str(p) for p in paths], label,
                        n_vertices)

    def add_entries(self, entries: list[engine.MeshEntry]) -> None:
        """Append loaded entries to the list."""
        self.state.entries.extend(entries)
        failed = sum(e.mesh is None for e in entries)
        self._set_status(f"Loaded {len(entries) - failed} meshes"
                         + (f"; {failed} could not be read (see the list)" if failed else "."))
        self._meshes_changed()

    def remove_selected(self) -> None:
        self.meshes_box._remove_selected()

    def _remove_rows(self, rows: list[int]) -> None:
        for row in sorted(rows, reverse=True):
            del self.state.entries[row]
        self._meshes_changed()

    def clear_meshes(self) -> None:
        self.state.entries.clear()
        self._meshes_changed()

    def _on_inclusion_changed(self, row: int, included: bool) -> None:
        if 0 <= row < len(self.state.entries) and self.state.entries[row].mesh is not None:
            self.state.entries[row].included = included
            # rebuilt after the item's signal returns (the list deletes its items)
            QTimer.singleShot(0, self, self._meshes_changed)

    def _meshes_changed(self) -> None:
        self._refresh_mesh_list()
        self.tabs.refresh_meshes()

    def _refresh_mesh_list(self) -> None:
        fits, failures = self.state.correspondence_report()
        self.meshes_box.show_entries(self.state.entries, fits, failures,
                                     self.state.grooming_report())
        self.pipeline.set_reference_names([e.name for e in self.usable_entries()])
        self.run_box.show_safeguard(self.state.safeguard_report())
        self._refresh_stage_labels()
        self._update_buttons()

    # -- build -------------------------------------------------------------------------------

    def build(self) -> None:
        """Run the stale stages one after another, each in its worker."""
        if self.is_busy:
            return
        try:
            settings = self.settings()
            plan = self.state.build.plan(settings)
        except ValueError as exc:
            self._set_status(str(exc), error=True)
            return
        if not plan:
            self._set_status("Model is up to date (nothing changed since the last build).")
            return
        self._build_seconds = 0.0

        def next_job(stage: str):
            settings = self.settings()  # the form may not change while busy
            return self.state.build.job(stage, settings), settings.keys()[stage]

        self.runner.run_plan(plan, next_job)

    def cancel(self) -> None:
        """Stop the running worker at its next progress report."""
        if self.is_busy:
            self.runner.cancel()
            self._set_status("Cancelling…")

    def _on_job_started(self, stage: str) -> None:
        self.run_box.job_started(stage)
        self.status_changed.emit(self.status_label.text())
        self._refresh_stage_labels()
        self._update_buttons()

    def _on_succeeded(self, stage: str, result: Any, key: Any, seconds: float) -> None:
        if stage in ("load", "labels"):
            self.add_entries(result)
        elif stage == "evaluation":
            self._on_evaluated(result)
        else:
            self._on_stage_done(stage, result, key, seconds)

    def _on_stage_done(self, stage: str, result: Any, key: tuple, seconds: float) -> None:
        self.state.build.store(stage, key, result, seconds)
        self._build_seconds = getattr(self, "_build_seconds", 0.0) + seconds
        if stage == "correspondence":
            self._refresh_mesh_list()
            if result.failures:
                failed = ", ".join(f"{n} ({r})" for n, r in result.failures.items())
                self._set_status(f"Correspondence failed for: {failed}", error=True)
        if stage == "model":
            self._set_model(result, key)
            self._set_status(f"Model built: {result.method}, {result.n_factors} factors, "
                             f"{result.n_vertices} vertices ({self._build_seconds:.1f} s).")
            self.model_built.emit(result)
        self._refresh_stage_labels()
        self.tabs.refresh_meshes()

    def _on_idle(self, outcome: str) -> None:
        self.run_box.job_ended(outcome)
        self._refresh_stage_labels()
        self._update_buttons()

    def _set_model(self, model, key: tuple | None, now: bool = False) -> None:
        self.state.model = model
        self.state.model_key = key
        title = ""
        if model is not None:
            title = (f"{model.method}: {model.n_factors} factors on {model.n_vertices} "
                     f"vertices, {len(model.source_meshes)} training shapes. Colour: "
                     f"displacement of each vertex at 1 SD of the selected factor.")
        self.tabs.show_model(model, title, now=now)
        self._update_buttons()

    def show_model(self, model) -> None:
        """Display ``model`` (a ShapeModel) in the factor and sample views."""
        self._set_model(model, None, now=True)

    # -- evaluation --------------------------------------------------------------------------

    def evaluate(self) -> None:
        """Evaluate the ticked methods (with their forms' parameters) on the aligned shapes."""
        if self.is_busy:
            return
        try:
            keys = self.stage_keys()
        except ValueError as exc:
            self._set_status(str(exc), error=True)
            return
        if not self.state.stages.is_current("alignment", keys):
            self._set_status("Build the model first (evaluation uses the aligned shapes).",
                             error=True)
            return
        names = self.eval_box.ticked()
        if not names:
            names = [self.model_method.currentText()]
            self.eval_checks[names[0]].setChecked(True)
        self.runner.run("evaluation", run_evaluation,
                        self.state.stages["correspondence"].result,
                        self.state.stages["alignment"].result,
                        self.pipeline.checked_methods(names))

    def _on_evaluated(self, results: dict[str, Any]) -> None:
        model = self.state.model
        self.state.record_evaluation(
            results, model is not None and model.method in self.forms
            and self.forms[model.method].values() == model.params)
        self.evaluation_view.set_results(results)
        self.tabs.setCurrentWidget(self.evaluation_view)
        self._set_status(f"Evaluated {', '.join(results)}.")

    # -- save, open, use ---------------------------------------------------------------------

    def save_model(self, path: str | Path) -> str:
        """Save the current model to ``path`` (atomic); returns the path written."""
        path = self.state.save_model(path)
        self._set_status(f"Saved {path}")
        return path

    def open_model(self, path: str | Path) -> None:
        """Load a model file for inspection."""
        model = self.state.open_model(path)
        self.pipeline.show_method(model.method, model.params)  # show how it was built
        self.show_model(model)
        self.tabs.setCurrentWidget(self.factor_view)
        self._set_status(f"Opened {path}")

    def _ask_save(self) -> str | None:
        return self.eval_box.ask_save(self.state)

    def _ask_open(self) -> None:
        path = self.eval_box.ask_open_path()
        if path:
            try:
                self.open_model(path)
            except (ValueError, OSError) as exc:
                self._set_status(str(exc), error=True)

    def _use_for_segmentation(self) -> None:
        if self.state.model is None:
            return
        path = self.state.saved_path if self.state.is_saved else self._ask_save()
        if path:
            self.use_for_segmentation.emit(path)

    # -- buttons, status, closing ------------------------------------------------------------

    def _update_buttons(self) -> None:
        busy = self.is_busy
        have_model = self.state.model is not None
        self.meshes_box.set_busy(busy)
        self.eval_box.open_button.setEnabled(not busy)
        self.build_button.setEnabled(not busy and len(self.usable_entries()) >= 3)
        self.cancel_button.setEnabled(busy)
        self.evaluate_button.setEnabled(not busy and "alignment" in self.state.stages)
        self.eval_box.save_button.setEnabled(not busy and have_model)
        self.use_button.setEnabled(not busy and have_model)

    def _set_status(self, text: str, error: bool = False) -> None:
        self.run_box.set_status(text, error)
        self.status_changed.emit(text)

    def close_views(self, wait_ms: int = 5000) -> None:
        """Cancel any worker, wait for it, and close the 3D views (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.runner.close(wait_ms)
        self.tabs.close_views()

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt API
        self.close_views()
        super().closeEvent(event)
