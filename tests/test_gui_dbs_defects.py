"""Issue 29's GUI defects (section 5), each driven as the workflow audit met it; each test
failed at eb2bdcf."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QMimeData, QPointF, Qt, QUrl  # noqa: E402
from PySide6.QtGui import QDropEvent  # noqa: E402
from PySide6.QtWidgets import QFileDialog, QInputDialog, QMessageBox  # noqa: E402
from recovery_runs import crashing_run  # noqa: E402

from app import demo, demo_tour  # noqa: E402
from core.io import load_model, save_points  # noqa: E402
from core.io.model_library import RESOURCES_MODELS, structure_info  # noqa: E402

LEFT_THALAMUS = RESOURCES_MODELS / "left_thalamus.npz"
RIGHT_CAUDATE = RESOURCES_MODELS / "right_caudate.npz"
if not (LEFT_THALAMUS.is_file() and RIGHT_CAUDATE.is_file()):
    pytest.skip("library models missing from resources/models", allow_module_level=True)


def _ring(window, n=8, radius=5.0):
    """``n`` contour points around the crosshair on its axial slice (one undo step)."""
    c = window.state.crosshair.copy()
    for k in range(n):
        t = 2 * np.pi * k / n
        window.state.active.add_point(c + [radius * np.cos(t), 1.5 * radius * np.sin(t), 0.0],
                               "axial", float(c[2]), checkpoint=k == 0)


def _drop(window, path):
    mime = QMimeData()
    mime.setUrls([QUrl.fromLocalFile(str(path))])
    event = QDropEvent(QPointF(10, 10), Qt.DropAction.CopyAction, mime,
                       Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier)
    window.dropEvent(event)


# -- 1. a dropped model adds a structure; every model change is one undo step -------------

def test_dropped_model_adds_a_structure_and_undo_removes_it(make_window):
    window = make_window()
    caudate = window.state.active
    _ring(window)
    window.wait_for_refit(20000)
    coef, model = caudate.coef.copy(), caudate.model
    _drop(window, LEFT_THALAMUS)
    assert len(window.state.structures) == 2
    added = window.state.active
    assert added is not caudate and added.model_path.name == "left_thalamus.npz"
    assert added.label == "thalamus (left)" and len(added.points) == 0
    # the fitted caudate is untouched: same model, name, points and fit
    assert caudate.model is model and caudate.label == "caudate nucleus (left)"
    assert len(caudate.points) == 8 and np.array_equal(caudate.coef, coef)
    window.undo()                                  # one step: the drop is gone
    assert window.state.structures == [caudate] and window.state.active is caudate
    assert caudate.model is model and len(caudate.points) == 8


def test_loading_another_model_is_one_undo_step_with_its_own_name(make_window):
    window = make_window()
    caudate = window.state.active
    _ring(window)
    window.wait_for_refit(20000)
    model, color, coef = caudate.model, caudate.color, caudate.coef.copy()
    window.load_model(RIGHT_CAUDATE)               # File > Load model: replaces, says so
    assert caudate.model_path.name == "right_caudate.npz"
    assert caudate.label == "caudate nucleus (right)"      # not the old structure's name
    window.wait_for_refit(20000)
    window.undo()
    assert caudate.model is model and caudate.label == "caudate nucleus (left)"
    assert caudate.model_path.name == "model.npz" and caudate.color == color
    assert np.allclose(caudate.coef, coef) and len(caudate.points) == 8
    window.redo()
    assert caudate.model_path.name == "right_caudate.npz"


# -- 2. imported points go to the structure the file names, or the user picks it -----------

def test_markups_name_chooses_the_structure_the_points_go_to(make_window, tmp_path):
    window = make_window()
    caudate = window.state.active
    window.add_structure(LEFT_THALAMUS)
    thalamus = window.state.active                # the active structure is the thalamus
    c = caudate.surface_vertices().mean(axis=0)
    xyz = c + np.array([[3.0, 0, 0], [0, 3.0, 0], [-3.0, 0, 0], [0, -3.0, 0]])
    path = tmp_path / "contour.mrk.json"
    save_points(path, xyz)
    doc = json.loads(path.read_text())
    doc["markups"][0]["name"] = "caudate nucleus (left)"     # Slicer's node name
    path.write_text(json.dumps(doc))
    window.open_path(path)
    assert len(caudate.points) == 4 and len(thalamus.points) == 0
    assert np.allclose(caudate.points.xyz, xyz, atol=1e-6)
    assert window.state.active is caudate
    # a CSV file named after a structure goes there too
    csv = tmp_path / "left_thalamus_contour.csv"
    save_points(csv, xyz + [0, 0, 2.0])
    window.open_path(csv)
    assert len(thalamus.points) == 4 and len(caudate.points) == 4


def test_unnamed_points_ask_which_structure(make_window, tmp_path, monkeypatch):
    window = make_window()
    caudate = window.state.active
    window.add_structure(LEFT_THALAMUS)
    window.state.set_active(caudate)
    monkeypatch.delenv("SSM_STUDIO_NO_DIALOGS")
    monkeypatch.setattr(QMessageBox, "question",            # closing at teardown
                        staticmethod(lambda *a, **k: QMessageBox.StandardButton.Discard))
    asked = []

    def pick(parent, title, label, items, current, editable):
        asked.append((list(items), current))
        return "thalamus (left)", True

    monkeypatch.setattr(QInputDialog, "getItem", staticmethod(pick))
    path = tmp_path / "points.csv"
    save_points(path, caudate.surface_vertices()[:5])
    window.open_path(path)
    assert asked == [(["caudate nucleus (left)", "thalamus (left)"], 0)]
    thalamus = window.state.structures[1]
    assert len(thalamus.points) == 5 and len(caudate.points) == 0
    # Cancel imports nothing
    monkeypatch.setattr(QInputDialog, "getItem", staticmethod(lambda *a: ("", False)))
    window.open_path(path)
    assert len(thalamus.points) == 5 and len(caudate.points) == 0


# -- 3. a recording quits by itself ---------------------------------------------------------

def test_recorded_tour_closes_without_asking_to_save(make_window, qtbot, tmp_path, monkeypatch):
    if demo_tour.truth_surface() is None:
        pytest.skip("demo data missing")
    window = make_window()
    monkeypatch.delenv("SSM_STUDIO_NO_DIALOGS")   # as on a display: the box would be modal
    asked = []
    monkeypatch.setattr(QMessageBox, "question", staticmethod(
        lambda *a, **k: asked.append(a) or QMessageBox.StandardButton.Cancel))
    with qtbot.waitSignal(window.closed, timeout=60000):
        tour = demo_tour.start_tour(window, record=tmp_path / "rec", interval_ms=1,
                                    quit_at_end=True, spacing=8.0)
        tour.steps = tour.steps[:5]              # message, zoom, a slice and two points
    assert window.unsaved and not asked          # edited, closed all the same
    assert not window.isVisible() and len(tour.frames) >= 3


# -- 4. crash recovery restores the session's file name --------------------------------------

def test_recovered_session_saves_to_its_own_file(make_window, tmp_path, monkeypatch):
    from core.session import document as sessions

    window = make_window(recovery=True)
    saved = tmp_path / "patient.json"
    assert window.save_session(path=saved)
    _ring(window, n=5)
    window.wait_for_refit(20000)
    window._autosave_timer.stop()
    window.write_recovery()
    crashing_run("r.write(s.load_session(sys.argv[1]))", str(window.sessions.recovery.path))
    window.close()

    fresh = make_window(load_demo=False, recovery=True)
    # without dialogs (no one to answer) the offer waits, no modal box, the files unclaimed
    boxes = []
    monkeypatch.setattr(QMessageBox, "question", staticmethod(
        lambda *a, **k: boxes.append(a) or QMessageBox.StandardButton.No))
    assert not fresh.offer_recovery() and not boxes
    assert fresh.offer_recovery(ask=lambda text: True)
    assert fresh.session_path == saved.resolve() and fresh.unsaved
    dialogs = []
    monkeypatch.setattr(QFileDialog, "getSaveFileName",
                        staticmethod(lambda *a, **k: dialogs.append(a) or ("", "")))
    assert fresh.save_session()                  # Ctrl+S: no file dialog, the same file
    assert not dialogs and not fresh.unsaved
    assert len(sessions.load_session(saved).points) == 5


# -- 5. one colour rule, however the model was loaded ----------------------------------------

def test_structure_colour_is_the_models_however_it_was_loaded(make_window):
    header = tuple(int(round(255 * c)) for c in structure_info(load_model(LEFT_THALAMUS)).color)
    window = make_window(load_demo=False)
    window.load_image(demo.demo_image())
    window.load_model(LEFT_THALAMUS)                         # File > Load model
    loaded = window.state.active
    assert loaded.color == header
    window.add_structure(LEFT_THALAMUS)                      # the library's Add
    added = window.state.active
    assert added.color != loaded.color                       # distinct from the other one
    window.remove_structure(loaded)
    other = make_window(load_demo=False)
    other.load_image(demo.demo_image())
    other.add_structure(LEFT_THALAMUS)
    assert other.state.structures[-1].color == header        # the same rule both ways
    # a colour the user chose is kept when the model changes
    added.set_properties(color=(10, 20, 30))
    window.load_model(RIGHT_CAUDATE)
    assert added.color == (10, 20, 30)


# -- 6. what a user needs while drawing is always in view, and nothing is cut ----------------

def _fully_visible(widget) -> bool:
    region = widget.visibleRegion().boundingRect()
    return widget.isVisible() and region.width() == widget.width() \
        and region.height() == widget.height()


@pytest.mark.parametrize("size", [(1280, 800), (1600, 1000)])
def test_side_panel_shows_names_coordinates_undo_count_and_fit(make_window, qtbot, size):
    window = make_window(size=size)
    window.add_structure(LEFT_THALAMUS)
    window.state.set_active(0)
    _ring(window)
    window.wait_for_refit(20000)
    qtbot.wait(50)
    # the Structures table: whole names
    table = window.structures_panel.table
    for row in range(table.rowCount()):
        item = table.item(row, 2)
        rect = table.visualItemRect(item)
        assert rect.width() >= table.fontMetrics().horizontalAdvance(item.text()) + 6, item.text()
        assert table.viewport().rect().contains(rect)
    # the drawing essentials, without scrolling: point count, undo/redo, the fit read-out
    bar = window.drawing_bar
    for widget in (window.tools_panel.count, bar.undo_button, bar.redo_button,
                   window.fit_panel.result):
        assert _fully_visible(widget), widget
    count = window.tools_panel.count
    assert count.text() == "8 contour point(s) on 1 slice(s)"
    assert count.width() >= count.fontMetrics().horizontalAdvance(count.text())
    assert "Residual" in window.fit_panel.result.text()
    assert bar.undo_button.isEnabled()
    # the Planning panel: whole AC/PC/midline coordinates
    for name, xyz in (("ac", [24.5, -18.25, -10.75]), ("pc", [-100.0, -118.5, 7.25]),
                      ("midline", [0.5, -10.0, 40.2])):
        window.plan.planning.set_landmark(name, xyz)
    window.plan.dock.raise_()
    qtbot.wait(50)
    for field in window.plan.panel.landmark_labels.values():
        assert _fully_visible(field)
        assert field.width() >= field.fontMetrics().horizontalAdvance(field.text()) + 4, field.text()


# -- 7. slice read-outs on a backdrop: readable over bright slices ----------------------------

def test_slice_title_and_window_readouts_have_a_dark_backdrop(make_window, qtbot):
    window = make_window()
    lo, _ = window.state.data_range
    window.state.set_window(1.0, lo)               # every voxel above the level: white
    view = window.workspace.views["axial"]
    view.zoom = 6.0                                 # zoomed into the bright brain
    view.update()
    qtbot.wait(50)
    image = view.grab().toImage()
    ratio = image.devicePixelRatio()
    layout = view.label_layout()
    for name in ("title", "window"):
        rect = layout[name][0]
        grey = [image.pixelColor(int(x * ratio), int(y * ratio)).lightness()
                for x in np.linspace(rect.left(), rect.right() - 1, 40)
                for y in np.linspace(rect.top(), rect.bottom() - 1, 6)]
        # a white background with thin outlined text is mostly > 200; on the backdrop, dark
        assert np.median(grey) < 90, (name, np.median(grey))
        assert max(grey) > 120, name                 # and the text is still there
