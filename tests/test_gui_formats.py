"""Clinical formats in the GUI: DICOM folder drop and series choice, NRRD/MHA, .h5 models,
.seg.nrrd export, sessions; no patient name or ID in titles, messages or file names."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("SimpleITK")
pytestmark = pytest.mark.gui

sys.path.insert(0, str(Path(__file__).parent))
import formats_synth as synth  # noqa: E402
from PySide6.QtCore import QMimeData, QPointF, Qt, QUrl  # noqa: E402
from PySide6.QtGui import QDropEvent  # noqa: E402

from app import formats  # noqa: E402
from app.window import MainWindow  # noqa: E402

PATIENT = ("DOE", "JANE", "PID-12345")


@pytest.fixture
def window(qtbot, tmp_path, monkeypatch):
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    win = MainWindow(with_3d=False, recovery=True)
    qtbot.addWidget(win)
    win.resize(1000, 700)
    return win


@pytest.fixture
def dicom_folder(tmp_path):
    """A folder named after the patient (as exports often are) holding two series."""
    folder = tmp_path / "DOE_JANE_PID-12345"
    big = synth.oblique_image((16, 14, 10), (1.0, 1.1, 2.0))
    small = synth.oblique_image((8, 7, 4), (1.0, 1.0, 3.0), seed=2)
    synth.write_series(folder, big, uid=synth.UID_ROOT + ".31", description="T1 MPRAGE")
    synth.write_series(folder, small, uid=synth.UID_ROOT + ".32", description="localizer",
                       name="L{:04d}.dcm")
    return folder, big, small


def _drop(window, path: Path) -> None:
    mime = QMimeData()
    mime.setUrls([QUrl.fromLocalFile(str(path))])
    event = QDropEvent(QPointF(40, 40), Qt.DropAction.CopyAction, mime, Qt.MouseButton.NoButton,
                       Qt.KeyboardModifier.NoModifier)
    window.dropEvent(event)


def _no_patient(text: str) -> None:
    for word in PATIENT:
        assert word not in text, text


def test_dropped_dicom_folder_opens_and_leaks_no_patient_name(window, dicom_folder, tmp_path):
    import SimpleITK as sitk

    folder, big, _ = dicom_folder
    _drop(window, folder)
    window.files.wait_for_image()           # read in a worker, shown when it is done
    vol = window.state.volume
    assert vol is not None and vol.shape == (16, 14, 10)
    assert np.array_equal(vol.data, sitk.GetArrayFromImage(big).T)
    title, message = window.windowTitle(), window.statusBar().currentMessage()
    assert "T1 MPRAGE" in title and "most files" in message
    _no_patient(title)
    _no_patient(message)
    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import save_model

    shapes, faces = synthetic_shapes(5, subdivisions=2, seed=3, size=(3.0, 3.0, 4.0))
    model = pca_model(shapes + vol.voxel_to_world((np.array(vol.shape) - 1) / 2), faces)
    save_model(tmp_path / "model.npz", model)
    window.load_model(tmp_path / "model.npz")
    window.write_recovery()  # autosave: its file name carries no patient information
    names = [p.name for p in (tmp_path / "state").rglob("*")]
    names += [p.name for p in window.export_all(tmp_path / "export")]
    assert len(names) >= 3
    # this test series has no Frame of Reference UID: the DICOM SEG and RTSTRUCT are left out
    # with a one-line reason, the other files are written
    message = window.statusBar().currentMessage()
    assert "Frame of Reference UID" in message and "SEG and RTSTRUCT not written" in message
    assert not any(name.endswith(".dcm") for name in names)
    for name in names:
        _no_patient(name)
    _no_patient(window.windowTitle())


def test_series_dialog_choice_is_kept_in_the_session(window, dicom_folder, tmp_path, qtbot):
    import SimpleITK as sitk

    folder, _, small = dicom_folder
    from core.io.dicom import list_series

    series = list_series(folder)
    from app.series_dialog import SeriesDialog

    dialog = SeriesDialog(series, window)
    qtbot.addWidget(dialog)
    assert dialog.list.count() == 2 and "T1 MPRAGE" in dialog.list.item(0).text()
    dialog.list.setCurrentRow(1)
    assert dialog.chosen().uid == synth.UID_ROOT + ".32"
    chosen = formats.resolve_dicom_choice(folder, ask=lambda s: s[1])
    window.load_image(chosen)
    assert window.state.volume.shape == (8, 7, 4)
    window.save_session(path=tmp_path / "session.json")
    window.open_session(tmp_path / "session.json")  # reopens the same series, no question
    assert window.state.volume.shape == (8, 7, 4)
    assert np.array_equal(window.state.volume.data, sitk.GetArrayFromImage(small).T)
    assert formats.resolve_dicom_choice(folder, ask=lambda s: None) is None  # cancelled


def test_nrrd_image_h5_model_and_seg_nrrd_export(window, tmp_path):
    import SimpleITK as sitk

    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import load_volume, save_model
    from core.io.nrrd import segmentation_fields

    image = synth.oblique_image((30, 28, 20), (1.0, 1.0, 1.5))
    sitk.WriteImage(image, str(tmp_path / "scan.nrrd"))
    sitk.WriteImage(image, str(tmp_path / "scan.mha"))
    _drop(window, tmp_path / "scan.mha")
    window.files.wait_for_image()
    mha = window.state.volume
    window.open_path(tmp_path / "scan.nrrd")
    window.files.wait_for_image()
    assert np.allclose(window.state.volume.affine, mha.affine, atol=1e-9)
    centre = window.state.volume.voxel_to_world((np.array(window.state.volume.shape) - 1) / 2)
    shapes, faces = synthetic_shapes(6, subdivisions=2, seed=1)
    model = pca_model(shapes, faces, n_factors=3)
    model.world_transform = np.eye(4)
    model.world_transform[:3, 3] = centre
    save_model(tmp_path / "putamen.h5", model)
    _drop(window, tmp_path / "putamen.h5")
    assert window.state.active.model is not None and window.state.active.model.n_factors == 3
    assert np.allclose(window.state.active.surface_vertices(), model.world_instance(), atol=1e-4)
    window.exports.export_labels(tmp_path / "out.seg.nrrd")
    (segment,) = segmentation_fields(tmp_path / "out.seg.nrrd")
    structure = window.state.active
    assert segment["Name"] == (structure.name or "putamen") and segment["LabelValue"] == "1"
    assert np.allclose([float(c) for c in segment["Color"].split()],
                       np.array(structure.color) / 255.0, atol=1e-5)
    labels = load_volume(tmp_path / "out.seg.nrrd")
    assert np.allclose(labels.affine, mha.affine, atol=1e-9) and labels.data.sum() > 50


def test_view_folder_says_which_series_and_names_the_others_when_it_fails(window, dicom_folder):
    """`view FOLDER` (no dialog): the series taken is said with the others and --series; when
    it cannot be read, the error names it, the readable others and --series."""
    folder, _, _ = dicom_folder
    notes = []
    window.load_image(folder, ask=False, notify=notes.append)
    assert window.state.volume.shape == (16, 14, 10)
    assert len(notes) == 1 and synth.UID_ROOT + ".31" in notes[0]
    assert f"others: {synth.UID_ROOT}.32" in notes[0] and "--series UID" in notes[0]
    _no_patient(notes[0])
    big = synth.oblique_image((16, 14, 10), (1.0, 1.1, 2.0))
    d = np.asarray(big.GetDirection()).reshape(3, 3)
    tilted = [np.array(big.TransformIndexToPhysicalPoint((0, 0, k))) + d[:, 1] * 0.5 * k
              for k in range(10)]
    synth.write_series(folder, big, uid=synth.UID_ROOT + ".31", description="T1 MPRAGE",
                       positions=tilted)
    notes.clear()
    with pytest.raises(ValueError) as err:
        window.load_image(folder, ask=False, notify=notes.append)
    text = str(err.value)
    assert "\n" not in text and "gantry tilt" in text
    assert f"series {synth.UID_ROOT}.31" in text
    assert f"other readable series: {synth.UID_ROOT}.32" in text and "--series UID" in text
    assert window.state.volume.shape == (16, 14, 10)  # the image shown before is kept


def test_gui_model_loading_refuses_what_the_cli_refuses(window, tmp_path):
    """Dropped or opened, a model file goes through core.io.load_model: a dataset stored in
    another file and a catalog without '#shape' are one-line errors; FILE#shape opens."""
    import h5py

    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import save_model

    shapes, faces = synthetic_shapes(6, subdivisions=1, seed=3)
    save_model(tmp_path / "m.h5", pca_model(shapes, faces, n_factors=3))
    with h5py.File(tmp_path / "m.h5", "a") as h5:
        n = h5["model/mean"].shape[0]
        del h5["model/mean"], h5["ssmstudio"]
        h5.create_dataset("model/mean", shape=(n,), dtype="f4",
                          external=[("/etc/passwd", 0, 4 * n)])
    _drop(window, tmp_path / "m.h5")
    message = window.statusBar().currentMessage()
    assert window.state.active.model is None
    assert str(tmp_path / "m.h5") in message and "another file" in message, message
    save_model(tmp_path / "face.h5", pca_model(shapes, faces, n_factors=3))
    with h5py.File(tmp_path / "face.h5", "a") as h5:
        h5.move("model", "shape/model")
        h5.move("representer", "shape/representer")
        h5.create_dataset("catalog/MorphableModel.shape/modelPath", data=b"/shape")
        h5.create_dataset("catalog/MorphableModel.shape/modelType", data=b"POLYGON_MESH_MODEL")
    window.open_path(tmp_path / "face.h5")
    assert window.state.active.model is None and "#shape" in window.statusBar().currentMessage()
    window.load_model(f"{tmp_path / 'face.h5'}#shape")
    assert window.state.active.model is not None and window.state.active.model.n_vertices == shapes.shape[1]


def test_an_image_opened_from_a_file_is_read_in_a_worker_and_can_be_cancelled(window, tmp_path,
                                                                               monkeypatch, qtbot):
    """Opening an image (menu, drop, recent file) returns at once; the image is read in a
    worker and shown when read; Cancel keeps the image that was open; a damaged file is a
    one-line error naming it."""
    import threading

    import SimpleITK as sitk

    import app.file_actions as file_actions

    first, second = tmp_path / "first.nrrd", tmp_path / "second.mha"
    sitk.WriteImage(synth.oblique_image((12, 10, 8), (1.0, 1.0, 1.5)), str(first))
    sitk.WriteImage(synth.oblique_image((9, 11, 7), (1.2, 1.0, 2.0), seed=3), str(second))
    window.open_path(first)
    window.files.wait_for_image()
    assert window.state.volume.shape == (12, 10, 8) and "first" in window.statusBar().currentMessage()

    release, started = threading.Event(), threading.Event()
    real = file_actions.read_image

    def slow_read(path, series=None, default_of=None, progress=None):
        started.set()
        while not release.wait(0.01):          # a long read, reporting progress (Cancel point)
            progress(0.5, "reading")
        return real(path, series, default_of, progress)

    monkeypatch.setattr(file_actions, "read_image", slow_read)
    window.open_path(second)                   # returns while the worker reads
    qtbot.waitUntil(started.is_set, timeout=5000)   # (the series scan ran first, in a worker)
    assert window.files.image_task.is_running
    assert window.state.volume.shape == (12, 10, 8)
    window.files.image_task.cancel()
    window.files.wait_for_image()
    assert window.state.volume.shape == (12, 10, 8)            # the open image is kept
    assert "cancelled" in window.statusBar().currentMessage()
    # the same file again, not cancelled: shown
    release.set()
    window.open_path(second)
    window.files.wait_for_image()
    assert window.state.volume.shape == (9, 11, 7)
    # a damaged file: one line naming it, the image kept
    monkeypatch.setattr(file_actions, "read_image", real)
    broken = tmp_path / "broken.nrrd"
    broken.write_bytes(first.read_bytes()[:200])
    window.open_path(broken)
    window.files.wait_for_image()
    message = window.statusBar().currentMessage()
    assert message.startswith("Error:") and "broken.nrrd" in message and "\n" not in message
    assert "Traceback" not in message and window.state.volume.shape == (9, 11, 7)


def test_a_session_opened_from_a_file_reads_its_image_in_a_worker(window, tmp_path):
    import SimpleITK as sitk

    image = tmp_path / "scan.nrrd"
    sitk.WriteImage(synth.oblique_image((12, 10, 8), (1.0, 1.0, 1.5)), str(image))
    window.load_image(image)
    window.state.set_window(321.0, 123.0)
    assert window.save_session(path=tmp_path / "case.json")
    other = tmp_path / "other.mha"
    sitk.WriteImage(synth.oblique_image((9, 11, 7), (1.2, 1.0, 2.0), seed=3), str(other))
    window.load_image(other)
    window.open_path(tmp_path / "case.json")
    assert window.files.image_task.is_running and window.state.volume.shape == (9, 11, 7)
    window.files.wait_for_image()
    assert window.state.volume.shape == (12, 10, 8)
    assert (window.state.window, window.state.level) == (321.0, 123.0)
    assert window.session_path == tmp_path / "case.json" and "Opened session" in \
        window.statusBar().currentMessage()
    # its image gone: one line naming it, nothing of the session applied
    window.load_image(other)
    image.unlink()
    window.open_path(tmp_path / "case.json")
    window.files.wait_for_image()
    message = window.statusBar().currentMessage()
    assert message.startswith("Error:") and "scan.nrrd" in message
    assert window.state.volume.shape == (9, 11, 7)


def test_closing_the_window_while_an_image_is_read_stops_the_reader(window, tmp_path, monkeypatch,
                                                                    qtbot):
    import threading

    import SimpleITK as sitk

    import app.file_actions as file_actions
    from app.workers import running_workers

    path = tmp_path / "scan.nrrd"
    sitk.WriteImage(synth.oblique_image((12, 10, 8), (1.0, 1.0, 1.5)), str(path))
    started = threading.Event()

    def endless_read(path, series=None, default_of=None, progress=None):
        started.set()
        while True:                            # only a Cancel ends it
            progress(0.5, "reading")
            threading.Event().wait(0.01)

    monkeypatch.setattr(file_actions, "read_image", endless_read)
    window.open_path(path)
    qtbot.waitUntil(started.is_set, timeout=5000)
    window.close()
    qtbot.waitUntil(lambda: not running_workers(), timeout=5000)
    assert window.state.volume is None or window.state.image_path != path
