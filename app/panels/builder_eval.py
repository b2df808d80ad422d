"""The model builder's evaluation: the "6. Evaluate and save" box, and the evaluation view (a
table of measures and their boxplots, per method).

The measures (reconstruction, generalisation, specificity, sparse reconstruction; Bernard et
al., CVPR 2016, section 3.1) are computed by ``core.evaluation`` in a worker; this widget
shows the summary table (mean ± SD over shapes, mm) and embeds the boxplot figure that
``core.evaluation`` draws with matplotlib, through matplotlib's QtAgg canvas.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QFileDialog,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QPushButton,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.panels import builder_engine as engine


class EvaluateBox(QGroupBox):
    """"6. Evaluate and save": methods to compare, Evaluate, Save, Open, Use for segmentation.

    Signals
    -------
    message(str, bool)
        A status line and whether it reports an error.
    """

    message = Signal(str, bool)

    def __init__(self, methods: Sequence[str], parent: QWidget | None = None):
        super().__init__("6. Evaluate and save", parent)
        self.checks: dict[str, QCheckBox] = {}
        layout = QVBoxLayout(self)
        row = QHBoxLayout()
        for name in methods:
            check = QCheckBox(name)
            check.setToolTip(f"Evaluate {name} with the parameters of its form above.")
            self.checks[name] = check
            row.addWidget(check)
        row.addStretch(1)
        layout.addLayout(row)
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
        layout.addLayout(row)
        layout.addWidget(self.use_button)

    def ticked(self) -> list[str]:
        return [name for name, check in self.checks.items() if check.isChecked()]

    def ask_save_path(self, start: str) -> str | None:
        path, _ = QFileDialog.getSaveFileName(self, "Save shape model", start,
                                              "Shape model (*.npz)")
        if not path:
            return None
        return path if path.endswith(".npz") else path + ".npz"

    def ask_save(self, state) -> str | None:
        """Ask where to save ``state``'s model (a ``BuilderState``) and save it there;
        returns the path written, or None if cancelled or failed (reported)."""
        if state.model is None:
            return None
        path = self.ask_save_path(state.saved_path or f"{state.model.method}_model.npz")
        if not path:
            return None
        try:
            path = state.save_model(path)
        except (ValueError, OSError) as exc:
            self.message.emit(f"Could not save: {exc}", True)
            return None
        self.message.emit(f"Saved {path}", False)
        return path

    def ask_open_path(self) -> str | None:
        path, _ = QFileDialog.getOpenFileName(self, "Open shape model", "",
                                              "Shape model (*.npz)")
        return path or None


class EvaluationView(QWidget):
    """Table (methods x measures) above the boxplots of the per-shape errors."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.table = QTableWidget(0, 0)
        self.table.setObjectName("evaluation_table")
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)
        self.info = QLabel("Build a model, tick the methods to compare and press Evaluate. "
                           "Errors are per-vertex Euclidean distances (mm), averaged per "
                           "shape; the table shows mean ± SD over shapes.")
        self.info.setWordWrap(True)
        self._canvas_holder = QWidget()
        self._canvas_layout = QVBoxLayout(self._canvas_holder)
        self._canvas_layout.setContentsMargins(0, 0, 0, 0)
        self.canvas = None
        splitter = QSplitter(Qt.Vertical)
        splitter.addWidget(self.table)
        splitter.addWidget(self._canvas_holder)
        splitter.setSizes([130, 470])
        layout = QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(self.info)
        layout.addWidget(splitter, 1)
        self.results: dict[str, Any] = {}

    def set_results(self, results: dict[str, Any]) -> None:
        """``results``: method name -> evaluation result of ``core.evaluation``."""
        self.results = results
        columns, rows = engine.evaluation_table(results)
        self.table.clear()
        self.table.setColumnCount(len(columns))
        self.table.setRowCount(len(rows))
        self.table.setHorizontalHeaderLabels(columns)
        self.table.setVerticalHeaderLabels(list(rows))
        for r, values in enumerate(rows.values()):
            for c, text in enumerate(values):
                item = QTableWidgetItem(text)
                item.setTextAlignment(Qt.AlignCenter)
                self.table.setItem(r, c, item)
        self._show_figure(engine.evaluation_figure(results) if results else None)

    def _show_figure(self, figure) -> None:
        from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg

        self.close_figure()
        if figure is None:
            return
        self.canvas = FigureCanvasQTAgg(figure)
        self.canvas.setObjectName("evaluation_canvas")
        self._canvas_layout.addWidget(self.canvas)
        self.canvas.draw_idle()

    def close_figure(self) -> None:
        if self.canvas is not None:
            self._canvas_layout.removeWidget(self.canvas)
            self.canvas.setParent(None)
            self.canvas.deleteLater()
            self.canvas = None
