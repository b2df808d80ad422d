"""The DICOM series dialog: pick one series of a folder that holds several (widgets only)."""

from __future__ import annotations

from PySide6.QtWidgets import (
    QDialog,
    QDialogButtonBox,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QVBoxLayout,
    QWidget,
)


class SeriesDialog(QDialog):
    """Pick one series of a DICOM folder (UID, modality, description, number of files)."""

    def __init__(self, series: list, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle("Choose a DICOM series")
        self.series = series
        layout = QVBoxLayout(self)
        layout.addWidget(QLabel(f"This folder holds {len(series)} image series. Open which one?"))
        self.list = QListWidget()
        for info in series:
            what = " ".join(p for p in (info.modality, info.description) if p) or "series"
            item = QListWidgetItem(f"{what} — {info.n_files} files\n{info.uid}")
            item.setToolTip(info.uid)
            self.list.addItem(item)
        self.list.setCurrentRow(0)
        self.list.itemDoubleClicked.connect(lambda _item: self.accept())
        layout.addWidget(self.list)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Open
                                   | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        layout.addWidget(buttons)

    def chosen(self):
        row = self.list.currentRow()
        return self.series[row] if 0 <= row < len(self.series) else None


def ask_series(parent: QWidget | None, series: list):
    """Show :class:`SeriesDialog`; the chosen SeriesInfo or None (cancelled)."""
    dialog = SeriesDialog(series, parent)
    return dialog.chosen() if dialog.exec() == QDialog.DialogCode.Accepted else None
