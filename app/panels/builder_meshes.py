"""The builder's training-mesh list: add (folder, files, drop), tick, remove, and what was found.

One row per mesh file: its name, vertex count, after correspondence the distance between the
corresponded mesh and the original and what grooming repaired or dropped, and the problems
found when loading (or why the correspondence failed). The widget only shows the entries the
panel gives it and reports what the user asks for through signals; loading runs in the panel's
worker.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (
    QAbstractItemView,
    QFileDialog,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QInputDialog,
    QLabel,
    QPushButton,
    QTreeWidget,
    QTreeWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.panels import builder_engine as engine
from app.panels.builder_engine import MeshEntry
from core.io import MESH_SUFFIXES

ERROR_COLOUR = "#b00020"
WARNING_COLOUR = "#a05a00"


class MeshListBox(QGroupBox):
    """"1. Training meshes": buttons, the list of mesh files and a one-line summary.

    Signals
    -------
    paths_requested(list)
        Files or folders the user chose to add.
    remove_requested(list)
        Row indices (descending) of the selected meshes.
    clear_requested()
    inclusion_changed(int, bool)
        A mesh was ticked or unticked (row, included). Emitted from inside the item's own
        signal: a receiver must rebuild the list later (``QTimer.singleShot(0, ...)``), since
        clearing it now would delete the item being delivered (a use-after-free crash).
    """

    paths_requested = Signal(list)
    label_maps_requested = Signal(list, object, int)   # files, label (number or name), vertices
    remove_requested = Signal(list)
    clear_requested = Signal()
    inclusion_changed = Signal(int, bool)

    def __init__(self, parent: QWidget | None = None):
        super().__init__("1. Training meshes", parent)
        self.add_folder_button = QPushButton("Add folder…")
        self.add_folder_button.setToolTip("Add every mesh file (" + " ".join(MESH_SUFFIXES)
                                          + ") of a folder. You can also drop files or "
                                            "folders onto this panel.")
        self.add_files_button = QPushButton("Add files…")
        self.add_files_button.setToolTip("Add mesh files.")
        self.labels_button = QPushButton("Add label maps…")
        self.labels_button.setToolTip("Make a training surface from one label of each label "
                                      "map (NIfTI, NRRD, Slicer .seg.nrrd; label by number or "
                                      "FreeSurfer/segment name).")
        self.labels_button.setVisible(engine.label_maps_available())
        self.remove_button = QPushButton("Remove")
        self.remove_button.setToolTip("Remove the selected meshes from the list.")
        self.clear_button = QPushButton("Clear")
        self.clear_button.setToolTip("Remove all meshes.")
        self.tree = QTreeWidget()
        self.tree.setObjectName("mesh_list")
        self.tree.setColumnCount(5)
        self.tree.setHeaderLabels(["Mesh", "Vertices", "Fit (mm)", "Problems", "Grooming"])
        self.tree.headerItem().setToolTip(
            4, "After correspondence: what grooming repaired, dropped or remeshed in this mesh.")
        self.tree.headerItem().setToolTip(
            2, "After correspondence: symmetric mean surface distance between the corresponded "
               "mesh (reference topology) and the original mesh.")
        self.tree.setRootIsDecorated(False)
        self.tree.setSelectionMode(QAbstractItemView.ExtendedSelection)
        for column in (0, 1, 2):
            self.tree.header().setSectionResizeMode(column, QHeaderView.ResizeToContents)
        self.tree.setToolTip("Training meshes. Untick a mesh to leave it out; meshes that "
                             "failed to load cannot be used.")
        self.summary = QLabel("No meshes. Add a folder of training meshes.")
        self.summary.setWordWrap(True)
        self.buttons_row = QHBoxLayout()
        for b in (self.add_folder_button, self.add_files_button, self.labels_button,
                  self.remove_button, self.clear_button):
            self.buttons_row.addWidget(b)
        layout = QVBoxLayout(self)
        layout.addLayout(self.buttons_row)
        layout.addWidget(self.tree, 1)
        layout.addWidget(self.summary)

        self.add_folder_button.clicked.connect(self._ask_folder)
        self.add_files_button.clicked.connect(self._ask_files)
        self.labels_button.clicked.connect(self._ask_label_maps)
        self.remove_button.clicked.connect(self.remove_selected)
        self.clear_button.clicked.connect(self.clear_requested)
        self.tree.itemChanged.connect(self._on_item_changed)

    def set_busy(self, busy: bool) -> None:
        for w in (self.add_folder_button, self.add_files_button, self.labels_button,
                  self.remove_button, self.clear_button, self.tree):
            w.setEnabled(not busy)

    # -- asking --------------------------------------------------------------------------

    def _ask_folder(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Folder of training meshes")
        if folder:
            self.paths_requested.emit([folder])

    def _ask_files(self) -> None:
        pattern = "Meshes (" + " ".join(f"*{s}" for s in MESH_SUFFIXES) + ")"
        files, _ = QFileDialog.getOpenFileNames(self, "Training meshes", "", pattern)
        if files:
            self.paths_requested.emit(files)

    def _ask_label_maps(self) -> None:
        files, _ = QFileDialog.getOpenFileNames(
            self, "Label maps", "", "Label maps (*.nii *.nii.gz *.nrrd *.seg.nrrd *.mha *.mhd);;"
                                    "All files (*)")
        if not files:
            return
        label, ok = QInputDialog.getText(self, "Label", "Label number or name (e.g. 11 or "
                                                        "Left-Caudate):")
        if not ok or not label.strip():
            return
        vertices, ok = QInputDialog.getInt(self, "Vertices", "Vertices per surface:", 2000,
                                           100, 100000, 100)
        if ok:
            text = label.strip()
            self.label_maps_requested.emit(files, int(text) if text.isdigit() else text,
                                           vertices)

    def remove_selected(self) -> None:
        rows = sorted({self.tree.indexOfTopLevelItem(i) for i in self.tree.selectedItems()},
                      reverse=True)
        if rows:
            self.remove_requested.emit(rows)

    def _on_item_changed(self, item: QTreeWidgetItem, column: int) -> None:
        row = self.tree.indexOfTopLevelItem(item)
        if row < 0 or column != 0 or not item.flags() & Qt.ItemIsUserCheckable:
            return
        self.inclusion_changed.emit(row, item.checkState(0) == Qt.Checked)

    # -- showing -------------------------------------------------------------------------

    def show_entries(self, entries: Sequence[MeshEntry],
                     fits: Mapping[str, float] | None = None,
                     failures: Mapping[str, str] | None = None,
                     grooming: Mapping[str, str] | None = None) -> None:
        """List ``entries``; ``fits`` (mm), ``failures`` and ``grooming`` (what was repaired)
        by mesh name from correspondence."""
        fits, failures, grooming = fits or {}, failures or {}, grooming or {}
        self.tree.blockSignals(True)
        self.tree.clear()
        for entry in entries:
            problems = list(entry.problems)
            if entry.included and entry.name in failures:
                problems.insert(0, failures[entry.name])
            fit = fits.get(entry.name) if entry.included else None
            item = QTreeWidgetItem([entry.name, "" if entry.mesh is None else
                                    str(entry.mesh.n_vertices),
                                    "" if fit is None else f"{fit:.2f}", "; ".join(problems),
                                    grooming.get(entry.name, "") if entry.included else ""])
            item.setToolTip(0, entry.path)
            item.setToolTip(3, "\n".join(problems))
            item.setToolTip(4, item.text(4))
            if entry.mesh is None:
                item.setFlags(item.flags() & ~Qt.ItemIsUserCheckable)
                for c in range(5):
                    item.setForeground(c, QColor(ERROR_COLOUR))
            else:
                item.setFlags(item.flags() | Qt.ItemIsUserCheckable)
                item.setCheckState(0, Qt.Checked if entry.included else Qt.Unchecked)
                if problems:
                    item.setForeground(3, QColor(WARNING_COLOUR))
            self.tree.addTopLevelItem(item)
        self.tree.blockSignals(False)
        self.summary.setText(_summary(entries))


def _summary(entries: Sequence[MeshEntry]) -> str:
    if not entries:
        return "No meshes. Add a folder of training meshes."
    usable = [e for e in entries if e.mesh is not None and e.included]
    counts = sorted({e.mesh.n_vertices for e in usable})
    span = (f"{counts[0]}–{counts[-1]}" if len(counts) > 1 else str(counts[0])) if counts else "—"
    bad = sum(e.mesh is None for e in entries)
    return (f"{len(usable)} of {len(entries)} meshes used, {span} vertices"
            + (f"; {bad} unreadable" if bad else ""))
