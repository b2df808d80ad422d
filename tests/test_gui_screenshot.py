"""Rendered window: not blank, the model's contour colour in every slice view, 3D view drawn."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QPoint, QRect  # noqa: E402
from PySide6.QtGui import QImage  # noqa: E402

from app import demo  # noqa: E402
from app.window import MainWindow, fits_screen, run_gui  # noqa: E402
from core.io import load_model  # noqa: E402
from core.io.model_library import structure_info  # noqa: E402


def _need_demo():
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")


def _rgb(image: QImage) -> np.ndarray:
    image = image.convertToFormat(QImage.Format.Format_RGB888)
    w, h, bpl = image.width(), image.height(), image.bytesPerLine()
    buf = np.frombuffer(image.constBits(), dtype=np.uint8, count=bpl * h).reshape(h, bpl)
    return buf[:, : 3 * w].reshape(h, w, 3).copy()


def _demo_color() -> np.ndarray:
    """The demo structure's colour: its model header's (issue 29: one colour rule)."""
    return np.round(255 * np.array(structure_info(load_model(demo.demo_model())).color))


def _contour_pixels(rgb: np.ndarray) -> int:
    target = _demo_color()
    return int(np.sum(np.all(np.abs(rgb.astype(int) - target) <= [12, 25, 30], axis=-1)))


def _tinted(rgb: np.ndarray, color: np.ndarray, amount: float = 20.0) -> np.ndarray:
    """Pixels whose colour leans towards ``color`` by more than ``amount`` (grey: 0)."""
    tint = rgb.astype(float) - rgb.astype(float).mean(axis=-1, keepdims=True)
    ref = color - color.mean()
    return tint @ (ref / np.linalg.norm(ref)) > amount


def _demo_window_with_3d(qtbot, tmp_path, monkeypatch, size=(1400, 900)) -> MainWindow:
    _need_demo()
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    window = MainWindow(recovery=False)
    qtbot.addWidget(window)
    window.resize(*size)
    window.load_demo()
    window.show()
    qtbot.waitExposed(window)
    return window


def test_window_screenshot_shows_contours_in_each_slice_view(qtbot, tmp_path, monkeypatch):
    window = _demo_window_with_3d(qtbot, tmp_path, monkeypatch)
    path = tmp_path / "window.png"
    window.save_screenshot(path)
    rgb = _rgb(QImage(str(path)))
    assert rgb.std() > 30                                # not blank
    ratio = rgb.shape[1] / window.width()
    regions = dict(window.workspace.views)
    regions["3d"] = window.workspace.volume_view
    crops = {}
    for name, widget in regions.items():
        top_left = widget.mapTo(window, QPoint(0, 0))
        x0, y0 = int(top_left.x() * ratio), int(top_left.y() * ratio)
        x1, y1 = x0 + int(widget.width() * ratio), y0 + int(widget.height() * ratio)
        crops[name] = rgb[y0:y1, x0:x1]
    for name in ("axial", "coronal", "sagittal"):
        crop = crops[name]
        assert crop.std() > 30, name
        assert _contour_pixels(crop) > 40, name
    # the 3D view rendered the slice planes (grey texture) and the structure-tinted surface
    crop3d = crops["3d"].astype(int)
    assert crop3d.std() > 15
    assert _tinted(crop3d, _demo_color()).sum() > 100
    # touching a factor slider colours the 3D surface by that factor's displacement
    view3d = window.workspace.volume_view
    model = window.state.active.model
    window.factors_panel.set_factor_sd(2, 1.0)
    view3d.flush()
    shown = view3d._surface_mesh["factor displacement (mm per SD)"]
    assert np.allclose(shown, np.sqrt(model.coef_var[2]) * np.linalg.norm(model.factors[2], axis=1))
    window._show_factor_region(-1)
    view3d.flush()
    assert "factor displacement (mm per SD)" not in view3d._surface_mesh.point_data
    window.close()


def test_screenshot_command_writes_a_png(tmp_path, monkeypatch, qapp):
    _need_demo()
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    path = tmp_path / "shot.png"
    assert run_gui(screenshot=str(path)) == 0
    rgb = _rgb(QImage(str(path)))
    assert rgb.shape[0] > 500 and rgb.shape[1] > 800
    assert rgb.std() > 30
    assert _contour_pixels(rgb) > 150
    assert rgb.shape[:2] == (1000, 1600)          # the same picture whatever the screen


class _Screen:
    def __init__(self, width: int, height: int) -> None:
        self.area = QRect(0, 0, width, height)

    def availableGeometry(self) -> QRect:  # noqa: N802 (QScreen's name)
        return self.area


@pytest.mark.parametrize("width, height, fits", [(1920, 1080, True), (1600, 1000, False),
                                                 (1280, 800, False), (1440, 900, False)])
def test_the_window_opens_maximised_on_a_screen_smaller_than_it(width, height, fits):
    # a 1280 x 800 laptop would otherwise show the window with its side panel off the screen
    assert fits_screen(_Screen(width, height)) is fits
    assert fits_screen(None) is True


def test_bad_image_on_the_command_line_exits_with_message(tmp_path, capsys, qapp, monkeypatch):
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    bad = tmp_path / "scan.nii.gz"
    bad.write_bytes(b"not a nifti file at all, just text")
    assert run_gui(image=str(bad), screenshot=str(tmp_path / "x.png")) == 2
    err = capsys.readouterr().err
    assert "scan.nii.gz" in err and "Traceback" not in err
    assert not (tmp_path / "x.png").exists()


def test_deferred_3d_view_is_created_after_the_slices(qtbot, tmp_path, monkeypatch):
    _need_demo()
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    window = MainWindow(recovery=False, defer_3d=True)
    qtbot.addWidget(window)
    window.load_demo()
    window.show()
    qtbot.waitExposed(window)
    assert window.workspace.volume_view is None
    assert window.workspace.views["axial"]._qimage is not None
    view3d = window.workspace.create_volume_view()
    assert window.workspace.create_volume_view() is view3d        # once
    window.runner._pending = (None, 0)                   # pretend a refit is queued
    assert view3d.defer() is True                        # 3D renders wait for refits
    window.runner._pending = None
    image = view3d.screenshot()
    assert image.std() > 15
    window.close()


def test_3d_view_follows_a_slice_step_without_waiting_for_the_scroll_to_end(qtbot, tmp_path,
                                                                          monkeypatch):
    """Issue 17: a slice step schedules the 3D render at once (RENDER_DELAY_MS, not the old
    60 ms debounce restarted by every step); an edit keeps the longer coalescing delay, and a
    pending slice render is not postponed by it. The new plane is what gets rendered."""
    from app.views import volume_view as vv_module

    window = _demo_window_with_3d(qtbot, tmp_path, monkeypatch, (1200, 800))
    window.render_now()
    vv = window.workspace.volume_view
    renders = []
    vv.plotter.ren_win.AddObserver("EndEvent", lambda *_: renders.append(1))
    vv._last_render = (-1e9, 0.0)                     # no recent render: no throttling
    window.state.step_slice("axial", 3)
    assert vv._timer.isActive() and vv._timer.interval() == vv_module.RENDER_DELAY_MS
    vv._mark("surface")                               # an edit meanwhile: not postponed
    assert vv._timer.interval() == vv_module.RENDER_DELAY_MS
    qtbot.waitUntil(lambda: len(renders) > 0, timeout=5000)
    z = window.state.crosshair[2]
    np.testing.assert_allclose(vv._plane_meshes["axial"].points[:, 2], z, atol=1e-6)
    qtbot.waitUntil(lambda: not vv._timer.isActive(), timeout=5000)
    vv._last_render = (-1e9, 0.0)
    vv._mark("surface")
    assert vv._timer.interval() == vv_module.COALESCE_MS
    window.close()


def test_3d_planes_show_the_second_images_composite(qtbot, tmp_path, monkeypatch):
    """With a second image, the 3D view's planes carry the same blend or checkerboard as the
    slice views (the first image alone, in its own window, without one)."""
    from core.geometry.planes import FRAMES, window_to_uint8
    from core.io import save_volume

    window = _demo_window_with_3d(qtbot, tmp_path, monkeypatch, (1200, 800))
    volume = window.state.volume
    path = tmp_path / "inverted.nii.gz"
    save_volume(path, (float(np.max(volume.data)) - np.asarray(volume.data)).astype(np.float32),
                volume.affine)
    assert window.load_second_image(path)
    qtbot.waitUntil(lambda: not window.features["second-image"].controller.is_running, timeout=30000)
    controller = window.features["second-image"].controller
    model, layer = controller.model, controller.layer
    model.set_mode("checkerboard")
    vv = window.workspace.volume_view
    vv.flush()
    sl = window.state.sampler.sample(FRAMES["axial"], FRAMES["axial"].depth(window.state.crosshair))
    texture = np.asarray(vv._plane_actors["axial"].texture.to_array())
    expected = layer.composite_slice(FRAMES["axial"], sl)[::-1]          # rows go bottom-up
    np.testing.assert_array_equal(texture.reshape(expected.shape), expected)
    model.clear()
    vv.flush()
    texture = np.asarray(vv._plane_actors["axial"].texture.to_array())
    plain = window_to_uint8(sl.data, window.state.window, window.state.level)[::-1]
    np.testing.assert_array_equal(texture.reshape(plain.shape), plain)
    window.close()


def test_a_3d_update_renders_once(qtbot, tmp_path, monkeypatch):
    """pyvistaqt's widget renders in its paint: the 3D view asks for that paint instead of
    also calling plotter.render() (which rendered every update twice)."""
    window = _demo_window_with_3d(qtbot, tmp_path, monkeypatch, (1200, 800))
    window.render_now()
    vv = window.workspace.volume_view
    renders = []
    vv.plotter.ren_win.AddObserver("EndEvent", lambda *_: renders.append(1))
    qtbot.wait(300)
    renders.clear()
    window.state.step_slice("axial", 2)
    qtbot.waitUntil(lambda: len(renders) > 0, timeout=5000)
    qtbot.wait(300)                                   # no second render follows
    assert len(renders) == 1
    z = window.state.crosshair[2]
    np.testing.assert_allclose(vv._plane_meshes["axial"].points[:, 2], z, atol=1e-6)
    window.close()
