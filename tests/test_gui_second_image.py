"""A second image over the first (issue 17): loading in a worker, blend and checkerboard in the
slice views, drawing on either image, and the session keeping it.

The second image is the demo T1 with its contrast inverted (a T2-like scan). On the same grid
it needs no registration; moved to another grid it is registered rigidly in the worker (the
core test, tests/test_coregistration.py, checks the recovered motion against the truth).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from core.geometry.planes import window_to_uint8  # noqa: E402
from core.io import save_volume  # noqa: E402
from core.registration.coregistration import checkerboard_mask  # noqa: E402


def inverted(data: np.ndarray) -> np.ndarray:
    top = float(np.max(data))
    return np.where(data > 0.05 * top, top - data, 0.0).astype(np.float32)


def _load(window, qtbot, path, transform=None):
    assert window.load_second_image(path, transform)
    qtbot.waitUntil(lambda: not window.features["second-image"].controller.is_running, timeout=30000)
    assert window.features["second-image"].controller.model.loaded


def _pixels(view) -> np.ndarray:
    image = view.grab().toImage()
    ptr = image.constBits()
    return np.array(ptr, dtype=np.uint8).reshape(image.height(), image.bytesPerLine())


@pytest.fixture
def second_path(window, tmp_path):
    volume = window.state.volume
    path = tmp_path / "t2like.nii.gz"
    save_volume(path, inverted(np.asarray(volume.data)), volume.affine)
    return path


def test_second_image_blends_checkers_and_drawing_works_on_either(window, qtbot, second_path):
    state, view = window.state, window.workspace.views["axial"]
    plain = _pixels(view)
    _load(window, qtbot, second_path)
    controller = window.features["second-image"].controller
    model, layer = controller.model, controller.layer
    assert not model.coregistered.registered            # same grid: nothing to register
    np.testing.assert_array_equal(model.transform, np.eye(4))
    assert "t2like" in window.features["second-image"].panel.info.text()
    voxel = np.rint(state.volume.world_to_voxel(state.crosshair)).astype(int)
    window.cursor_label.refresh()                      # both intensities in the status bar
    assert f"second {inverted(np.asarray(state.volume.data))[tuple(voxel)]:.4g}" in \
        window.cursor_label.text()
    # blend: (1 - a) first + a second, each in its own window
    first = window_to_uint8(view._slice.data, state.window, state.level)
    second_slice = model.sampler.sample(view.frame, view._slice.depth).data
    second = window_to_uint8(second_slice, *model.window_of("second"))
    model.set_opacity(1.0)
    np.testing.assert_array_equal(layer.composite(view), second)
    model.set_opacity(0.5)
    expected = np.rint(0.5 * first.astype(float) + 0.5 * second.astype(float))
    assert np.abs(layer.composite(view).astype(float) - expected).max() <= 1
    qtbot.wait(50)
    blended = _pixels(view)
    # checkerboard: the first image on the mask's squares, the second on the others
    window.registry["second-checkerboard"].trigger()
    assert model.mode == "checkerboard"
    mask = checkerboard_mask(view._slice, model.checker_mm)
    np.testing.assert_array_equal(layer.composite(view), np.where(mask, first, second))
    qtbot.wait(50)
    checkered = _pixels(view)
    assert np.mean(plain != blended) > 0.05 and np.mean(blended != checkered) > 0.05
    # draw on the first image, then on the second: same pixel, same world point
    window.set_tool("draw")
    centre = state.volume.voxel_to_world(
        np.rint(state.volume.world_to_voxel(state.crosshair)).astype(int) + [25, 20, 0])
    x, y = view.world_to_screen(centre)
    QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(int(round(x)), int(round(y))))
    on_first = state.active.points.xyz[-1].copy()
    first_window = (state.window, state.level)
    window.registry["second-swap-base"].trigger()
    assert model.base == "second"
    assert (state.window, state.level) == model.window_of("second") != first_window
    assert model.window_of("first") == first_window       # kept for when it is the base again
    np.testing.assert_array_equal(layer.composite(view), np.where(mask, second, first))
    QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(int(round(x)), int(round(y))))
    assert len(state.active.points) == 2
    np.testing.assert_allclose(state.active.points.xyz[-1], on_first, atol=1e-9)


def test_second_image_is_kept_with_the_session(window, qtbot, second_path, tmp_path):
    _load(window, qtbot, second_path)
    model = window.features["second-image"].controller.model
    model.set_mode("checkerboard")
    model.set_checker_mm(6.0)
    model.set_base("second")
    session = tmp_path / "s.json"
    assert window.save_session(path=session)
    import json

    doc = json.loads(session.read_text())["info"]["second_image"]
    assert doc["path"].endswith("t2like.nii.gz") and len(doc["transform"]) == 4
    model.clear()
    assert not model.loaded
    window.open_session(session)
    qtbot.waitUntil(lambda: model.loaded and not window.features["second-image"].controller.is_running,
                    timeout=30000)
    assert (model.mode, model.checker_mm, model.base) == ("checkerboard", 6.0, "second")
    np.testing.assert_allclose(model.transform, np.eye(4))
    assert not window.unsaved                # restored from the file: nothing to save


def test_second_image_on_another_grid_is_registered_in_a_worker_and_can_be_cancelled(
        window, qtbot, tmp_path):
    """A first image at 3 mm and the inverted copy moved by 6 mm and 5 degrees: loading runs the
    rigid registration in a worker; the recovered transform undoes the motion; a cancelled
    load changes nothing."""
    from core.datasets.images import moved_copy

    t1 = window.state.volume
    data = np.ascontiguousarray(np.asarray(t1.data, np.float32)[::3, ::3, ::3])
    affine = np.asarray(t1.affine, float) @ np.diag([3.0, 3.0, 3.0, 1.0])
    first_path, second_path = tmp_path / "t1_3mm.nii.gz", tmp_path / "t2_moved.nii.gz"
    save_volume(first_path, data, affine)
    angle = np.radians(5.0)
    truth = np.eye(4)
    truth[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                     [0, 0, 1]]
    truth[:3, 3] = [6.0, -4.0, 3.0]
    moved = moved_copy(inverted(data), affine, truth, np.random.default_rng(0), noise=0.01,
                       bias=0.1, scanner_offset_mm=(30.0, 0.0, 0.0))
    save_volume(second_path, moved.data, moved.affine)
    window.load_image(first_path)
    model = window.features["second-image"].controller.model
    assert window.load_second_image(second_path)
    assert window.features["second-image"].controller.is_running            # the GUI thread is free meanwhile
    window.features["second-image"].controller.cancel()
    qtbot.waitUntil(lambda: not window.features["second-image"].controller.is_running, timeout=30000)
    assert not model.loaded
    _load(window, qtbot, second_path)
    assert model.coregistered.registered
    brain = affine[:3, :3] @ np.array([[33, 39, 31], [20, 50, 35], [45, 30, 25]]).T \
        + affine[:3, 3:4]
    back = (model.transform @ moved.truth)[:3]
    err = np.linalg.norm(back[:, :3] @ brain + back[:, 3:4] - brain, axis=0)
    assert err.max() < 1.5, err


def test_second_image_shortcuts_are_in_help_and_the_readme(window):
    from pathlib import Path

    from app.actions import SHORTCUTS

    keys = {window.registry[name].shortcut().toString()
            for name in ("open-second", "second-checkerboard", "second-swap-base")}
    assert keys == {"Ctrl+Shift+I", "K", "Ctrl+B"}
    listed = {k for k, _ in SHORTCUTS}
    assert keys <= listed
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    assert "| Ctrl+Shift+I |" in readme and "| K / Ctrl+B |" in readme
    assert "docs/second-image.png" in readme


def test_unreadable_second_image_is_a_one_line_error_naming_the_file(window, qtbot, tmp_path):
    bad = tmp_path / "broken_t2.nii.gz"
    bad.write_bytes(b"this is not an image")
    errors = []
    window.features["second-image"].controller.error.connect(errors.append)
    assert window.load_second_image(bad)
    qtbot.waitUntil(lambda: not window.features["second-image"].controller.is_running, timeout=30000)
    assert not window.features["second-image"].controller.model.loaded
    assert len(errors) == 1 and "broken_t2.nii.gz" in errors[0] and "\n" not in errors[0]
    assert "Traceback" not in errors[0]


def test_session_drawn_on_the_second_image_reopens_with_the_first_images_window(
        window, qtbot, second_path, tmp_path):
    """The saved window/level is the base's; with the second image missing on reopening, the
    first image still gets its own window back (and the missing file is said)."""
    state = window.state
    _load(window, qtbot, second_path)
    first_window = (state.window, state.level)
    window.features["second-image"].controller.model.set_base("second")
    assert (state.window, state.level) != first_window
    session = tmp_path / "s.json"
    assert window.save_session(path=session)
    second_path.unlink()
    errors = []
    window.features["second-image"].controller.error.connect(errors.append)
    window.open_session(session)
    assert not window.features["second-image"].controller.model.loaded
    assert errors and "t2like.nii.gz" in errors[0] and "not found" in errors[0]
    np.testing.assert_allclose((state.window, state.level), first_window)


def test_a_second_load_while_one_runs_is_refused_and_the_first_one_completes(window, qtbot,
                                                                          second_path):
    errors = []
    window.features["second-image"].controller.error.connect(errors.append)
    assert window.load_second_image(second_path)
    assert not window.load_second_image(second_path.with_name("other.nii.gz"))
    assert errors and "still loading" in errors[0]
    qtbot.waitUntil(lambda: not window.features["second-image"].controller.is_running, timeout=30000)
    assert window.features["second-image"].controller.model.path.name == "t2like.nii.gz"
