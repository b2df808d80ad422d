"""Issue 17 tools in the segmentation workspace, driven like a user: the filled label overlay
and its volume, brush and eraser on the label map (undo, session, export), moving the model
by hand (translate, rotate, scale; undo)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from app import demo  # noqa: E402
from app.window import MainWindow  # noqa: E402
from core.geometry.segmentation import voxelize  # noqa: E402
from core.io import load_volume  # noqa: E402

NO_MOD = Qt.KeyboardModifier.NoModifier
LEFT = Qt.MouseButton.LeftButton


@pytest.fixture
def window(qtbot, tmp_path, monkeypatch):
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1300, 900)
    win.load_demo()
    win.show()
    qtbot.waitExposed(win)
    centre = win.state.active.surface_vertices().mean(axis=0)
    win.state.set_crosshair(centre)
    yield win
    win.runner.cancel()
    win.runner.wait()
    win.unsaved = False
    win.close()


def drag(view, points, modifier=NO_MOD):
    """Press at the first widget point, move through the others, release at the last."""
    pts = [QPoint(int(round(x)), int(round(y))) for x, y in points]
    QTest.mousePress(view, LEFT, modifier, pts[0])
    for p in pts[1:]:
        QTest.mouseMove(view, p)
    QTest.mouseRelease(view, LEFT, modifier, pts[-1])


def mesh_volume(vertices, faces):
    """Enclosed volume of a closed triangle mesh (divergence theorem), mm^3."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0)


def test_label_overlay_is_the_exported_map_and_its_volume_is_shown(window, qtbot):
    view = window.workspace.views["axial"]
    s = window.state.active
    labels = window.exports.label_map()
    # the overlay on this slice is the exported map's slice, voxel for voxel (axis-aligned demo)
    mask = window.features["editing"].overlay.slice_mask(s, view)
    assert mask.sum() > 20
    volume = window.state.volume
    ijk = np.rint(np.linalg.inv(volume.affine) @ np.append(window.state.crosshair, 1))[:3]
    assert mask.sum() == labels[:, :, int(ijk[2])].sum()
    # the volume read-out: voxel count x voxel volume, close to the surface's own volume
    voxel = abs(np.linalg.det(volume.affine[:3, :3]))
    shown = window.features["editing"].overlay.volume_mm3()
    assert shown == pytest.approx(labels.sum() * voxel)
    truth = mesh_volume(s.surface_vertices(), s.model.faces)
    assert abs(shown / truth - 1) < 0.05
    qtbot.waitUntil(lambda: f"{shown:,.0f} mm³" in window.features["editing"].volume_label.text(),
                    timeout=2000)
    # fill colours the pixels inside; opacity 0 leaves the image as it was
    window.features["editing"].panel.outline.setChecked(False)
    x, y = view.world_to_screen(_inside_point(window, view)) + 3   # off the crosshair's lines
    filled = view.grab().toImage().pixelColor(int(x), int(y))
    window.features["editing"].panel.opacity.setValue(0)
    plain = view.grab().toImage().pixelColor(int(x), int(y))
    assert _towards(filled, s.color) > _towards(plain, s.color) + 12  # the structure's tint
    window.features["editing"].panel.opacity.setValue(60)
    assert window.features["editing"].overlay.opacity == pytest.approx(0.6)
    # outline and fill switch independently
    view.grab()
    assert not view.show_outline
    window.features["editing"].panel.outline.setChecked(True)
    view.grab()
    assert view.show_outline
    window.features["editing"].panel.fill.setChecked(False)
    assert not window.features["editing"].overlay.fill
    window.features["editing"].overlay.set_fill(True)
    assert window.features["editing"].panel.fill.isChecked()  # the panel follows the model


def _inside_point(window, view):
    """A world point on the axial slice inside the label map (the first labelled voxel)."""
    from scipy.ndimage import distance_transform_edt

    mask = window.features["editing"].overlay.slice_mask(window.state.active, view)
    row, col = np.unravel_index(np.argmax(distance_transform_edt(mask)), mask.shape)
    u, v = view._slice.pixel_to_plane(col, row)  # the voxel deepest inside
    return view.frame.to_world(np.array([u, v, view.depth]))


def test_brush_and_eraser_edit_the_label_map_with_undo_session_and_export(window, qtbot,
                                                                          tmp_path):
    view = window.workspace.views["axial"]
    s = window.state.active
    before = int(window.exports.label_map().sum())
    window.set_tool("brush")
    window.features["editing"].panel.radius.setValue(3.0)
    # a stroke outside the structure, 6 mm long
    start = window.state.crosshair + [25.0, 0.0, 0.0]
    a, b = view.world_to_screen(start), view.world_to_screen(start + [6.0, 0, 0])
    drag(view, [a, (a + b) / 2, b])
    assert s.edits is not None and len(s.edits.added) > 0
    added = len(s.edits.added)
    # a 3 mm brush dragged 6 mm on 1 mm voxels: between the disc (29) and the swept area
    assert 29 <= added <= 29 + 7 * 6 + 10
    assert int(window.exports.label_map().sum()) == before + added
    qtbot.waitUntil(lambda: f"+{added}/−0 by hand" in window.features["editing"].volume_label.text(),
                    timeout=2000)
    # the eraser inside the structure removes voxels; Ctrl+brush erases too
    window.set_tool("eraser")
    inside = view.world_to_screen(_inside_point(window, view))
    drag(view, [inside])
    removed = len(s.edits.removed)
    assert removed > 0
    assert int(window.exports.label_map().sum()) == before + added - removed
    # one undo step per stroke
    window.undo()
    assert len(s.edits.removed) == 0 and len(s.edits.added) == added
    window.redo()
    assert len(s.edits.removed) == removed
    # kept with the session
    path = tmp_path / "session.json"
    assert window.save_session(path=path)
    window.state.active.set_edits(None, checkpoint=False)
    window.open_session(path)
    s = window.state.active
    assert len(s.edits.added) == added and len(s.edits.removed) == removed
    # exported with the marks of the manual edits
    written = window.export_all(tmp_path / "out")
    names = sorted(p.name for p in written)
    assert "segmentation_manual_edits.nii.gz" in names
    marks = np.asarray(load_volume(tmp_path / "out" / "segmentation_manual_edits.nii.gz").data)
    assert int((marks == 1).sum()) == added and int((marks == 2).sum()) == removed
    exported = np.asarray(load_volume(tmp_path / "out" / "segmentation.nii.gz").data)
    model_only = voxelize(s.surface_vertices(), s.model.faces, window.state.volume)
    assert np.all(exported[marks == 1] == 1) and np.all(exported[marks == 2] == 0)
    assert np.array_equal(exported[marks == 0], model_only[marks == 0])
    # a locked structure is not edited
    s.set_properties(locked=True)
    window.set_tool("brush")
    drag(view, [a])
    assert len(s.edits.added) == added


def test_move_model_by_hand_translate_rotate_scale_and_undo(window):
    view = window.workspace.views["axial"]
    s = window.state.active
    window.set_tool("move")
    pose0 = s.pose.copy()
    c0 = s.surface_vertices().mean(axis=0)
    # translate: the centre follows the drag (8 mm right, 5 mm anterior on the axial slice)
    p = view.world_to_screen(c0)
    q = view.world_to_screen(c0 + [8.0, 5.0, 0.0])
    drag(view, [p, (p + q) / 2, q])
    c1 = s.surface_vertices().mean(axis=0)
    np.testing.assert_allclose(c1 - c0, [8.0, 5.0, 0.0], atol=0.6)  # one pixel ~ 0.5 mm
    np.testing.assert_allclose(s.placement, s.pose)  # the pose prior follows the hand
    # rotate (Ctrl): a quarter turn about the axial normal through the centre
    before = s.surface_vertices().copy()
    a = view.world_to_screen(c1 + [20.0, 0, 0])
    b = view.world_to_screen(c1 + [0, 20.0, 0])
    drag(view, [a, b], Qt.KeyboardModifier.ControlModifier)
    after = s.surface_vertices()
    d0, d1 = before - before.mean(axis=0), after - after.mean(axis=0)
    cross = d0[:, 0] * d1[:, 1] - d0[:, 1] * d1[:, 0]
    angle = np.degrees(np.arctan2(cross, np.sum(d0[:, :2] * d1[:, :2], axis=1)))
    assert np.median(np.abs(np.abs(angle) - 90)) < 3
    np.testing.assert_allclose(d1[:, 2], d0[:, 2], atol=1e-6)  # about the slice normal
    # scale (Shift): dragging from 10 to 15 mm from the centre scales by 1.5
    size = np.ptp(after, axis=0)
    a = view.world_to_screen(c1 + [10.0, 0, 0])
    b = view.world_to_screen(c1 + [15.0, 0, 0])
    drag(view, [a, b], Qt.KeyboardModifier.ShiftModifier)
    np.testing.assert_allclose(np.ptp(s.surface_vertices(), axis=0) / size, 1.5, rtol=0.08)
    # one undo step per drag
    for _ in range(3):
        window.undo()
    np.testing.assert_allclose(s.pose, pose0)


# ------------------------------------------------------------------------------------------
# Navigation and display
# ------------------------------------------------------------------------------------------


def test_ctrl_wheel_zooms_towards_the_cursor(window):
    from PySide6.QtCore import QPointF
    from PySide6.QtGui import QWheelEvent

    view = window.workspace.views["axial"]
    x, y = view.width() * 0.8, view.height() * 0.3   # off centre
    before = view.screen_to_world(x, y)
    event = QWheelEvent(QPointF(x, y), view.mapToGlobal(QPointF(x, y)), QPoint(0, 0),
                        QPoint(0, 120), Qt.MouseButton.NoButton,
                        Qt.KeyboardModifier.ControlModifier, Qt.ScrollPhase.NoScrollPhase, False)
    view.wheelEvent(event)
    assert view.zoom == pytest.approx(1.15)
    np.testing.assert_allclose(view.screen_to_world(x, y), before, atol=1e-9)


def test_zoom_to_structure_layouts_colour_maps_and_typed_window(window, tmp_path):
    from app.panels import navigation as nav

    s = window.state.active
    vertices = s.surface_vertices()
    window.registry["zoom-structure"].trigger()
    for view in window.workspace.views.values():
        xy = view.world_to_screen(vertices)
        span = xy.max(axis=0) - xy.min(axis=0)
        # the structure fills ~60% of the view along its tighter side, centred
        fill = max(span[0] / view.width(), span[1] / view.height())
        assert 0.55 < fill < 0.65
        centre = (xy.max(axis=0) + xy.min(axis=0)) / 2
        np.testing.assert_allclose(centre, [view.width() / 2, view.height() / 2], atol=2)
    np.testing.assert_allclose(window.state.crosshair, vertices.mean(axis=0), atol=1.0)
    # one view maximised (F) and back
    window.active_view = "coronal"
    window.registry["maximise"].trigger()
    views = window.workspace.views
    assert views["coronal"].isVisible() and not views["axial"].isVisible()
    window.registry["maximise"].trigger()
    assert all(v.isVisible() for v in views.values())
    window.features["navigation"].set_layout("sagittal")
    assert views["sagittal"].isVisible() and not views["coronal"].isVisible()
    window.features["navigation"].set_layout("2 x 2")
    # colour maps: the pixels follow the lookup table of the windowed grey value
    view = views["axial"]
    window.features["navigation"].set_colormap("hot")
    lut = nav.colormap_lut("hot")
    assert lut.shape == (256, 3) and lut[0].tolist() != lut[-1].tolist()
    from core.geometry.planes import window_to_uint8

    grey = window_to_uint8(view._slice.data, window.state.window, window.state.level)
    r, c = grey.shape[0] // 2, grey.shape[1] // 2
    assert view._qimage.pixelColor(c, r).getRgb()[:3] == tuple(lut[grey[r, c]])
    window.features["navigation"].set_colormap("inverted grey")
    assert view._qimage.pixelColor(c, r).red() == 255 - grey[r, c]
    with pytest.raises(ValueError, match="colour map must be one of"):
        nav.colormap_lut("rainbow")
    # typed window and level (the dialog's values; no dialog under tests)
    dialog = nav.WindowLevelDialog(window)
    dialog.width_box.setValue(80.0)
    dialog.level_box.setValue(120.0)
    window.state.set_window(*dialog.values())
    assert (window.state.window, window.state.level) == (80.0, 120.0)


def test_recent_files_and_screenshot(window, tmp_path):
    from app.panels import navigation as nav

    recent = nav.recent_files()
    assert recent[:2] == [str(demo.demo_model().resolve()), str(demo.demo_image().resolve())]
    nav.remember(demo.demo_image())
    assert nav.recent_files()[0] == str(demo.demo_image().resolve())
    assert len(set(nav.recent_files())) == len(nav.recent_files())  # no duplicates
    recent_menu = window.registry.menu("file.recent")
    window.features["navigation"].fill_recent()
    assert [a.text() for a in recent_menu.actions()][0] == demo.demo_image().name
    path = tmp_path / "shot.png"
    window.save_screenshot(path)
    from PySide6.QtGui import QImage

    image = QImage(str(path))
    assert image.width() == window.width() and image.height() == window.height()


def test_3d_view_has_a_labelled_orientation_cube_and_plane_and_point_toggles(qtbot, tmp_path,
                                                                            monkeypatch):
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo data missing")
    from app.views.orientation import FACES

    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    win = MainWindow(with_3d=True, recovery=False)
    qtbot.addWidget(win)
    win.resize(1000, 700)
    win.load_demo()
    win.show()
    qtbot.waitExposed(win)
    try:
        view = win.workspace.volume_view
        cube = view.orientation_widget.GetOrientationMarker()
        assert [cube.GetXPlusFaceText(), cube.GetXMinusFaceText(), cube.GetYPlusFaceText(),
                cube.GetYMinusFaceText(), cube.GetZPlusFaceText(), cube.GetZMinusFaceText()] \
            == list(FACES.values()) == ["R", "L", "A", "P", "S", "I"]
        win.state.active.add_point(win.state.crosshair, "axial", win.workspace.views["axial"].depth)
        view.flush()
        assert view._plane_actors and view._points_actor is not None
        win.registry["show-planes"].trigger()            # off
        assert not any(a.GetVisibility() for a in view._plane_actors.values())
        win.registry["show-points"].trigger()
        assert not view._points_actor.GetVisibility()
        win.state.active.add_point(win.state.crosshair + [1, 0, 0], "axial",
                            win.workspace.views["axial"].depth)
        view.flush()                             # redraws keep the choice
        assert not view._points_actor.GetVisibility()
        win.registry["show-planes"].trigger()            # on again
        assert all(a.GetVisibility() for a in view._plane_actors.values())
    finally:
        win.runner.cancel()
        win.runner.wait()
        win.unsaved = False
        win.close()


# ------------------------------------------------------------------------------------------
# Ruler and angle
# ------------------------------------------------------------------------------------------


def test_ruler_and_angle_in_a_slice_kept_with_the_session_and_exported(window, tmp_path):
    view = window.workspace.views["axial"]
    c = window.state.crosshair.copy()
    window.set_tool("ruler")
    a, b = view.world_to_screen(c), view.world_to_screen(c + [12.0, 16.0, 0.0])
    drag(view, [a, (a + b) / 2, b])
    store = window.features["measurements"].store
    assert len(store.items) == 1
    ruler = store.items[0]
    px = 1.0 / view._base()[0]                      # mm per pixel
    assert ruler.value == pytest.approx(20.0, abs=2 * px)
    assert ruler.frame == "axial" and ruler.depth == pytest.approx(view.depth)
    window.set_tool("angle")
    for p in (c + [10.0, 0, 0], c, c + [0, 10.0, 0]):   # a right angle at c
        drag(view, [view.world_to_screen(p)])
    assert len(store.items) == 2 and store.items[1].kind == "angle"
    assert store.items[1].value == pytest.approx(90.0, abs=np.degrees(2 * px / 10.0) + 0.5)
    # drawn on their slice only: the measurement colour is there, not one slice further
    assert _green_pixels(view) > 50
    window.state.step_slice("axial", 1)
    assert _green_pixels(view) == 0
    window.state.step_slice("axial", -1)
    # session and export
    path = tmp_path / "session.json"
    assert window.save_session(path=path)
    window.features["measurements"].store.clear()
    window.open_session(path)
    assert [m.kind for m in window.features["measurements"].store.items] == ["ruler", "angle"]
    written = {p.name for p in window.export_all(tmp_path / "out")}
    assert {"measurements.csv", "measurements.mrk.json"} <= written
    rows = (tmp_path / "out" / "measurements.csv").read_text().splitlines()
    assert float(rows[1].split(",")[1]) == pytest.approx(ruler.value, abs=1e-3)


def _green_pixels(view) -> int:
    """Pixels of the measurement colour (120, 255, 140) in the view's image."""
    image = view.grab().toImage().convertToFormat(view.grab().toImage().Format.Format_RGB888)
    ptr = image.constBits()
    rgb = np.frombuffer(ptr, dtype=np.uint8, count=image.sizeInBytes()).reshape(
        image.height(), image.bytesPerLine())[:, :3 * image.width()].reshape(
        image.height(), image.width(), 3).astype(int)
    return int(np.sum((np.abs(rgb - [120, 255, 140]) <= 12).all(axis=2)))


def test_every_shortcut_is_unique_and_listed_in_help_and_readme(window):
    from pathlib import Path

    from PySide6.QtGui import QAction

    from app.actions import SHORTCUTS

    keys = [a.shortcut().toString() for a in window.findChildren(QAction)
            if not a.shortcut().isEmpty()]
    duplicates = {k for k in keys if keys.count(k) > 1}
    assert not duplicates, duplicates
    listed = " ".join(k for k, _ in SHORTCUTS)
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    for key in ("B / X", "G", "Z", "F", "Ctrl+L", "F12", "M / A", "Ctrl+wheel"):
        assert key in listed
        assert f"| {key} |" in readme, key


def _towards(pixel, color) -> float:
    """How far ``pixel`` leans from grey towards the hue of ``color`` (RGB units; grey: 0):
    a fill in the structure's colour raises it."""
    rgb = np.array([pixel.red(), pixel.green(), pixel.blue()], dtype=float)
    hue = np.asarray(color, dtype=float) - np.mean(color)
    return float((rgb - rgb.mean()) @ hue / np.linalg.norm(hue))


def test_label_fill_follows_the_surface_on_every_repaint(window, qtbot):
    """The slice images of the fill are cached per view: moving the surface (a refit) must
    repaint the new fill, not the cached old one."""
    view = window.workspace.views["axial"]
    s = window.state.active
    window.features["editing"].panel.outline.setChecked(False)
    inside = _inside_point(window, view)
    x, y = view.world_to_screen(inside) + 3           # off the crosshair's lines
    tinted = view.grab().toImage().pixelColor(int(x), int(y))
    pose = s.pose.copy()
    pose[:3, 3] += (40.0, 0.0, 0.0)           # the whole structure 40 mm to the side
    s.set_surface(s.coef, pose, s.surface_vertices() + (40.0, 0.0, 0.0))
    moved = view.grab().toImage().pixelColor(int(x), int(y))
    assert _towards(tinted, s.color) > _towards(moved, s.color) + 12   # no fill left here
    x2, y2 = view.world_to_screen(inside + (40.0, 0.0, 0.0))
    again = view.grab().toImage().pixelColor(int(x2), int(y2))
    assert _towards(again, s.color) > _towards(moved, s.color) + 12    # it moved along
