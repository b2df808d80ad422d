"""The model-builder panel, driven like a user: load meshes, build, cancel, inspect, save.

Runs under pytest-xvfb (xcb platform, real OpenGL through Mesa). The build uses 5 meshes of
the demo training set (resources/demo/meshes) to keep the correspondence stage short.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PySide6.QtCore import QMimeData, QPointF, Qt, QTimer, QUrl
from PySide6.QtGui import QDropEvent
from PySide6.QtWidgets import QCheckBox, QComboBox, QDoubleSpinBox, QLineEdit, QMainWindow, QSpinBox

import core.correspondence  # noqa: F401 - imported here, not in the timed worker
from app.panels.builder import BuilderPanel
from app.panels.builder_engine import NO_CORRESPONDENCE
from app.panels.builder_forms import ParameterForm, parse_numpydoc_parameters
from core.datasets.factors import ellipsoid_surface, planted_shapes, support_iou
from core.io import TriMesh, load_model, save_mesh
from core.models import LSF, PCA, Varimax

DEMO = Path(__file__).resolve().parents[1] / "resources" / "demo" / "meshes"
N_TRAIN = 5


@pytest.fixture
def panel(qtbot):
    window = QMainWindow()
    panel = BuilderPanel()
    window.setCentralWidget(panel)
    window.resize(1200, 800)
    qtbot.addWidget(window)
    window.show()
    qtbot.waitExposed(window)
    yield panel
    panel.close_views()
    window.close()


def wait_idle(qtbot, panel, timeout_ms: int) -> None:
    qtbot.waitUntil(lambda: not panel.is_busy, timeout=timeout_ms)


def demo_files(n: int = N_TRAIN) -> list[Path]:
    files = sorted(DEMO.glob("*.vtk"))
    if len(files) < n:
        pytest.skip("demo training set missing (resources/demo/meshes)")
    return files[:n]


class GapMeter:
    """Counts ticks of a 20 ms GUI-thread timer: ticks arrive only while the event loop runs
    (how long its gaps are is timing, not a test's business)."""

    def __init__(self):
        self.timer = QTimer()
        self.timer.setInterval(20)
        self.timer.timeout.connect(self._tick)
        self.ticks = 0

    def _tick(self):
        self.ticks += 1

    def __enter__(self):
        self.timer.start()
        return self

    def __exit__(self, *exc):
        self.timer.stop()


# ------------------------------------------------------------------------------------------
# Forms generated from estimator signatures
# ------------------------------------------------------------------------------------------


def test_numpydoc_parameters_are_parsed():
    doc = """Thing.

    Parameters
    ----------
    alpha, beta : float, default 1
        Two weights
        on two lines.
    mode : {'fast', "slow"}, default 'fast'

    Returns
    -------
    x : int
        Not a parameter.
    """
    parsed = parse_numpydoc_parameters(doc)
    assert parsed["alpha"] == ("float, default 1", "Two weights on two lines.")
    assert parsed["beta"] == parsed["alpha"]
    assert parsed["mode"][0].startswith("{'fast'")
    assert "x" not in parsed


def test_forms_follow_estimator_signatures(qtbot):
    for cls in (PCA, LSF, Varimax):
        form = ParameterForm(cls)
        qtbot.addWidget(form)
        # defaults round-trip: the form's values build the same estimator as cls()
        assert form.values() == {k: cls().get_params()[k] for k in cls.setting_names()}
    form = ParameterForm(LSF)
    qtbot.addWidget(form)
    assert isinstance(form.editor("split"), QCheckBox)
    assert isinstance(form.editor("max_iter"), QSpinBox)
    assert isinstance(form.editor("lambda_"), QDoubleSpinBox)
    assert isinstance(form.editor("graph"), QComboBox)
    assert [form.editor("graph").itemText(i) for i in range(form.editor("graph").count())] == \
        ["mesh", "euclidean"]
    assert isinstance(form.editor("tol"), QLineEdit)  # 1e-5 is shown as typed
    assert "Outer block-coordinate-descent" in form.editor("max_iter").toolTip()
    form.editor("max_iter").setValue(7)
    form.editor("graph").setCurrentText("euclidean")
    form.editor("tol").setText("1e-3")
    values = form.values()
    assert (values["max_iter"], values["graph"], values["tol"]) == (7, "euclidean", 1e-3)
    form.editor("tol").setText("-2")
    with pytest.raises(ValueError, match="tol"):
        form.values()
    form.reset()
    assert form.values() == {k: LSF().get_params()[k] for k in LSF.setting_names()}
    assert "connectivity" not in form.names()  # the mesh graph comes from the pipeline
    # None allowed: the spin box minimum stands for None
    pca_form = ParameterForm(PCA)
    qtbot.addWidget(pca_form)
    assert pca_form.values()["n_factors"] is None
    pca_form.editor("n_factors").setValue(3)
    assert pca_form.values()["n_factors"] == 3


# ------------------------------------------------------------------------------------------
# Loading
# ------------------------------------------------------------------------------------------


def test_load_lists_vertex_counts_and_problems(panel, qtbot, tmp_path):
    files = demo_files(2)
    bad = tmp_path / "broken.vtk"
    bad.write_text("this is not a VTK file\n")
    empty = tmp_path / "notes.stl"
    empty.write_bytes(b"")
    panel.add_paths([str(files[0]), str(bad), str(empty)])
    wait_idle(qtbot, panel, 20000)
    assert [e.name for e in panel.state.entries] == [files[0].name, "broken.vtk", "notes.stl"]
    good, broken, blank = (panel.mesh_list.topLevelItem(i) for i in range(3))
    assert int(good.text(1)) == panel.state.entries[0].mesh.n_vertices > 1000
    assert broken.text(1) == "" and broken.text(3)  # the problem is shown, nothing aborted
    assert blank.text(3)
    assert len(panel.usable_entries()) == 1
    assert not panel.build_button.isEnabled()  # fewer than 3 usable meshes
    # drag and drop of a file adds it too
    mime = QMimeData()
    mime.setUrls([QUrl.fromLocalFile(str(files[1]))])
    drop = QDropEvent(QPointF(10, 10), Qt.CopyAction, mime, Qt.LeftButton, Qt.NoModifier)
    panel.dropEvent(drop)
    wait_idle(qtbot, panel, 20000)
    assert [e.name for e in panel.usable_entries()] == [files[0].name, files[1].name]
    # unticking a mesh leaves it out of training
    panel.mesh_list.topLevelItem(0).setCheckState(0, Qt.Unchecked)
    assert [e.name for e in panel.usable_entries()] == [files[1].name]
    # the list is rebuilt after the signal (rebuilding inside it deleted the item: a crash)
    qtbot.wait(50)
    assert panel.mesh_list.topLevelItemCount() == 4
    assert panel.mesh_list.topLevelItem(0).checkState(0) == Qt.Unchecked


# ------------------------------------------------------------------------------------------
# Build, inspect, cancel, rebuild, save
# ------------------------------------------------------------------------------------------


def test_build_inspect_cancel_save(panel, qtbot, tmp_path):
    files = demo_files()
    panel.add_paths([str(f) for f in files])
    wait_idle(qtbot, panel, 20000)
    assert len(panel.usable_entries()) == N_TRAIN
    panel.n_references.setValue(1)
    panel.model_method.setCurrentText("pca")

    # --- build through the panel, watching the event loop stay responsive ----------------
    progress = []
    panel.progress_bar.valueChanged.connect(progress.append)
    with GapMeter() as gaps, qtbot.waitSignal(panel.model_built, timeout=180000) as built:
        qtbot.mouseClick(panel.build_button, Qt.LeftButton)
        assert not panel.build_button.isEnabled() and panel.cancel_button.isEnabled()
    wait_idle(qtbot, panel, 5000)
    model = built.args[0]
    assert gaps.ticks > 0  # the GUI thread went on processing events during the build
    assert max(progress) == 1000 and len(progress) > 3
    assert model.method == "pca" and model.n_factors == N_TRAIN - 1
    assert sorted(model.source_meshes) == sorted(f.name for f in files)
    assert panel.build_button.isEnabled() and not panel.cancel_button.isEnabled()
    corr = panel.state.stages["correspondence"].result
    align = panel.state.stages["alignment"].result
    assert model.n_vertices == corr.meshes[0].n_vertices
    fits = [float(panel.mesh_list.topLevelItem(i).text(2)) for i in range(N_TRAIN)]
    assert 0.0 <= min(fits) and max(fits) < 1.0  # mm: corresponded meshes cover the originals
    # the model reproduces the aligned training shapes exactly (K - 1 PCA modes)
    coef = np.linalg.lstsq(model.basis, (align.aligned - model.mean).reshape(N_TRAIN, -1).T,
                           rcond=None)[0]
    recon = model.mean + (model.basis @ coef).T.reshape(align.aligned.shape)
    assert np.abs(recon - align.aligned).max() < 1e-6

    # --- factor view: colour map and slider ----------------------------------------------
    panel.tabs.setCurrentWidget(panel.factor_view)
    view = panel.factor_view
    assert view.factor_list.count() == model.n_factors
    np.testing.assert_allclose(view.displayed_points(), model.mean)
    view.factor_list.setCurrentRow(1)
    view.slider.setValue(250)  # +2.5 SD
    expected = model.mean + 2.5 * np.sqrt(model.coef_var[1]) * model.factors[1]
    np.testing.assert_allclose(view.displayed_points(), expected, atol=1e-9)
    moved = np.linalg.norm(view.displayed_points() - model.mean, axis=1)
    assert moved.max() > 0.5  # mm: a visible deformation
    np.testing.assert_allclose(view.actor.mapper.dataset.points, expected, atol=1e-5)
    view.slider.setValue(-300)
    np.testing.assert_allclose(view.displayed_points(),
                               model.mean - 3 * np.sqrt(model.coef_var[1]) * model.factors[1],
                               atol=1e-9)
    magnitude = view.actor.mapper.dataset.point_data["mm at 1 SD"]
    np.testing.assert_allclose(magnitude, np.sqrt(model.coef_var[1])
                               * np.linalg.norm(model.factors[1], axis=1))

    # --- samples -----------------------------------------------------------------------------
    panel.tabs.setCurrentWidget(panel.samples_view)
    samples = panel.samples_view.samples
    assert samples is not None and samples.shape == (6, model.n_vertices, 3)
    coef = np.linalg.lstsq(model.basis, (samples - model.mean).reshape(6, -1).T, rcond=None)[0]
    np.testing.assert_allclose(model.mean + (model.basis @ coef).T.reshape(samples.shape),
                               samples, atol=1e-8)  # samples lie in the model's span

    # --- save and reload identical -----------------------------------------------------------
    path = panel.save_model(tmp_path / "pca_model.npz")
    loaded = load_model(path)
    for name in ("mean", "factors", "coef_var", "faces", "world_transform"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(model, name))
    assert loaded.method == model.method and loaded.source_meshes == model.source_meshes
    with qtbot.waitSignal(panel.use_for_segmentation, timeout=1000) as used:
        qtbot.mouseClick(panel.use_button, Qt.LeftButton)
    assert used.args == [path]

    # --- changing the model parameters reruns only the model stage -----------------------
    panel.model_method.setCurrentText("lsf")
    panel.current_form().editor("max_iter").setValue(100000)  # long enough to cancel
    panel.current_form().editor("tol").setText("0")
    assert panel.stale_stages() == ["model"]
    with qtbot.waitSignal(panel.progress_bar.valueChanged, timeout=30000):
        qtbot.mouseClick(panel.build_button, Qt.LeftButton)
    qtbot.waitUntil(lambda: panel.progress_bar.value() > 0, timeout=60000)
    assert panel._worker_stage == "model"
    qtbot.wait(300)
    worker = panel._worker
    qtbot.mouseClick(panel.cancel_button, Qt.LeftButton)
    wait_idle(qtbot, panel, 5000)  # Cancel is reached at the next progress report
    assert worker.isFinished() and worker.was_cancelled
    assert "cancelled" in panel.status_label.text()
    assert panel.progress_bar.format() == "cancelled"
    assert panel.build_button.isEnabled() and not panel.cancel_button.isEnabled()
    assert panel.state.stages["correspondence"].result is corr  # earlier stages intact
    assert panel.state.stages["alignment"].result is align
    assert panel.state.model is model  # the last complete model is still shown
    assert panel.stage_labels["model"].text().startswith("out of date")

    # --- a quick method then builds from the cached stages only ----------------------------
    panel.model_method.setCurrentText("varimax")
    assert panel.stale_stages() == ["model"]  # only the model stage is to run
    with qtbot.waitSignal(panel.model_built, timeout=30000) as built:
        qtbot.mouseClick(panel.build_button, Qt.LeftButton)
    wait_idle(qtbot, panel, 5000)
    assert built.args[0].method == "varimax"
    assert panel.state.stages["correspondence"].result is corr
    assert panel.stale_stages() == []

    # --- evaluation of two methods side by side -------------------------------------------
    panel.eval_checks["pca"].setChecked(True)
    panel.eval_checks["varimax"].setChecked(True)
    qtbot.mouseClick(panel.evaluate_button, Qt.LeftButton)
    wait_idle(qtbot, panel, 120000)
    results = panel.state.evaluation
    assert list(results) == ["pca", "varimax"], panel.status_label.text()
    table = panel.evaluation_view.table
    assert table.rowCount() == 2 and table.verticalHeaderItem(1).text() == "varimax"
    headers = [table.horizontalHeaderItem(c).text() for c in range(table.columnCount())]
    assert "g avg (mm)" in headers and "g0.05 avg (mm)" in headers and "s avg (mm)" in headers
    assert panel.evaluation_view.canvas is not None
    for method in results:  # K - 1 factors span the centred training set: no error
        assert np.max(results[method]["reconstruction"]["max"]) < 1e-6
        assert np.min(results[method]["generalisation"]["avg"]) > 0.01
    # the evaluation of the shown model's method goes into its file's metadata
    assert panel.state.model.info["evaluation"]["method"] == "varimax"
    assert panel.state.model.info["correspondence"]["reference"] == corr.reference_name
    # PCA and its rotation span the same space: same generalisation
    np.testing.assert_allclose(results["pca"]["generalisation"]["avg"],
                               results["varimax"]["generalisation"]["avg"], rtol=1e-6)


def test_cancel_during_correspondence(panel, qtbot):
    files = demo_files()
    panel.add_paths([str(f) for f in files])
    wait_idle(qtbot, panel, 20000)
    panel.n_references.setValue(2)
    with GapMeter() as gaps:
        with qtbot.waitSignal(panel.progress_bar.valueChanged, timeout=30000):
            qtbot.mouseClick(panel.build_button, Qt.LeftButton)
        assert panel._worker_stage == "correspondence"
        qtbot.wait(1500)  # the process pool is registering
        assert panel.is_busy
        worker = panel._worker
        qtbot.mouseClick(panel.cancel_button, Qt.LeftButton)
        # generous: a loaded machine can take seconds to stop the pool; what is checked is
        # that Cancel is reached and no work goes on after it, not how fast
        wait_idle(qtbot, panel, 30000)
    assert gaps.ticks > 0  # the GUI thread kept processing events while the pool registered
    assert worker.isFinished() and worker.was_cancelled  # no work goes on after Cancel
    assert "Correspondence cancelled" in panel.status_label.text()
    assert panel.state.stages == {} and panel.state.model is None
    assert panel.build_button.isEnabled() and not panel.cancel_button.isEnabled()
    assert panel.stage_labels["correspondence"].text() == "not run"

    # closing the panel while a stage runs stops the worker (and its process pool) cleanly
    with qtbot.waitSignal(panel.progress_bar.valueChanged, timeout=30000):
        qtbot.mouseClick(panel.build_button, Qt.LeftButton)
    qtbot.wait(500)
    worker = panel._worker
    assert worker is not None and worker.stage == "correspondence"
    panel.close_views()  # returns once the worker and its pool are stopped
    assert worker.isFinished() and worker.was_cancelled
    panel.close_views()  # idempotent


def test_lsf_factors_from_corresponded_meshes_show_planted_regions(panel, qtbot, tmp_path):
    """Meshes already in correspondence (shared topology) skip CPD; LSF recovers the planted
    local factors and the factor view colours exactly their regions."""
    base, faces = ellipsoid_surface(3)
    planted = planted_shapes(base, faces, n_shapes=16, n_factors=4, noise=0.02, random_state=3)
    for k, shape in enumerate(planted.shapes):
        save_mesh(tmp_path / f"shape_{k:02d}.vtk", TriMesh(shape, faces))
    panel.add_paths([str(tmp_path)])
    wait_idle(qtbot, panel, 20000)
    assert len(panel.usable_entries()) == 16
    panel.reference_combo.setCurrentText(NO_CORRESPONDENCE)
    panel.align_method.setCurrentText("none")
    panel.model_method.setCurrentText("lsf")
    panel.current_form().editor("n_factors").setValue(8)
    with qtbot.waitSignal(panel.model_built, timeout=60000) as built:
        qtbot.mouseClick(panel.build_button, Qt.LeftButton)
    wait_idle(qtbot, panel, 5000)
    model = built.args[0]
    assert model.method == "lsf" and model.params["n_factors"] == 8
    # unaligned shapes: the model sits where the shapes are
    np.testing.assert_allclose(model.world_transform, np.eye(4), atol=1e-6)
    iou = support_iou(planted.factors, model.factors)
    assert iou.mean() > 0.75, iou
    panel.tabs.setCurrentWidget(panel.factor_view)
    view = panel.factor_view
    for m in range(min(4, model.n_factors)):
        view.factor_list.setCurrentRow(m)
        shown = view.actor.mapper.dataset.point_data["mm at 1 SD"]
        coloured = shown > 0.1 * shown.max()
        # the coloured region is one planted support (local), not the whole surface
        best = max(range(len(planted.supports)),
                   key=lambda j: (coloured & planted.supports[j]).sum())
        inside = (coloured & planted.supports[best]).sum() / coloured.sum()
        assert coloured.mean() < 0.3 and inside > 0.8


def test_mesh_list_shows_what_grooming_repaired(panel, qtbot, tmp_path):
    from core.datasets.shapes import known_homology_shapes

    pop = known_homology_shapes("bean", 4, seed=8, n_points=(150, 170))
    paths = []
    for k, mesh in enumerate(pop.meshes):
        v, f = mesh.vertices, mesh.faces
        if k == 2:  # a stray island of a few voxels beside the structure
            island = v[f[:4]].reshape(-1, 3)[:4] * 0.05 + v.max(axis=0) + 5.0
            f = np.vstack([f, np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]) + len(v)])
            v = np.vstack([v, island])
        paths.append(tmp_path / f"shape_{k}.vtk")
        save_mesh(paths[-1], TriMesh(v, f))
    panel.add_paths([str(p) for p in paths])
    wait_idle(qtbot, panel, 20000)
    panel.n_references.setValue(1)
    panel.model_method.setCurrentText("pca")
    with qtbot.waitSignal(panel.model_built, timeout=120000):
        qtbot.mouseClick(panel.build_button, Qt.LeftButton)
    wait_idle(qtbot, panel, 5000)
    rows = {panel.mesh_list.topLevelItem(i).text(0): panel.mesh_list.topLevelItem(i)
            for i in range(4)}
    assert panel.mesh_list.headerItem().text(4) == "Grooming"
    assert rows["shape_2.vtk"].text(4).startswith("dropped 1 piece"), rows["shape_2.vtk"].text(4)
    assert all("dropped" not in rows[f"shape_{k}.vtk"].text(4) for k in (0, 1, 3))
    # the run box says what the correspondence safeguard tried and kept, as the record does
    record = panel.state.stages["correspondence"].result.safeguard
    remesh = {s["stage"]: s for s in record["stages"]}["remesh"]
    shown = panel.run_box.safeguard_label
    assert shown.isVisibleTo(panel) and shown.text().startswith("Safeguard: remesh ")
    assert f"{remesh['criterion_mm']['no remesh']:.3f} mm" in shown.text()
    assert shown.text().count("Safeguard: ") == 1 + len(
        {s["stage"]: s for s in record["stages"]}["refinement"]["passes"])
