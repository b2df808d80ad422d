"""Issue 29's planning workflow in the GUI (section 3): plan points where the user clicks, at
sub-voxel precision, or typed; *Place models automatically* offered when a new patient image
opens while the models sit at template coordinates; nudging the placement by hand with undo
and a read-out; the 3D view framing the structures and the whole trajectory."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from app import demo  # noqa: E402
from core.io.model_library import RESOURCES_MODELS  # noqa: E402

LEFT_THALAMUS = RESOURCES_MODELS / "left_thalamus.npz"


def _need_demo():
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")


def _click(view, xyz):
    x, y = view.world_to_screen(np.asarray(xyz, float))
    pixel = QPoint(int(round(x)), int(round(y)))
    QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier, pixel)
    return view.screen_to_world(pixel.x(), pixel.y())          # where the click landed


@pytest.fixture
def anisotropic_scan(tmp_path):
    """The demo T1's voxels on a 1 x 1 x 1.2 mm grid (the audit's scan)."""
    from core.io import load_volume, save_volume

    _need_demo()
    image = load_volume(demo.demo_image())
    affine = image.affine @ np.diag([1.0, 1.0, 1.2, 1.0])
    path = tmp_path / "scan_1x1x1.2.nii.gz"
    save_volume(path, image.data[40:160, 40:190, 40:150].astype(np.float32),
                affine @ np.array([[1, 0, 0, 40], [0, 1, 0, 40], [0, 0, 1, 40], [0, 0, 0, 1.0]]))
    return path


def test_plan_points_sit_where_clicked_not_on_voxel_centres(make_window, anisotropic_scan):
    window = make_window(load_demo=False)
    window.load_image(anisotropic_scan)
    volume = window.state.volume
    view = window.workspace.views["axial"]
    view.zoom = 12.0                               # ~20 screen pixels per mm
    centre = window.state.crosshair.copy()         # a voxel centre
    view.center = view.frame.to_plane(centre)[:2]
    view.update()
    # AC and PC 0.45 mm off voxel centres, in opposite directions: snapping loses 0.9 mm
    ac_true = centre + [0.35, 12.45, 0.0]
    pc_true = centre + [0.35, -14.55, 0.0]
    view.center = view.frame.to_plane((ac_true + pc_true) / 2)[:2]
    view.zoom = 5.0
    view.update()
    panel = window.plan.panel
    clicked_ac = _click(view, ac_true)
    panel.set_landmark("ac")
    clicked_pc = _click(view, pc_true)
    panel.set_landmark("pc")
    ac, pc = window.plan.planning.landmarks["ac"], window.plan.planning.landmarks["pc"]
    assert np.allclose(ac, clicked_ac) and np.allclose(pc, clicked_pc)
    true_distance = float(np.linalg.norm(ac_true - pc_true))            # 27.0 mm
    measured = float(np.linalg.norm(ac - pc))
    pixel_mm = 1.0 / view._base()[0]
    assert abs(measured - true_distance) <= 2 * pixel_mm < 0.2
    # the crosshair itself stays on the voxel centre (the slices shown are voxels)
    ijk = volume.world_to_voxel(window.state.crosshair)
    assert np.allclose(ijk, np.round(ijk), atol=1e-6)
    # target and entry go where clicked too
    target_click = _click(view, centre + [2.3, 1.7, 0.0])
    panel.set_target_here()
    assert np.allclose(window.plan.planning.target_of(window.state.active), target_click)


def test_plan_points_are_editable_by_typing_coordinates(make_window, anisotropic_scan):
    window = make_window(load_demo=False)
    window.load_image(anisotropic_scan)
    panel, planning = window.plan.panel, window.plan.planning
    messages = []
    panel.message.connect(messages.append)
    field = panel.landmark_labels["ac"]
    field.setText("1.25, -2.5, 3.75")
    field.editingFinished.emit()
    assert np.allclose(planning.landmarks["ac"], [1.25, -2.5, 3.75])
    field.setText("(0.5 -27.25 4.1)")                    # brackets and spaces are fine
    field.editingFinished.emit()
    assert np.allclose(planning.landmarks["ac"], [0.5, -27.25, 4.1])
    field.setText("0.5, nonsense, 4")                     # said, and nothing changes
    field.editingFinished.emit()
    assert np.allclose(planning.landmarks["ac"], [0.5, -27.25, 4.1])
    assert "not three numbers" in messages[-1] and field.text() == "0.50, -27.25, 4.10"
    planning.undo()
    assert np.allclose(planning.landmarks["ac"], [1.25, -2.5, 3.75])
    panel.entry_field.setText("10, 20, 60")
    panel.entry_field.editingFinished.emit()
    assert np.allclose(planning.entry_of(window.state.active), [10, 20, 60])
    # the fields show the whole coordinates at the narrowest dock
    window.resize(1280, 800)
    window.plan.dock.raise_()
    QTest.qWait(50)
    for f in [*panel.landmark_labels.values(), panel.entry_field]:
        assert f.width() >= f.fontMetrics().horizontalAdvance(f.text()) + 4, f.objectName()


def test_new_patient_offers_placement_then_nudge_with_undo(make_window, moved_case, qtbot,
                                                           monkeypatch):
    pytest.importorskip("SimpleITK")
    template, patient, shift = moved_case
    window = make_window(load_demo=False)
    window.load_image(template)
    window.load_model(demo.demo_model())
    window.add_structure(LEFT_THALAMUS)
    structures = list(window.state.structures)
    before = [s.surface_vertices().copy() for s in structures]
    asked = []
    monkeypatch.setattr(window, "ask", lambda text: asked.append(text) or True)
    monkeypatch.setattr(window, "place_automatically", lambda: window.auto_place.start(
        template, show_dialog=False, levels_mm=(8.0,), polish=False))
    done = []
    window.auto_place.finished.connect(done.append)
    window.load_image(patient)                      # the models sit at template coordinates
    assert len(asked) == 1 and "template's coordinates" in asked[0]
    assert "caudate nucleus (left)" in asked[0] and "thalamus (left)" in asked[0]
    qtbot.waitUntil(lambda: bool(done), timeout=90000)
    placed = [s.surface_vertices().copy() for s in structures]
    for b, p in zip(before, placed):
        assert np.linalg.norm(p.mean(axis=0) - (b.mean(axis=0) + shift)) < 2.0
    assert window.auto_place.structures_at_template() == []    # placed: nothing more to offer
    window.load_image(patient)
    assert len(asked) == 1

    # nudge: shift 2 mm to the right, then turn 5 degrees about S/I, all structures together
    dialog = window.features["placement-nudge"].show()
    dialog.shift_step.setValue(2.0)
    dialog.buttons[("shift", 0, 1)].click()
    for p, s in zip(placed, structures):
        assert np.allclose(s.surface_vertices(), p + [2.0, 0, 0], atol=1e-6)
    assert "Nudged 2.0 mm and 0.0°" in dialog.readout.text()
    shifted = [s.surface_vertices().copy() for s in structures]
    centre = np.vstack(shifted).mean(axis=0)
    dialog.turn_step.setValue(5.0)
    dialog.buttons[("turn", 2, 1)].click()
    turned = [s.surface_vertices() for s in structures]
    assert np.allclose(np.vstack(turned).mean(axis=0), centre, atol=1e-6)  # about the centre
    for a, b in zip(shifted, turned):
        r = np.linalg.lstsq(np.c_[a - centre], b - centre, rcond=None)[0]
        assert np.degrees(np.arccos(np.clip(r[0, 0], -1, 1))) == pytest.approx(5.0, abs=1e-6)
    assert "5.0°" in dialog.readout.text()
    # the contour points' distance to the surfaces is in the read-out
    c = structures[0].surface_vertices().mean(axis=0)
    window.state.set_active(structures[0])
    window.state.active.add_point(c + [3, 0, 0], "axial", float(c[2]))
    dialog.refresh()
    assert "1 contour point(s)" in dialog.readout.text()
    window.state.active.remove_point(0)
    # undo of a nudge: the dialog's Undo (every structure), or Ctrl+Z (the active one)
    dialog.undo_button.click()
    for a, s in zip(shifted, structures):
        assert np.allclose(s.surface_vertices(), a, atol=1e-6)
    dialog.undo_button.click()
    for p, s in zip(placed, structures):
        assert np.allclose(s.surface_vertices(), p, atol=1e-6)
    assert not dialog.undo_button.isEnabled()


def test_3d_view_frames_the_structures_and_the_whole_trajectory(make_window, qtbot):
    window = make_window(with_3d=True, size=(1400, 900))
    window.add_structure(LEFT_THALAMUS)
    window.state.set_active(0)
    view = window.workspace.volume_view
    qtbot.waitUntil(lambda: view is not None and view._camera_set, timeout=20000)
    caudate = window.state.active
    target = window.plan.planning.target_of(caudate)
    entry = target + np.array([-25.0, 20.0, 62.0])          # a frontal entry, 70 mm away
    window.plan.planning.set_entry(caudate, entry)
    view.flush()
    renderer = view.plotter.renderer
    width, height = renderer.GetSize()

    def on_screen(points):
        out = []
        for p in np.asarray(points).reshape(-1, 3):
            renderer.SetWorldPoint(*p, 1.0)
            renderer.WorldToDisplay()
            out.append(renderer.GetDisplayPoint()[:2])
        return np.array(out)

    shown = np.vstack([s.surface_vertices() for s in window.state.structures]
                      + [entry[None], target[None]])
    xy = on_screen(shown)
    assert np.all(xy[:, 0] > 0) and np.all(xy[:, 0] < width), (xy.min(0), xy.max(0), width)
    assert np.all(xy[:, 1] > 0) and np.all(xy[:, 1] < height), (xy.min(0), xy.max(0), height)
