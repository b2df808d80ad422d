"""Saving and exporting from the GUI: label map, mesh, points, sessions, crash recovery."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402
from recovery_runs import crashing_run  # noqa: E402

from app import demo  # noqa: E402
from app.window import MainWindow  # noqa: E402
from core.geometry.mesh import volume as mesh_volume  # noqa: E402
from core.geometry.toolkit import vertex_normals  # noqa: E402
from core.io import load_mesh, load_points, load_volume  # noqa: E402


def _need_demo():
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")


@pytest.fixture
def state_dir(tmp_path, monkeypatch):
    folder = tmp_path / "state"
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(folder))
    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    return folder


def _window(qtbot, recovery=False) -> MainWindow:
    win = MainWindow(with_3d=False, recovery=recovery)
    qtbot.addWidget(win)
    win.resize(1200, 850)
    return win


def _draw(window, offsets, frame="axial"):
    view = window.workspace.views[frame]
    window.set_tool("draw")
    for d in offsets:
        x, y = view.world_to_screen(window.state.crosshair + np.asarray(d, float))
        QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                         QPoint(int(round(x)), int(round(y))))


RING = [(6 * np.cos(t), 9 * np.sin(t), 0.0) for t in np.linspace(0, 2 * np.pi, 10, endpoint=False)]


def test_export_label_map_mesh_and_points_reread(qtbot, tmp_path, state_dir):
    _need_demo()
    window = _window(qtbot)
    window.load_demo()
    window.show()
    _draw(window, RING)
    window.wait_for_refit(20000)
    written = window.export_all(tmp_path / "out")
    names = sorted(p.name for p in written)
    # the active structure's files, and every structure's (Export all; no DICOM source here)
    assert {"points.csv", "points.mrk.json", "segmentation.nii.gz", "surface.vtk"} <= set(names)
    assert {"all_labels.seg.nrrd", "all_labels.nii.gz"} <= set(names), names
    assert not [n for n in names if n.endswith(".dcm")]

    labels = load_volume(tmp_path / "out" / "segmentation.nii.gz")
    image = window.state.volume
    assert labels.shape == image.shape
    assert np.allclose(labels.affine, image.affine)
    assert set(np.unique(labels.data)) == {0, 1}
    vertices, faces = window.state.active.surface_vertices(), window.state.active.model.faces
    inside_mm3 = float(labels.data.sum()) * abs(np.linalg.det(image.affine[:3, :3]))
    assert inside_mm3 == pytest.approx(mesh_volume(vertices, faces), rel=0.12)
    # points 1.5 mm inside / outside the surface along its normals are labelled 1 / 0
    normals = vertex_normals(vertices, faces)
    for sign, expected in ((-1.5, 1), (1.5, 0)):
        ijk = np.rint(image.world_to_voxel(vertices + sign * normals)).astype(int)
        assert np.mean(labels.data[tuple(ijk.T)] == expected) > 0.9

    mesh = load_mesh(tmp_path / "out" / "surface.vtk")
    assert np.allclose(mesh.vertices, vertices, atol=1e-4)
    assert np.array_equal(mesh.faces, faces)

    for name in ("points.csv", "points.mrk.json"):
        pset = load_points(tmp_path / "out" / name)
        assert np.allclose(pset.points, window.state.active.points.xyz, atol=1e-5), name
    window.close()


def test_session_round_trip_with_relative_paths(qtbot, tmp_path, state_dir):
    _need_demo()
    data = tmp_path / "case" / "data"
    data.mkdir(parents=True)
    image = data / "t1.nii.gz"
    model = data / "model.npz"
    shutil.copy(demo.demo_image(), image)
    shutil.copy(demo.demo_model(), model)
    window = _window(qtbot)
    window.load_image(image)
    window.load_model(model)
    window.show()
    _draw(window, RING)
    window.wait_for_refit(20000)
    window.factors_panel.set_factor_sd(1, 1.5)
    window.state.set_window(300.0, 120.0)
    session_file = tmp_path / "case" / "session.json"
    assert window.windowTitle().endswith(" *")          # unsaved edits
    assert window.save_session(path=session_file)
    assert not window.windowTitle().endswith(" *") and "session.json" in window.windowTitle()
    doc = json.loads(session_file.read_text())
    assert doc["image"] == "data/t1.nii.gz" and doc["model"] == "data/model.npz"
    active = window.state.active
    points, coef, pose = active.points, active.coef.copy(), active.pose.copy()
    window.close()

    moved = tmp_path / "elsewhere"
    shutil.move(str(tmp_path / "case"), moved)
    other = _window(qtbot)
    other.open_session(moved / "session.json")
    assert other.state.image_path.resolve() == (moved / "data" / "t1.nii.gz").resolve()
    assert np.allclose(other.state.active.points.xyz, points.xyz)
    assert np.array_equal(other.state.active.points.frame, points.frame)
    assert np.allclose(other.state.active.coef, coef) and np.allclose(other.state.active.pose, pose)
    assert (other.state.window, other.state.level) == (300.0, 120.0)
    assert other.factors_panel.value_labels[1].text() == "+1.50"
    other.close()


def test_autosave_and_recovery_after_a_crash(qtbot, tmp_path, state_dir):
    _need_demo()

    window = _window(qtbot, recovery=True)
    window.load_demo()
    window.show()
    _draw(window, RING[:6])
    window.wait_for_refit(20000)
    qtbot.waitUntil(lambda: window.sessions.recovery.path.exists(), timeout=5000)
    window._autosave_timer.stop()
    window.write_recovery()                      # the autosave of the last edit
    points = window.state.active.points.xyz.copy()
    coef = window.state.active.coef.copy()

    # a run that autosaved the same work and then died without cleaning up
    crashing_run("r.write(s.load_session(sys.argv[1]))", str(window.sessions.recovery.path))
    window.close()                               # clean exit: its own file is removed

    asked = []
    fresh = _window(qtbot, recovery=True)
    assert fresh.offer_recovery(ask=lambda text: asked.append(text) or True)
    assert "6 contour point" in asked[0]
    assert np.allclose(fresh.state.active.points.xyz, points)
    assert np.allclose(fresh.state.active.coef, coef)
    assert fresh.state.volume is not None and fresh.state.active.model is not None
    assert not fresh.offer_recovery(ask=lambda text: True)   # offered once
    fresh.close()
    assert not list(state_dir.glob("recovery-*"))
