"""The structure list: one row per structure (visibility, colour, name, side, model, lock).

The selected row is the active structure (drawing, sliders, refit and undo act on it). Name,
side, colour, visibility and lock are edited here and written to the workspace model
(:meth:`app.model.state.Structure.set_properties`); the table follows the model's events, with
its own signals blocked while it does (no feedback loop). *Add* offers the model library
(``core.io.model_library``: ``resources/models/`` and the user's model folder), a model file, or
an empty structure; adding and removing go through the session controller (and stop the
removed structure's refit). ``add_file()`` asks the window for a file dialog; ``message`` and
``error`` are for its status bar.
"""

from __future__ import annotations

from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (
    QAbstractItemView,
    QColorDialog,
    QComboBox,
    QHBoxLayout,
    QHeaderView,
    QMenu,
    QMessageBox,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QToolButton,
    QVBoxLayout,
    QWidget,
)

from app.model.state import SIDES, Structure, WorkspaceState
from app.workers import error_message

COLUMNS = ("", "", "Name", "Side", "Model", "Lock")
VISIBLE, COLOR, NAME, SIDE, MODEL, LOCK = range(len(COLUMNS))


class StructuresPanel(QWidget):
    """List of the workspace's structures; see the module docstring."""

    add_file = Signal()               # ask for a model file (the window's dialog)
    message = Signal(str)
    error = Signal(str)

    def __init__(self, state: WorkspaceState, sessions, refit, library=None,
                 parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        self.sessions = sessions      # app.model.controllers.SessionController
        self.refit = refit            # app.refit.RefitController
        self._library = library       # () -> list of core.io.model_library.LibraryEntry
        self._syncing = False
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setObjectName("structure-table")
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().hide()
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.DoubleClicked
                                   | QAbstractItemView.EditTrigger.EditKeyPressed)
        header = self.table.horizontalHeader()
        for column in (VISIBLE, COLOR, SIDE, LOCK):
            header.setSectionResizeMode(column, QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(NAME, QHeaderView.ResizeMode.Stretch)
        # the model file is in the name's tooltip: in a 300-pixel dock a Model column left
        # the names "cau..." (issue 29)
        self.table.setColumnHidden(MODEL, True)
        self.table.setWordWrap(False)
        self.table.setTextElideMode(Qt.TextElideMode.ElideRight)
        self.table.setVerticalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAsNeeded)
        layout.addWidget(self.table)
        row = QHBoxLayout()
        self.add_button = QToolButton()
        self.add_button.setText("Add structure")
        self.add_button.setPopupMode(QToolButton.ToolButtonPopupMode.InstantPopup)
        self.add_menu = QMenu(self.add_button)
        self.add_menu.aboutToShow.connect(self._fill_add_menu)
        self.add_button.setMenu(self.add_menu)
        self.remove_button = QPushButton("Remove")
        self.color_button = QPushButton("Colour…")
        row.addWidget(self.add_button)
        row.addStretch(1)
        row.addWidget(self.color_button)
        row.addWidget(self.remove_button)
        layout.addLayout(row)
        self.remove_button.clicked.connect(lambda: self.remove_structure(self.state.active))
        self.color_button.clicked.connect(self.choose_color)
        self.table.itemChanged.connect(self._on_item_changed)
        self.table.itemSelectionChanged.connect(self._on_selection)
        self.table.cellDoubleClicked.connect(lambda r, c: c == COLOR and self.choose_color())
        state.events.structures.connect(self.rebuild)
        state.events.active.connect(self._select_active)
        state.events.structure_changed.connect(self._on_structure)
        self.rebuild()

    # -- model -> table ----------------------------------------------------------------------
    def rebuild(self) -> None:
        self._syncing = True
        try:
            self.table.setRowCount(len(self.state.structures))
            for row, s in enumerate(self.state.structures):
                self._fill_row(row, s)
        finally:
            self._syncing = False
        self._fit_height()
        self._select_active()

    def _fit_height(self) -> None:
        """As tall as its rows (two to six): no empty rows taking the drawing bar's room."""
        rows = min(max(self.table.rowCount(), 2), 6)
        row_height = self.table.verticalHeader().defaultSectionSize()
        height = (self.table.horizontalHeader().sizeHint().height() + rows * row_height
                  + 2 * self.table.frameWidth() + 2)
        self.table.setFixedHeight(height)

    def _fill_row(self, row: int, s: Structure) -> None:
        flags = Qt.ItemFlag
        for column, checked in ((VISIBLE, s.visible), (LOCK, s.locked)):
            item = QTableWidgetItem()
            item.setFlags(flags.ItemIsEnabled | flags.ItemIsSelectable | flags.ItemIsUserCheckable)
            item.setCheckState(Qt.CheckState.Checked if checked else Qt.CheckState.Unchecked)
            item.setToolTip("Show in the views" if column == VISIBLE else "Lock: no drawing")
            self.table.setItem(row, column, item)
        swatch = QTableWidgetItem()
        swatch.setFlags(flags.ItemIsEnabled | flags.ItemIsSelectable)
        swatch.setData(Qt.ItemDataRole.DecorationRole, QColor(*s.color))   # shown when selected too
        swatch.setToolTip("Double-click to change the colour")
        self.table.setItem(row, COLOR, swatch)
        model = "—" if s.model_path is None else s.model_path.name + (" (demo)" if s.demo else "")
        name = QTableWidgetItem(s.name or "(unnamed)")
        name.setFlags(flags.ItemIsEnabled | flags.ItemIsSelectable | flags.ItemIsEditable)
        name.setToolTip(f"{s.label}: model {model}. Double-click to rename")
        self.table.setItem(row, NAME, name)
        item = QTableWidgetItem(model)
        item.setFlags(flags.ItemIsEnabled | flags.ItemIsSelectable)
        item.setToolTip(str(s.model_path) if s.model_path else "No model: add one from a file")
        self.table.setItem(row, MODEL, item)
        side = self.table.cellWidget(row, SIDE)
        if not isinstance(side, QComboBox):
            side = QComboBox()
            side.addItems([text or "—" for text in SIDES])
            side.currentIndexChanged.connect(lambda i, combo=side: self._on_side(combo, i))
            self.table.setCellWidget(row, SIDE, side)
        side.blockSignals(True)
        side.setCurrentIndex(SIDES.index(s.side) if s.side in SIDES else 0)
        side.blockSignals(False)

    def _select_active(self) -> None:
        row = self.state.structures.index(self.state.active)
        self._syncing = True
        try:
            self.table.selectRow(row)
        finally:
            self._syncing = False

    def _on_structure(self, structure: Structure, what: str) -> None:
        if what in ("properties", "model") and structure in self.state.structures:
            self._syncing = True
            try:
                self._fill_row(self.state.structures.index(structure), structure)
            finally:
                self._syncing = False

    # -- table -> model ----------------------------------------------------------------------
    def _structure_at(self, row: int) -> Structure | None:
        return self.state.structures[row] if 0 <= row < len(self.state.structures) else None

    def _on_selection(self) -> None:
        if self._syncing:
            return
        rows = {index.row() for index in self.table.selectedIndexes()}
        if len(rows) == 1:
            self.state.set_active(rows.pop())

    def _on_item_changed(self, item: QTableWidgetItem) -> None:
        s = self._structure_at(item.row())
        if self._syncing or s is None:
            return
        checked = item.checkState() == Qt.CheckState.Checked
        if item.column() == VISIBLE:
            s.set_properties(visible=checked)
        elif item.column() == LOCK:
            s.set_properties(locked=checked)
        elif item.column() == NAME:
            s.set_properties(name=item.text())

    def _on_side(self, combo: QComboBox, index: int) -> None:
        for row in range(self.table.rowCount()):
            if self.table.cellWidget(row, SIDE) is combo and not self._syncing:
                self._structure_at(row).set_properties(side=SIDES[index])

    def choose_color(self) -> None:
        s = self.state.active
        color = QColorDialog.getColor(QColor(*s.color), self, f"Colour of {s.label}")
        if color.isValid():
            s.set_properties(color=(color.red(), color.green(), color.blue()))

    def _fill_add_menu(self) -> None:
        self.add_menu.clear()
        entries = self._library() if self._library is not None else []
        for entry in entries:
            if entry.structure is None:
                action = self.add_menu.addAction(f"{entry.path.name}: unreadable")
                action.setEnabled(False)
                action.setToolTip(entry.error)
                continue
            action = self.add_menu.addAction(
                f"{entry.structure.label} — {entry.path.name}",
                lambda path=str(entry.path): self.add_structure(path))
            action.setToolTip(f"{entry.path}: {entry.n_factors} factors, {entry.n_vertices} vertices")
        if not entries:
            self.add_menu.addAction("(no library models found)").setEnabled(False)
        self.add_menu.addSeparator()
        self.add_menu.addAction("From a model file…", self.add_file.emit)
        self.add_menu.addAction("Empty structure (points only)", lambda: self.state.add_structure())

    # -- adding and removing -----------------------------------------------------------------
    def add_structure(self, path) -> bool:
        """A new active structure with the model file ``path``; False (and ``error``) if unreadable."""
        try:
            _, text = self.sessions.add_structure(path)
        except (ValueError, OSError) as exc:
            self.error.emit(error_message(exc))
            return False
        self.message.emit(text)
        return True

    def remove_structure(self, structure: Structure, ask: bool = True) -> None:
        if ask and len(structure.points) and QMessageBox.question(
                self, "Remove structure", f"Remove {structure.label} and its "
                f"{len(structure.points)} contour point(s)?") != QMessageBox.StandardButton.Yes:
            return
        self.refit.cancel(structure)
        self.state.remove_structure(structure)
        self.message.emit(f"Removed {structure.label}")
