"""*Open second image*: a T2, FLAIR or CT scan over the first image (issue 17).

:func:`install_second_image` adds to a main window, without the window knowing the details:

- File > *Open second image…* (Ctrl+Shift+I): any image the app reads (NIfTI, NRRD,
  MetaImage, a DICOM series). Reading, the rigid registration onto the first image when the
  grids differ (``core.registration.volumes`` through ``core.registration.coregistration``) and
  the resampling run in a :class:`app.workers.DialogTask` (progress, Cancel: a cancelled load
  changes nothing);
- the composite layer in every slice view (:class:`app.views.second_image_layer.
  SecondImageLayer`): blend with an opacity, or checkerboard (View > K);
- *Swap base image* (Ctrl+B): which image is drawn on (the other is shown over it), and the
  one window/level acts on; points are world coordinates, so nothing moves;
- a "Second image" box in the side panel with these settings;
- the session keeps the path, the transform and the settings (``info.second_image``); a
  reopened session resamples with the stored transform, without registering again.
"""

from __future__ import annotations

import os
from pathlib import Path

from PySide6.QtCore import QObject, Qt, Signal
from PySide6.QtWidgets import (
    QComboBox,
    QDoubleSpinBox,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSlider,
    QVBoxLayout,
    QWidget,
)

from app.actions import add_help_shortcuts
from app.model.second_image import SecondImage
from app.views.second_image_layer import SecondImageLayer
from app.workers import DialogTask
from core.geometry.planes import window_to_uint8

SHORTCUTS = [("Ctrl+Shift+I", "Open a second image (T2, FLAIR, CT) over the first"),
             ("K", "Second image: checkerboard / blend"),
             ("Ctrl+B", "Second image: swap the base image (the one drawn on)")]


def _load(path: str, reference, transform=None, series=None, progress=None):
    """Worker: read the second image and bring it onto the reference grid."""
    from core.io import DataFileError, load_volume
    from core.registration.coregistration import coregister

    second = load_volume(path, series=series)
    try:
        return coregister(reference, second, transform, progress=progress)
    except DataFileError:
        raise
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


class SecondImageController(QObject):
    """Loads the second image in a worker and keeps the views and the panel in step."""

    message = Signal(str)
    error = Signal(str)

    def __init__(self, window):
        super().__init__(window)
        self.w = window
        self.model = SecondImage(window.state)
        self.layer = SecondImageLayer(self.model)
        self.task = DialogTask("Open second image", "Reading and registering the second image…",
                               window)
        self.task.succeeded.connect(self._on_loaded)
        self.task.failed.connect(lambda m: self.error.emit(f"Second image not opened: {m}"))
        self.task.cancelled.connect(
            lambda: self.message.emit("Second image cancelled: nothing changed"))
        # (path, session display settings, first image, notes on the DICOM series choice)
        self._pending: tuple | None = None
        views = list(window.workspace.views.values())
        for view in views:
            view.layers.insert(0, self.layer)         # under the label fill and the contours
        for event in (self.model.events.loaded, self.model.events.display):
            event.connect(lambda: [v.update() for v in views])
        window.workspace.volume_view_created.connect(self._wire_volume_view)
        if window.workspace.volume_view is not None:
            self._wire_volume_view()

    def _wire_volume_view(self) -> None:
        """The 3D planes show the same composite as the slice views (the first image alone,
        in its own window, without a second image)."""
        view, layer, model = self.w.workspace.volume_view, self.layer, self.model

        def grey(frame, sl):
            composite = layer.composite_slice(frame, sl)
            return composite if composite is not None else \
                window_to_uint8(sl.data, *model.window_of("first"))

        view.plane_key = layer.display_key
        view.plane_grey = grey
        for event in (model.events.display, model.events.loaded):
            event.connect(view._on_planes)

    @property
    def is_running(self) -> bool:
        return self.task.is_running

    def load(self, path: str | os.PathLike, transform=None, show_dialog: bool = True,
             display: dict | None = None) -> bool:
        """Start loading ``path`` (``transform``: a known second -> first world matrix)."""
        if self.w.state.volume is None:
            self.error.emit("Open the first image before a second one")
            return False
        if self.task.is_running:
            self.error.emit(f"{path}: a second image is still loading; wait or cancel it first")
            return False
        notes: list[str] = []
        resolved = self.w.files.resolve_image(path, None if show_dialog else False, notes)
        if resolved is None:
            return False
        self._pending = (str(resolved), display, self.w.state.volume, notes)
        return self.task.start(_load, str(resolved), self.w.state.volume, transform,
                               show_dialog=show_dialog)

    def cancel(self) -> None:
        self.task.cancel()

    def wait(self, msecs: int = 60000) -> bool:
        return self.task.wait(msecs)

    def _on_loaded(self, coregistered) -> None:
        path, display, reference, notes = self._pending or ("second image", None, None, [])
        self._pending = None
        if reference is not self.w.state.volume:      # another first image meanwhile
            self.error.emit(f"{path}: the first image changed while the second one was "
                            "loading; open the second image again")
            return
        try:
            self.model.set_image(coregistered, path, edited=display is None)
        except ValueError as exc:                      # the first image changed meanwhile
            self.error.emit(str(exc))
            return
        if display:                                    # a session's: restored, not edited
            with self.w.state.events.edited.blocked():
                self.model.apply_display(display)
        self.message.emit(f"Second image {self.model.describe()}"
                          + (f" ({notes[0]})" if notes else ""))

    def restore(self, document: dict | None) -> None:
        """A session's ``info.second_image``: load it again with its transform."""
        if not document:
            self.model.clear()
            return
        path = Path(document.get("path", ""))
        if document.get("first_window"):              # the session's window may be the
            self.w.state.set_window(*document["first_window"])   # second image's (its base)
        if not path.exists():
            self.error.emit(f"{path}: the session's second image was not found; not shown")
            return
        self.load(path, transform=document.get("transform"),
                  show_dialog=not self.w._quiet_errors(), display=document)


class SecondImagePanel(QWidget):
    """Blend / checkerboard, opacity, square size, the base image and *Remove*."""

    def __init__(self, controller: SecondImageController, parent: QWidget | None = None):
        super().__init__(parent)
        model = self.model = controller.model
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        self.info = QLabel()
        self.info.setWordWrap(True)
        layout.addWidget(self.info)
        row = QHBoxLayout()
        self.mode = QComboBox()
        self.mode.addItems(["Blend", "Checkerboard"])
        self.mode.setToolTip("How the other image is shown over the base image (K)")
        self.opacity = QSlider(Qt.Orientation.Horizontal)
        self.opacity.setObjectName("second_opacity")
        self.opacity.setRange(0, 100)
        self.opacity.setToolTip("Opacity of the image shown over the base image")
        self.squares = QDoubleSpinBox()
        self.squares.setRange(1.0, 100.0)
        self.squares.setSuffix(" mm")
        self.squares.setToolTip("Checkerboard square size")
        row.addWidget(self.mode)
        row.addWidget(self.opacity, 1)
        row.addWidget(self.squares)
        layout.addLayout(row)
        row = QHBoxLayout()
        self.base = QComboBox()
        self.base.addItems(["Draw on the first image", "Draw on the second image"])
        self.base.setToolTip("The base image: painted at the bottom, window/level acts on it "
                             "(Ctrl+B). Points stay where they are.")
        self.remove = QPushButton("Remove")
        row.addWidget(self.base, 1)
        row.addWidget(self.remove)
        layout.addLayout(row)
        self.mode.currentIndexChanged.connect(
            lambda i: model.set_mode(("blend", "checkerboard")[i]))
        self.opacity.valueChanged.connect(lambda v: model.set_opacity(v / 100))
        self.squares.valueChanged.connect(model.set_checker_mm)
        self.base.currentIndexChanged.connect(lambda i: model.set_base(("first", "second")[i]))
        self.remove.clicked.connect(model.clear)
        model.events.loaded.connect(self.follow)
        model.events.display.connect(self.follow)
        self.follow()

    def follow(self) -> None:
        m = self.model
        widgets = (self.mode, self.opacity, self.squares, self.base)
        for widget in widgets:
            widget.blockSignals(True)
        self.mode.setCurrentIndex(0 if m.mode == "blend" else 1)
        self.opacity.setValue(int(round(100 * m.opacity)))
        self.squares.setValue(m.checker_mm)
        self.base.setCurrentIndex(0 if m.base == "first" else 1)
        for widget in widgets:
            widget.blockSignals(False)
            widget.setEnabled(m.loaded)
        self.opacity.setEnabled(m.loaded and m.mode == "blend")
        self.squares.setEnabled(m.loaded and m.mode == "checkerboard")
        self.remove.setEnabled(m.loaded)
        self.info.setText(m.describe() if m.loaded else
                          "No second image (File > Open second image…, Ctrl+Shift+I)")


class SecondImageFeature:
    """The window's feature ``"second-image"``: the second-image ``controller`` (worker,
    model, layer), its actions (File > Open / Remove second image, View > checkerboard and
    swap), side-panel box (``panel``), status-bar value and session hooks."""

    def __init__(self, window):
        self.controller = controller = SecondImageController(window)
        model = controller.model
        controller.message.connect(window.show_message)
        controller.error.connect(window.show_error)
        add_help_shortcuts(SHORTCUTS)

        def toggle_mode() -> None:
            if model.loaded:
                model.set_mode("blend" if model.mode == "checkerboard" else "checkerboard")

        def swap() -> None:
            if model.loaded:
                model.swap_base()
                window.show_message(f"Drawing on the {model.base} image")

        r = window.registry
        self.open = r.add("open-second", "Open second &image (T2, FLAIR, CT)…",
                          lambda: window.open_dialog("second"), "Ctrl+Shift+I",
                          "Show a second scan over the first; registered rigidly when the "
                          "grids differ")
        self.checkerboard = r.add("second-checkerboard", "Second image: checkerboard / blend",
                                  toggle_mode, "K")
        self.swap_base = r.add("second-swap-base", "Second image: swap the base image", swap,
                               "Ctrl+B", "Draw on the other image (the points stay where they are)")
        self.remove = r.add("remove-second", "Remove second image", model.clear)
        r.place("file", "open-second", "remove-second", after="open-dicom")
        r.place("view", None, "second-checkerboard", "second-swap-base")
        self.panel = SecondImagePanel(controller)
        box = QGroupBox("Second image")
        box_layout = QVBoxLayout(box)
        box_layout.setContentsMargins(2, 2, 2, 2)
        box_layout.addWidget(self.panel)
        side = window.side_dock
        side.panel.layout().insertWidget(min(2, side.panel.layout().count()), box)
        side.boxes["Second image"] = box
        before = window.cursor_label.extra               # the status bar: its value too

        def extra(world) -> str:
            value = model.value_at(world)
            text = before(world)
            return text if value is None else (f"second {value:.4g}" + (f"   {text}" if text else ""))

        window.cursor_label.extra = extra
        window.sessions.info_providers["second_image"] = model.to_document
        window.sessions.info_readers["second_image"] = controller.restore
