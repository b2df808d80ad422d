"""Issue 17's segmentation-side defects, each driven as a user meets it (each failed before)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402
from PySide6.QtWidgets import QFileDialog  # noqa: E402

from app import demo  # noqa: E402


def click(view, world):
    x, y = view.world_to_screen(world)
    QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(int(round(x)), int(round(y))))


# -- defect 7: messages and guards -----------------------------------------------------------

def test_too_few_points_for_the_pose_is_a_hint_not_an_error(make_window):
    window = make_window()
    window.fit_panel.set_settings(pose="similarity")
    window.set_tool("draw")
    view = window.workspace.views["axial"]
    click(view, window.state.crosshair)
    window.wait_for_refit()
    info = window.state.active.fit_info
    assert info.level == "info" and "2 more point" in info.message
    assert "#c0392b" not in window.fit_panel.result.text()          # not shown in red
    assert window.runner.n_started == 0                               # no fit was tried
    click(view, window.state.crosshair + [4.0, 0, 0])
    click(view, window.state.crosshair + [0, 5.0, 0])
    window.wait_for_refit(20000)
    assert window.state.active.fit_info.n_iter > 0 and not window.state.active.fit_info.message


def test_save_and_export_without_an_image_say_so_before_any_dialog(make_window, monkeypatch):
    window = make_window(load_demo=False)
    opened = []
    monkeypatch.setattr(QFileDialog, "getSaveFileName",
                        staticmethod(lambda *a, **k: opened.append("save") or ("", "")))
    monkeypatch.setattr(QFileDialog, "getExistingDirectory",
                        staticmethod(lambda *a, **k: opened.append("folder") or ""))
    assert not window.save_session(ask=True)
    assert "open an image first" in window.statusBar().currentMessage()
    window.export_dialog("labels")
    window.export_dialog("points")
    window.export_all_dialog()
    assert opened == []
    assert "nothing to export" in window.statusBar().currentMessage()


def test_export_all_asks_before_overwriting_an_earlier_export(make_window, tmp_path, monkeypatch):
    window = make_window()
    folder = tmp_path / "case"
    monkeypatch.setattr(QFileDialog, "getExistingDirectory", staticmethod(lambda *a, **k: str(folder)))
    window.export_all_dialog()
    first = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    # the active structure's files and every structure's (one here: with its name and colour
    # for 3D Slicer, and ITK-SNAP's label description)
    assert set(first) == {"segmentation.nii.gz", "surface.vtk", "all_labels.seg.nrrd",
                          "all_labels.nii.gz", "all_labels.txt"}
    window.state.active.place_at(window.state.crosshair + [3.0, 0, 0])      # a different result
    questions = []
    window.ask = lambda text: questions.append(text) or False
    window.export_all_dialog()
    assert questions and "segmentation.nii.gz" in questions[0] and "all_labels.seg.nrrd" in questions[0]
    assert {p.name: p.stat().st_mtime_ns for p in folder.iterdir()} == first   # untouched
    window.ask = lambda text: True
    window.export_all_dialog()
    assert all(p.stat().st_mtime_ns != first[p.name] for p in folder.iterdir())


def test_image_that_misses_the_model_is_warned_about(make_window, tmp_path):
    from core.io import load_volume, save_volume

    window = make_window()
    image = load_volume(demo.demo_image())
    far = image.affine.copy()
    far[:3, 3] += [400.0, 0.0, 0.0]                                # scanner coordinates elsewhere
    path = tmp_path / "far.nii.gz"
    save_volume(path, image.data[::4, ::4, ::4], far @ np.diag([4.0, 4.0, 4.0, 1.0]))
    window.load_image(path)
    assert "do not overlap" in window.statusBar().currentMessage()


def test_delete_without_a_point_under_the_cursor_stays_on_the_slice(make_window):
    window = make_window()
    window.set_tool("draw")
    view = window.workspace.views["axial"]
    c = window.state.crosshair
    click(view, c)
    click(view, c + [5.0, 0, 0])
    window.state.step_slice("axial", 3)                  # a slice with no points
    window.active_view = "axial"
    window.cursor_label.on_hover(None)
    window.delete_point()
    assert len(window.state.active.points) == 2                 # nothing removed from the other slice
    assert "No point to delete" in window.statusBar().currentMessage()
    window.state.step_slice("axial", -3)
    window.delete_point()                                # back on it: its last point goes
    assert len(window.state.active.points) == 1
    assert window.state.active.points.xyz[0] == pytest.approx(c, abs=1.0)
    window.wait_for_refit()


# -- defect 6: stale read-outs ----------------------------------------------------------------

RING = [(6 * np.cos(t), 9 * np.sin(t), 0.0) for t in np.linspace(0, 2 * np.pi, 8, endpoint=False)]


def _draw_ring(window):
    window.set_tool("draw")
    view = window.workspace.views["axial"]
    for d in RING:
        click(view, window.state.crosshair + np.asarray(d))


def test_slider_edit_updates_the_residual_and_the_next_refit_says_it_refitted(make_window):
    from core.geometry.toolkit import surface_distance

    window = make_window()
    _draw_ring(window)
    window.wait_for_refit(20000)
    fitted = window.state.active.fit_info.residual_mm
    window.factors_panel.set_factor_sd(0, 2.5)
    info = window.state.active.fit_info
    state = window.state
    expected = np.mean(surface_distance(state.active.points.xyz, state.active.surface_vertices(),
                                        state.active.model.faces))
    assert info.residual_mm == pytest.approx(expected) and info.residual_mm != pytest.approx(fitted)
    assert "after your edit" in window.fit_panel.result.text()
    click(window.workspace.views["axial"], window.state.crosshair + [0.0, -9.5, 0.0])
    window.wait_for_refit(20000)
    assert "slider values" in window.state.active.fit_info.message        # not silently undone
    assert window.state.active.fit_info.n_iter > 0


def test_without_automatic_refit_the_fit_is_marked_out_of_date(make_window):
    window = make_window()
    _draw_ring(window)
    window.wait_for_refit(20000)
    window.fit_panel.auto.setChecked(False)
    click(window.workspace.views["axial"], window.state.crosshair + [0.0, -9.5, 0.0])
    assert window.state.active.fit_info.out_of_date
    assert "Out of date" in window.fit_panel.result.text()
    window.fit_panel.refit_button.click()
    window.wait_for_refit(20000)
    assert not window.state.active.fit_info.out_of_date
    assert "Out of date" not in window.fit_panel.result.text()


def test_reopened_session_reads_out_its_fit(make_window, tmp_path):
    window = make_window()
    _draw_ring(window)
    window.wait_for_refit(20000)
    residual = window.state.active.fit_info.residual_mm
    path = tmp_path / "s.json"
    assert window.save_session(path=path)
    other = make_window(load_demo=False)
    other.open_session(path)
    assert "No fit yet" not in other.fit_panel.result.text()
    assert "restored" in other.fit_panel.result.text()
    assert other.state.active.fit_info.residual_mm == pytest.approx(residual, abs=0.05)


# -- defect 8: strokes and the small-window layout ---------------------------------------------

def _drag(view, a, b, steps=12):
    start, end = view.world_to_screen(a), view.world_to_screen(b)
    QTest.mousePress(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(*np.rint(start).astype(int)))
    for t in np.linspace(0, 1, steps):
        QTest.mouseMove(view, QPoint(*np.rint((1 - t) * start + t * end).astype(int)))
    QTest.mouseRelease(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                       QPoint(*np.rint(end).astype(int)))


def test_separate_strokes_on_one_slice_are_not_joined(make_window):
    from app.views.slice_view import POINT_COLOR

    window = make_window()
    window.set_tool("draw")
    view = window.workspace.views["axial"]
    c = window.state.crosshair
    _drag(view, c + [-14.0, -8.0, 0], c + [-14.0, 8.0, 0])      # left side, downwards
    _drag(view, c + [14.0, 8.0, 0], c + [14.0, -8.0, 0])        # right side, upwards
    pts = window.state.active.points
    first = pts.stroke[0]
    assert len(np.unique(pts.stroke)) == 2 and np.sum(pts.stroke == first) >= 5
    # nothing painted on the straight line that used to join the end of one to the other
    image = view.grab().toImage()
    ratio = image.width() / view.width()
    gap = 0.5 * (pts.xyz[pts.stroke == first][-1] + pts.xyz[pts.stroke != first][0])
    x, y = view.world_to_screen(gap)
    target = (POINT_COLOR.red(), POINT_COLOR.green(), POINT_COLOR.blue())
    for dx in range(-2, 3):
        color = image.pixelColor(int((x + dx) * ratio), int(y * ratio))
        assert (color.red(), color.green(), color.blue()) != target
    # single clicks on a slice still make one contour
    window.undo()
    window.undo()
    for d in ([0, 5.0, 0], [5.0, 0, 0], [0, -5.0, 0]):
        click(view, c + d)
    assert len(np.unique(window.state.active.points.stroke)) == 1
    window.wait_for_refit(20000)


def test_small_window_keeps_titles_off_the_letters_and_the_side_panel_can_go(make_window, qtbot):
    window = make_window(size=(800, 600))
    window.render_now()
    for name, view in window.workspace.views.items():
        layout = view.label_layout()
        title, top = layout["title"][0], layout["top"][0]
        assert not title.intersects(top), name
        assert layout["window"][0].left() > layout["bottom"][0].right() or \
            not layout["window"][0].intersects(layout["bottom"][0]), name
    assert window.registry["side-panel"] in window.registry.menu("view").actions()
    width = window.workspace.views["axial"].width()
    window.registry["side-panel"].trigger()
    qtbot.waitUntil(lambda: window.workspace.views["axial"].width() > width + 80, timeout=3000)
    assert not window.side_dock.isVisible()
    window.tabs.setCurrentIndex(1) if window.tabs.count() > 1 else None
    window.tabs.setCurrentIndex(0)
    assert not window.side_dock.isVisible()          # stays hidden across tab switches
    window.registry["side-panel"].trigger()
    assert window.side_dock.isVisible()


# -- defect 2: laterality ---------------------------------------------------------------------

def test_image_without_sform_or_qform_is_marked_unknown_and_exports_ask(make_window, tmp_path):
    import nibabel as nib

    from core.io import load_volume

    window = make_window()
    demo_image = load_volume(demo.demo_image())
    header = nib.Nifti1Header()
    header.set_data_shape(demo_image.shape)
    image = nib.Nifti1Image(demo_image.data, None, header)
    image.set_sform(None, code=0)
    image.set_qform(None, code=0)
    path = tmp_path / "no_orientation.nii.gz"
    nib.save(image, str(path))
    window.load_image(path)
    assert not window.state.orientation_known
    assert "orientation is unknown" in window.statusBar().currentMessage()
    for name, view in window.workspace.views.items():
        layout = view.label_layout()
        assert {layout[edge][1] for edge in ("left", "right", "top", "bottom")} == {"?"}, name
        assert "orientation unknown" in layout["title"][1]
    window.state.active.place_at(window.state.crosshair)
    questions = []
    window.ask = lambda text: questions.append(text) or False
    assert window.export_all(tmp_path / "out") == [] and not (tmp_path / "out").exists()
    assert "left" in questions[0] and "right" in questions[0]
    window.ask = lambda text: True
    assert {p.name for p in window.export_all(tmp_path / "out")} == {
        "segmentation.nii.gz", "surface.vtk", "all_labels.seg.nrrd", "all_labels.nii.gz",
        "all_labels.txt"}
    window.load_image(demo.demo_image())                # a known orientation: letters again
    assert window.workspace.views["axial"].label_layout()["left"][1] == "R"


# -- defect 5: imported points -----------------------------------------------------------------

def test_imported_contours_are_grouped_by_plane_and_keep_their_normals(make_window, tmp_path):
    from core.io import load_points, save_points

    window = make_window()
    source = demo.demo_points()
    if source is None:
        pytest.skip("demo contour points missing")
    pset = load_points(source)
    window.import_points(source)
    pts = window.state.active.points
    assert len(pts) == len(pset) and pts.n_slices() == 3                  # three contours
    assert window.tools_panel.count.text() == f"{len(pset)} contour point(s) on 3 slice(s)"
    assert np.allclose(window.state.active.point_normals(), pset.normals, atol=1e-6)
    # each contour is on its own axis-aligned slice: Clear slice removes one of them
    sagittal = pts.frame == 2
    x = float(np.mean(pts.xyz[sagittal, 0]))
    window.state.set_crosshair(np.r_[x, window.state.crosshair[1:]])
    window.active_view = "sagittal"
    window.clear_active_slice()
    assert len(window.state.active.points) == len(pset) - int(sagittal.sum())
    # a tilted contour without normals: one group, normals perpendicular in its plane
    t = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    tilt = np.radians(25)
    ring = np.stack([8 * np.cos(t), 6 * np.sin(t) * np.cos(tilt), 6 * np.sin(t) * np.sin(tilt)], 1)
    ring += window.state.crosshair
    save_points(tmp_path / "tilted.csv", ring)
    window.state.active.clear_points()
    window.import_points(tmp_path / "tilted.csv")
    assert window.state.active.points.n_slices() == 1
    assert "1 oblique" in window.statusBar().currentMessage()
    window.wait_for_refit(20000)


# -- defect 1: a bad fit is flagged ------------------------------------------------------------

def test_implausible_fit_is_flagged_and_export_asks(make_window, tmp_path):
    window = make_window()
    window.fit_panel.set_settings(pose="none")          # the model cannot follow the points
    window.set_tool("draw")
    view = window.workspace.views["axial"]
    far = window.state.crosshair + np.array([30.0, 25.0, 0.0])
    for t in np.linspace(0, 2 * np.pi, 10, endpoint=False):
        click(view, far + [6 * np.cos(t), 6 * np.sin(t), 0.0])
    window.wait_for_refit(30000)
    info = window.state.active.fit_info
    assert info.n_iter > 0 and info.warnings
    assert any("from the surface" in w for w in info.warnings)
    text = window.fit_panel.result.text()
    assert "implausible" in text and "Check this fit" in text
    questions = []
    window.ask = lambda q: questions.append(q) or False
    assert window.export_all(tmp_path / "out") == [] and "implausible" in questions[0]
    # a good fit is not flagged
    window.state.active.clear_points()
    window.fit_panel.set_settings(pose="similarity")
    window.state.active.reset_placement()
    centre = window.state.active.surface_vertices().mean(axis=0)
    from core.geometry.slicing import polylines

    line = polylines(window.state.active.surface_vertices(), window.state.active.model.faces,
                     np.array([0, 0, window.state.crosshair[2]]), np.array([0, 0, 1.0]))[0]
    for p in line.points[:: max(1, len(line.points) // 10)]:
        click(view, p)
    window.wait_for_refit(30000)
    assert window.state.active.fit_info.n_iter > 0 and window.state.active.fit_info.warnings == ()
    assert np.isfinite(centre).all()
