"""Several structures in one session (issue 14): list, drawing, per-structure undo, sessions."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from app.window import MainWindow  # noqa: E402
from core.io.model_library import list_library  # noqa: E402


def _library(name: str):
    for entry in list_library():
        if entry.structure is not None and entry.path.stem == name:
            return entry.path
    pytest.skip(f"library model {name} missing from resources/models/")


def _draw_around(window, centre, radius, n, frame="axial"):
    """Click n points on a circle around ``centre`` in the slice through it."""
    axis = {"sagittal": 0, "coronal": 1, "axial": 2}[frame]
    cross = window.state.crosshair.copy()
    cross[axis] = centre[axis]
    window.state.set_crosshair(cross)
    view = window.workspace.views[frame]
    window.set_tool("draw")
    others = [a for a in range(3) if a != axis]
    for t in np.linspace(0, 2 * np.pi, n, endpoint=False):
        p = window.state.crosshair.copy()
        p[others[0]] = centre[others[0]] + radius * np.cos(t)
        p[others[1]] = centre[others[1]] + radius * np.sin(t)
        x, y = view.world_to_screen(p)
        QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                         QPoint(int(round(x)), int(round(y))))


def test_two_structures_draw_undo_save_reopen(window, qtbot, tmp_path):
    state = window.state
    first = state.active
    assert window.add_structure(_library("right_caudate"))
    second = state.active
    assert second is not first and len(state.structures) == 2
    assert second.label == "caudate nucleus (right)" and second.demo
    assert second.color != first.color
    panel = window.structures_panel
    assert panel.table.rowCount() == 2 and panel.table.item(1, 2).text() == "caudate nucleus"
    assert panel.table.selectedIndexes()[0].row() == 1          # the new one is active

    # draw into the second (active) structure: only it is refitted
    first_before = first.surface_vertices().copy()
    centre2 = second.surface_vertices().mean(axis=0)
    _draw_around(window, centre2, 4.0, 6)
    assert window.wait_for_refit(20000)
    assert len(second.points) == 6 and len(first.points) == 0
    assert second.fit_info.n_iter > 0
    assert np.array_equal(first.surface_vertices(), first_before)

    # select the first in the list, draw there, undo there: the second is untouched
    panel.table.selectRow(0)
    assert state.active is first
    centre1 = first.surface_vertices().mean(axis=0)
    _draw_around(window, centre1, 3.0, 4)
    window.wait_for_refit(20000)
    assert len(first.points) == 4
    second_points, second_coef = second.points, second.coef.copy()
    window.undo()
    window.undo()
    assert len(first.points) == 2
    assert second.points is second_points and np.array_equal(second.coef, second_coef)
    window.wait_for_refit(20000)

    # both structures' contours are drawn in the axial view, each from its own surface
    axial = window.workspace.views["axial"]
    assert axial._segments.get(first.id) is not None and axial._segments.get(second.id) is not None

    # rename and recolour, save, reopen in a fresh window
    second.set_properties(name="caudate R", color=(10, 200, 90))
    assert panel.table.item(1, 2).text() == "caudate R"
    path = tmp_path / "two.json"
    assert window.save_session(path=path)
    doc = json.loads(path.read_text())
    assert doc["format_version"] == 1 and len(doc["structures"]) == 2
    assert doc["active_structure"] == 0
    assert doc["model"] == doc["structures"][0]["model"]          # top level = active structure
    assert len(doc["points"]) == 2

    other = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(other)
    other.open_session(path)
    a, b = other.state.structures
    assert other.state.active is a
    assert [len(a.points), len(b.points)] == [2, 6]
    assert np.allclose(a.points.xyz, first.points.xyz) and np.allclose(b.points.xyz, second.points.xyz)
    assert np.allclose(b.coef, second.coef) and np.allclose(b.pose, second.pose)
    assert b.name == "caudate R" and b.side == "right" and b.color == (10, 200, 90)
    assert b.model_path.name == "right_caudate.npz"
    assert not other.state.active.can_undo() and not b.can_undo()
    other.state.set_active(b)
    assert other.factors_panel.value_labels[0].text() == \
        f"{b.coef[0] / np.sqrt(b.model.coef_var[0]):+.2f}"
    other.close()


def test_locked_or_hidden_structure_refuses_drawing(window):
    s = window.state.active
    s.set_properties(locked=True)
    assert window.structures_panel.table.item(0, 5).checkState() == Qt.CheckState.Checked
    _draw_around(window, s.surface_vertices().mean(axis=0), 3.0, 2)
    assert len(s.points) == 0
    assert "locked" in window.statusBar().currentMessage()
    # unlocking from the list's check box allows drawing again
    window.structures_panel.table.item(0, 5).setCheckState(Qt.CheckState.Unchecked)
    assert not s.locked
    _draw_around(window, s.surface_vertices().mean(axis=0), 3.0, 2)
    assert len(s.points) == 2
    window.wait_for_refit(20000)


def test_remove_structure_keeps_the_others(window):
    state = window.state
    first = state.active
    window.add_structure(_library("left_thalamus"))
    thalamus = state.active
    window.remove_structure(thalamus)
    assert state.structures == [first] and state.active is first
    assert thalamus.id not in window.workspace.views["axial"]._segments
    assert window.structures_panel.table.rowCount() == 1
