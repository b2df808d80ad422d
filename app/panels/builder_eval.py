"""Evaluation view of the model builder: a table of measures and their boxplots, per method.

The measures (reconstruction, generalisation, specificity, sparse reconstruction; Bernard et
al., CVPR 2016, section 3.1) are computed by ``core.evaluation`` in a worker; this widget
shows the summary table (mean ± SD over shapes, mm) and embeds the boxplot figure that
``core.evaluation`` draws with matplotlib, through matplotlib's QtAgg canvas.
"""

from __future__ import annotations

from typing import Any

from PySide6.QtWidgets import (
    QHeaderView,
    QLabel,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)
from PySide6.QtCore import Qt

from app.panels import builder_engine as engine


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
