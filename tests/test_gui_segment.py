"""The segmentation workspace driven like a user: clicks, keys, sliders, refits, undo/redo.

Runs under pytest-xvfb (QT_QPA_PLATFORM=xcb). Most tests build the window without the 3D
view (it adds nothing to what they check and costs start-up time); the screenshot tests in
test_gui_screenshot.py cover it.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QEvent, QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from app import demo  # noqa: E402
from app.window import MainWindow  # noqa: E402
from core.geometry.planes import window_to_uint8  # noqa: E402
from core.geometry.slicing import polylines, sample_polyline  # noqa: E402
from core.geometry.toolkit import surface_distance  # noqa: E402
from core.io import load_model  # noqa: E402

NO_MOD = Qt.KeyboardModifier.NoModifier
LEFT = Qt.MouseButton.LeftButton


def _need_demo():
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")


def click(view, xy, modifier=NO_MOD, button=LEFT):
    QTest.mouseClick(view, button, modifier, QPoint(int(round(xy[0])), int(round(xy[1]))))


def test_demo_loads_image_and_model_at_crosshair(window):
    state = window.state
    assert state.volume is not None and state.active.model is not None
    centroid = state.active.surface_vertices().mean(axis=0)
    # the crosshair starts on the model (snapped to the nearest voxel centre, 1 mm grid)
    assert np.all(np.abs(state.crosshair - centroid) <= 0.5 + 1e-9)
    for name, view in window.workspace.views.items():
        assert view._segments_uv is not None and len(view._segments_uv) > 10, name


def test_click_in_axial_view_lands_on_the_voxel_displayed_there(window, qtbot):
    view = window.workspace.views["axial"]
    window.set_tool("draw")
    volume = window.state.volume
    center_ijk = np.rint(volume.world_to_voxel(window.state.crosshair)).astype(int)
    # far from the model outline and off the crosshair lines (overlays would change the pixel)
    targets = [center_ijk + d for d in ([30, 25, 0], [-35, -21, 0], [27, -40, 0], [-31, 33, 0])]
    image = view.grab().toImage()
    ratio = image.width() / view.width()
    scale = view._base()[0]
    for n, ijk in enumerate(targets, start=1):
        world = volume.voxel_to_world(ijk)
        x, y = view.world_to_screen(world)
        # what is painted at that pixel is the windowed intensity of that voxel
        # the pixel containing the voxel centre (pixel i covers [i, i+1) in widget coordinates)
        grey = image.pixelColor(int(np.floor(x * ratio)), int(np.floor(y * ratio))).red()
        expected = window_to_uint8(np.array([volume.data[tuple(ijk)]]), window.state.window,
                                   window.state.level)[0]
        assert abs(int(grey) - int(expected)) <= 2
        click(view, (x, y))
        assert len(window.state.active.points) == n
        placed = window.state.active.points.xyz[-1]
        assert placed[2] == pytest.approx(world[2], abs=1e-9)      # on the slice
        assert np.linalg.norm(placed - world) <= 0.75 / scale + 1e-9  # within a pixel
    # radiological convention: screen left is patient right (+x), screen up is anterior (+y)
    xs = view.world_to_screen(window.state.active.points.xyz)
    order = np.argsort(xs[:, 0])
    assert np.all(np.diff(window.state.active.points.xyz[order, 0]) < 0)
    assert np.all(np.diff(window.state.active.points.xyz[np.argsort(xs[:, 1]), 1]) < 0)


def test_navigate_click_moves_the_other_views(window):
    axial = window.workspace.views["axial"]
    coronal = window.workspace.views["coronal"]
    sagittal = window.workspace.views["sagittal"]
    target = window.state.crosshair + np.array([-10.0, 15.0, 0.0])
    click(axial, axial.world_to_screen(target))
    assert window.state.crosshair == pytest.approx(target, abs=0.5)
    assert coronal.depth == pytest.approx(window.state.crosshair[1])
    assert sagittal.depth == pytest.approx(window.state.crosshair[0])
    assert coronal._slice.depth == pytest.approx(coronal.depth)


def test_page_keys_and_wheel_step_slices(window, qtbot):
    axial = window.workspace.views["axial"]
    axial.setFocus()
    z0 = window.state.crosshair[2]
    QTest.keyClick(axial, Qt.Key.Key_PageUp)
    assert window.state.crosshair[2] == pytest.approx(z0 + 1.0)
    QTest.keyClick(axial, Qt.Key.Key_PageDown)
    QTest.keyClick(axial, Qt.Key.Key_PageDown)
    assert window.state.crosshair[2] == pytest.approx(z0 - 1.0)
    sagittal = window.workspace.views["sagittal"]
    x0 = window.state.crosshair[0]
    window.state.step_slice("sagittal", 3)
    assert sagittal.depth == pytest.approx(x0 + 3.0)


def _truth_points(model, coef, shift, frames=(("axial", 0.0), ("axial", 4.0), ("coronal", 0.0),
                                              ("coronal", -8.0), ("sagittal", 0.0)), spacing=3.0):
    """Contour points of a known instance on slices through its centre, snapped to voxel planes."""
    truth = model.world_instance(coef) + shift
    centre = np.rint(truth.mean(axis=0))
    out = []
    for name, offset in frames:
        axis = {"sagittal": 0, "coronal": 1, "axial": 2}[name]
        normal = np.eye(3)[axis]
        origin = centre + offset * normal
        lines = polylines(truth, model.faces, origin, normal)
        pts, _ = sample_polyline(lines[0], spacing=spacing)
        out.append((name, origin[axis], pts))
    return truth, out


def test_refit_moves_the_surface_towards_clicked_points(window, qtbot):
    model = window.state.active.model
    rng = np.random.default_rng(3)
    coef = 1.5 * rng.standard_normal(model.n_factors) * np.sqrt(model.coef_var)
    truth, slices = _truth_points(model, coef, shift=np.array([1.5, -2.0, 1.0]))
    faces = model.faces
    before = surface_distance(truth, window.state.active.surface_vertices(), faces).mean()
    window.set_tool("draw")
    clicked = 0
    for name, depth, pts in slices:
        window.state.set_crosshair(np.where(np.eye(3)[{"sagittal": 0, "coronal": 1, "axial": 2}[name]] > 0,
                                            depth, window.state.crosshair))
        view = window.workspace.views[name]
        assert view.depth == pytest.approx(depth)
        for p in pts:
            click(view, view.world_to_screen(p))
            clicked += 1
    assert len(window.state.active.points) == clicked
    applied = []
    window.refit_applied.connect(applied.append)
    qtbot.waitUntil(lambda: bool(applied) and not window.runner.is_busy, timeout=20000)
    # distance from the true surface's vertices to the fitted surface (sliding along the
    # surface is free for a fit to contour points, so vertex-to-vertex distances are not used)
    after = surface_distance(truth, window.state.active.surface_vertices(), faces).mean()
    assert after < 0.6 * before and after < 1.5, (before, after)
    assert window.state.active.fit_info.residual_mm < 1.0
    assert window.state.active.fit_info.n_iter > 0
    # the contour overlay follows the fit: the axial cross-section is now near the truth's
    axial = window.workspace.views["axial"]
    seg = axial._segments_uv.reshape(-1, 2)
    assert axial.depth == pytest.approx(slices[1][1])
    truth_uv = axial.frame.to_plane(slices[1][2])[:, :2]
    d = np.linalg.norm(seg[:, None, :] - truth_uv[None], axis=2).min(axis=0)
    assert np.median(d) < 1.5


def test_undo_redo_with_keyboard_shortcuts(window, qtbot):
    view = window.workspace.views["coronal"]
    window.set_tool("draw")
    c = window.state.crosshair
    for dx in (0.0, 4.0, 8.0):
        click(view, view.world_to_screen(c + [dx, 0, 0]))
    assert len(window.state.active.points) == 3
    with qtbot.waitActive(window):
        window.activateWindow()
    view.setFocus()
    QTest.keyClick(view, Qt.Key.Key_Z, Qt.KeyboardModifier.ControlModifier)
    assert len(window.state.active.points) == 2
    QTest.keyClick(view, Qt.Key.Key_Z, Qt.KeyboardModifier.ControlModifier)
    assert len(window.state.active.points) == 1
    QTest.keyClick(view, Qt.Key.Key_Z,
                   Qt.KeyboardModifier.ControlModifier | Qt.KeyboardModifier.ShiftModifier)
    assert len(window.state.active.points) == 2
    assert window.state.active.points.xyz[-1] == pytest.approx(window.state.crosshair + [4, 0, 0], abs=1.0)
    window.wait_for_refit()


def test_drag_adds_spaced_points_as_one_undo_step(window):
    view = window.workspace.views["axial"]
    window.set_tool("draw")
    c = window.state.crosshair
    start = view.world_to_screen(c)
    end = view.world_to_screen(c + [-12.0, 0, 0])
    QTest.mousePress(view, LEFT, NO_MOD, QPoint(*np.rint(start).astype(int)))
    for t in np.linspace(0, 1, 30):
        xy = (1 - t) * start + t * end
        QTest.mouseMove(view, QPoint(*np.rint(xy).astype(int)))
    QTest.mouseRelease(view, LEFT, NO_MOD, QPoint(*np.rint(end).astype(int)))
    n = len(window.state.active.points)
    assert 6 <= n <= 10          # 12 mm at >= 1.5 mm spacing
    gaps = np.linalg.norm(np.diff(window.state.active.points.xyz, axis=0), axis=1)
    assert np.all(gaps >= 1.5 - 1e-9)
    normals = window.state.active.points.normals()
    assert np.allclose(np.abs(normals[:, 1]), 1.0, atol=0.05)   # perpendicular to a left-right stroke
    window.undo()
    assert len(window.state.active.points) == 0
    window.wait_for_refit()


def test_delete_point_and_clear_slice(window):
    view = window.workspace.views["axial"]
    window.set_tool("draw")
    c = window.state.crosshair
    for dx in (0.0, 5.0, 10.0):
        click(view, view.world_to_screen(c + [dx, 0, 0]))
    click(view, view.world_to_screen(c + [5.0, 0, 0]), Qt.KeyboardModifier.ControlModifier)
    assert len(window.state.active.points) == 2
    assert not np.any(np.isclose(window.state.active.points.xyz[:, 0], c[0] + 5.0, atol=0.6))
    window.state.step_slice("axial", 2)
    click(view, view.world_to_screen(window.state.crosshair))
    assert len(window.state.active.points) == 3
    window.active_view = "axial"
    window.clear_active_slice()
    assert len(window.state.active.points) == 2
    window.state.step_slice("axial", -2)
    window.clear_active_slice()
    assert len(window.state.active.points) == 0
    window.undo()
    assert len(window.state.active.points) == 2
    window.wait_for_refit()


def test_factor_slider_sets_coefficient_in_sd_units(window):
    panel = window.factors_panel
    model = window.state.active.model
    assert len(panel.sliders) == model.n_factors
    panel.set_factor_sd(0, 2.0)
    expected = model.world_instance(np.r_[2.0 * np.sqrt(model.coef_var[0]), np.zeros(model.n_factors - 1)])
    assert np.allclose(window.state.active.surface_vertices(), expected)
    assert panel.value_labels[0].text() == "+2.00"
    window.undo()
    assert np.allclose(window.state.active.coef, 0.0)
    assert panel.sliders[0].value() == 0


def test_place_here_moves_model_centre_to_crosshair(window):
    target = window.state.crosshair + np.array([20.0, -10.0, 5.0])
    window.state.set_crosshair(target)
    window.place_here()
    assert window.state.active.surface_vertices().mean(axis=0) == pytest.approx(window.state.crosshair,
                                                                                abs=1e-6)
    window.undo()
    assert window.state.active.surface_vertices().mean(axis=0) == pytest.approx(
        window.state.active.model.world_instance().mean(axis=0), abs=1e-6)


def test_bad_model_file_is_reported_not_raised(window, tmp_path):
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"this is not a zip file")
    window.open_path(bad)
    message = window.statusBar().currentMessage()
    assert "broken.npz" in message and "Traceback" not in message
    assert window.state.active.model is not None       # the previous model is kept


def test_fit_error_keeps_the_surface_and_shows_the_message(window, qtbot):
    before = window.state.active.surface_vertices().copy()
    window.fit_panel.set_settings(pose="similarity")
    window.set_tool("draw")
    view = window.workspace.views["axial"]
    click(view, view.world_to_screen(window.state.crosshair))   # one point: too few for a similarity
    window.wait_for_refit()
    assert window.state.active.fit_info.message
    assert np.allclose(window.state.active.surface_vertices(), before)


def test_model_with_other_vertex_count_replaces_the_fit(window, tmp_path):
    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import save_model

    shapes, faces = synthetic_shapes(6, subdivisions=2, seed=1)
    model = pca_model(shapes + window.state.crosshair, faces, n_factors=3)
    path = tmp_path / "other.npz"
    save_model(path, model)
    window.load_model(path)
    assert window.state.active.model.n_vertices == load_model(path).n_vertices
    assert len(window.factors_panel.sliders) == 3


def test_builder_tab_is_created_lazily_and_hands_over_its_model(window, qtbot, tmp_path):
    pytest.importorskip("app.panels.builder")
    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import save_model

    assert window.builder is None and window.tabs.count() == 2
    window.tabs.setCurrentIndex(1)
    assert window.builder is not None and window.tabs.currentWidget() is window.builder
    assert not window.side_dock.isVisible()
    shapes, faces = synthetic_shapes(5, subdivisions=2, seed=2)
    path = tmp_path / "built.npz"
    save_model(path, pca_model(shapes + window.state.crosshair, faces, n_factors=2))
    window.builder.use_for_segmentation.emit(str(path))
    assert window.tabs.currentWidget() is window.workspace and window.side_dock.isVisible()
    assert window.state.active.model_path == path and window.state.active.model.n_factors == 2


def test_status_bar_reports_position_voxel_and_value_under_cursor(window):
    view = window.workspace.views["coronal"]
    volume = window.state.volume
    ijk = np.rint(volume.world_to_voxel(window.state.crosshair)).astype(int) + [10, 0, -7]
    world = volume.voxel_to_world(ijk)
    x, y = view.world_to_screen(world)
    # a synthetic move event (QTest.mouseMove moves the X pointer, whose events arrive late)
    from PySide6.QtCore import QPointF
    from PySide6.QtGui import QMouseEvent
    from PySide6.QtWidgets import QApplication

    pos = QPointF(round(x), round(y))
    QApplication.sendEvent(view, QMouseEvent(QEvent.Type.MouseMove, pos, view.mapToGlobal(pos),
                                             Qt.MouseButton.NoButton, Qt.MouseButton.NoButton, NO_MOD))
    text = window.cursor_label.text()
    assert f"voxel ({ijk[0]}, {ijk[1]}, {ijk[2]})" in text
    assert f"value {volume.data[tuple(ijk)]:.4g}" in text
    import re

    shown = [float(v) for v in re.search(r"R ([-+\d.]+)  A ([-+\d.]+)  S ([-+\d.]+) mm", text).groups()]
    assert np.allclose(shown, world, atol=0.05 + 0.75 / view._base()[0])   # rounding + pixel


def test_zoom_pan_keep_clicks_exact_and_window_drag_changes_contrast(window):
    view = window.workspace.views["axial"]
    centre = view.world_to_screen(window.state.crosshair)
    QTest.mousePress(view, Qt.MouseButton.RightButton, NO_MOD, QPoint(*np.rint(centre).astype(int)))
    QTest.mouseMove(view, QPoint(int(centre[0]), int(centre[1]) - 120))
    QTest.mouseRelease(view, Qt.MouseButton.RightButton, NO_MOD, QPoint(int(centre[0]), int(centre[1]) - 120))
    assert view.zoom > 1.5
    QTest.mousePress(view, Qt.MouseButton.MiddleButton, NO_MOD, QPoint(*np.rint(centre).astype(int)))
    QTest.mouseMove(view, QPoint(int(centre[0]) + 40, int(centre[1]) + 25))
    QTest.mouseRelease(view, Qt.MouseButton.MiddleButton, NO_MOD,
                       QPoint(int(centre[0]) + 40, int(centre[1]) + 25))
    window.set_tool("draw")
    target = window.state.crosshair + np.array([3.0, -4.0, 0.0])
    click(view, view.world_to_screen(target))
    assert np.linalg.norm(window.state.active.points.xyz[-1] - target) <= 0.75 / view._base()[0] + 1e-9
    w0, l0 = window.state.window, window.state.level
    QTest.mousePress(view, LEFT, Qt.KeyboardModifier.ShiftModifier, QPoint(100, 100))
    QTest.mouseMove(view, QPoint(160, 70))
    QTest.mouseRelease(view, LEFT, Qt.KeyboardModifier.ShiftModifier, QPoint(160, 70))
    assert window.state.window > w0 and window.state.level > l0
    assert len(window.state.active.points) == 1          # shift-drag did not draw
    window.wait_for_refit()


def test_oblique_image_clicks_and_display_agree(qtbot, tmp_path, monkeypatch):
    """An image whose voxel axes are rotated 20 degrees: views stay world-aligned."""
    from scipy import ndimage

    from core.io import Volume

    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    rng = np.random.default_rng(5)
    data = ndimage.gaussian_filter(rng.normal(size=(60, 50, 40)), 2).astype(np.float32)
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    affine = np.eye(4)
    affine[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([1.0, 1.2, 1.5])
    affine[:3, 3] = [-30, -25, -20]
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1000, 800)
    win.state.set_image(Volume(data, affine))
    win.show()
    qtbot.waitExposed(win)
    view = win.workspace.views["axial"]
    assert not win.state.sampler.aligned
    win.set_tool("draw")
    image = view.grab().toImage()
    ratio = image.width() / view.width()
    for ijk in ([30, 25, 20], [20, 30, 20], [38, 18, 20]):
        world = win.state.volume.voxel_to_world(np.array(ijk, float))
        win.state.set_crosshair(world)
        image = view.grab().toImage()
        x, y = view.world_to_screen(world + [4.0, 3.0, 0])       # off the crosshair lines
        click(view, (x, y))
        placed = win.state.active.points.xyz[-1]
        assert abs(placed[2] - world[2]) < 1e-9
        assert np.linalg.norm(placed - (world + [4.0, 3.0, 0])) <= 0.75 / view._base()[0] + 1e-9
        # the painted grey level is the trilinear intensity at that world point
        vox = win.state.volume.world_to_voxel(placed)
        value = ndimage.map_coordinates(data, vox[:, None], order=1)[0]
        # the pixel containing the voxel centre (pixel i covers [i, i+1) in widget coordinates)
        grey = image.pixelColor(int(np.floor(x * ratio)), int(np.floor(y * ratio))).red()
        expected = window_to_uint8(np.array([value]), win.state.window, win.state.level)[0]
        assert abs(int(grey) - int(expected)) <= 12   # pixel vs exact point: within one pixel's variation
    win.close()


def test_shortcuts_are_listed_in_help(window):
    from app.window import SHORTCUTS

    listed = " ".join(key for key, _ in SHORTCUTS)
    for action_id in ("open-image", "load-model", "save-session", "undo", "redo", "export-all",
                      "place-here"):
        action = window.registry[action_id]
        key = action.shortcut().toString()
        assert key and key in listed, action.text()
    assert window.registry["shortcuts"] in window.registry.menu("help").actions()


def test_dropping_a_model_file_loads_it(window, tmp_path):
    from PySide6.QtCore import QMimeData, QPointF, QUrl
    from PySide6.QtGui import QDragEnterEvent, QDropEvent
    from PySide6.QtWidgets import QApplication

    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import save_model

    shapes, faces = synthetic_shapes(5, subdivisions=2, seed=4)
    path = tmp_path / "dropped.npz"
    save_model(path, pca_model(shapes + window.state.crosshair, faces, n_factors=3))
    mime = QMimeData()
    mime.setUrls([QUrl.fromLocalFile(str(path))])
    enter = QDragEnterEvent(QPoint(50, 50), Qt.DropAction.CopyAction, mime, Qt.MouseButton.NoButton, NO_MOD)
    QApplication.sendEvent(window, enter)
    assert enter.isAccepted()
    event = QDropEvent(QPointF(50, 50), Qt.DropAction.CopyAction, mime, Qt.MouseButton.NoButton, NO_MOD)
    window.dropEvent(event)             # Qt routes a Drop only inside a real drag session
    assert window.state.active.model_path == path and window.state.active.model.n_factors == 3


def test_open_stroke_normals_point_out_of_the_model(window):
    """A stroke along one side only: the sign comes from the model surface, not the centroid."""
    from core.geometry.toolkit import vertex_normals

    state = window.state
    vertices, faces = state.active.surface_vertices(), state.active.model.faces
    normals = vertex_normals(vertices, faces)
    depth = state.crosshair[2]
    from core.geometry.slicing import polylines

    line = polylines(vertices, faces, np.array([0, 0, depth]), np.array([0, 0, 1.0]))[0]
    stroke = line.points[: max(4, len(line.points) // 4)]      # a quarter of the outline
    for p in stroke:
        state.active.add_point(p, "axial", depth, checkpoint=False)
    got = state.active.points.normals((vertices, normals))
    from scipy.spatial import cKDTree

    _, near = cKDTree(vertices).query(stroke)
    assert np.mean(np.einsum("ij,ij->i", got, normals[near]) > 0) > 0.8
    window.wait_for_refit()


def test_factor_sliders_show_each_factors_share_of_the_training_variance(window, tmp_path):
    """Issue 17, defect 4 (Segment tab): the sliders carry the model's explained shares; the
    truth is the SVD of the centred training shapes (eigenvalue ratios)."""
    from core.evaluation.simulated_user import synthetic_shapes
    from core.io import save_model
    from core.models import PCA

    shapes, faces = synthetic_shapes(8, subdivisions=2, seed=4)
    shapes = shapes + window.state.crosshair
    model = PCA(n_factors=3, connectivity=faces).fit(shapes).to_shape_model()
    path = tmp_path / "pca3.npz"
    save_model(path, model)
    window.load_model(path)
    panel = window.factors_panel
    centred = (shapes - shapes.mean(axis=0)).reshape(len(shapes), -1)
    sv = np.linalg.svd(centred, compute_uv=False)
    truth = sv ** 2 / np.sum(sv ** 2)
    shown = [float(label.text().rstrip("%")) / 100 for label in panel.share_labels]
    assert len(shown) == 3
    np.testing.assert_allclose(shown, truth[:3], atol=0.0006)   # display rounds to 0.1 %
    assert f"{100 * truth[:3].sum():.1f}%" in panel.summary.text()


class _PaintCounter:
    """Counts the paint events a widget receives."""

    def __init__(self, widget):
        from PySide6.QtCore import QObject

        class Filter(QObject):
            def eventFilter(inner, obj, event):  # noqa: N802, N805 - Qt API
                if event.type() == QEvent.Type.Paint:
                    self.count += 1
                return False

        self.count = 0
        self.filter = Filter()
        widget.installEventFilter(self.filter)


def test_a_click_with_a_quick_refit_is_painted_once_with_its_new_contours(window, qtbot,
                                                                          monkeypatch):
    """The window's repaints wait for the edit's refit (app.paint_gate: one repaint per click
    instead of several); a slow refit does not hold the point back for more than HOLD_S."""
    import time

    import core.reconstruction as reconstruction
    from app import paint_gate

    window.set_tool("draw")
    view = window.workspace.views["axial"]
    centre = window.state.active.surface_vertices().mean(axis=0)
    cross = window.state.crosshair.copy()
    cross[2] = centre[2]
    window.state.set_crosshair(cross)
    for i in range(4):                          # enough points for a similarity fit
        click(view, view.world_to_screen(centre + (6 * np.cos(i), 6 * np.sin(i), 0)))
        window.wait_for_refit()
    qtbot.wait(100)
    monkeypatch.setattr(paint_gate, "HOLD_S", 30.0)   # however slow the machine
    counter = _PaintCounter(view)
    fits = []
    window.refit_applied.connect(fits.append)
    click(view, view.world_to_screen(centre + (7.0, 0.0, 0.0)))
    qtbot.waitUntil(lambda: bool(fits) and counter.count >= 1, timeout=10000)
    qtbot.wait(100)
    assert counter.count == 1                   # point and new contours in one repaint
    # a slow fit: the point is painted after at most the wait, before the fit's result
    fit = reconstruction.fit_points

    def slow_fit(*args, **kwargs):
        time.sleep(1.5)
        return fit(*args, **kwargs)

    monkeypatch.setattr(reconstruction, "fit_points", slow_fit)
    monkeypatch.setattr(paint_gate, "HOLD_S", 0.05)
    counter.count, fits[:] = 0, []
    click(view, view.world_to_screen(centre + (0.0, 7.0, 0.0)))
    qtbot.waitUntil(lambda: counter.count >= 1, timeout=10000)
    assert not fits                             # painted while the fit was still running
    window.wait_for_refit()
