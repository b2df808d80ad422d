"""The demo tour (issue 17): the simulated user draws contours slice by slice with the live
refit, sweeps a factor, exports; any key stops it; --record writes PNG frames."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")

from PySide6.QtCore import Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from app import demo, demo_tour  # noqa: E402
from app.window import MainWindow  # noqa: E402


@pytest.fixture
def window(qtbot, tmp_path, monkeypatch):
    if demo_tour.truth_surface() is None or demo.demo_model() is None:
        pytest.skip("demo data missing")
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1100, 800)
    win.load_demo()
    win.show()
    qtbot.waitExposed(win)
    yield win
    win.runner.cancel()
    win.runner.wait()
    win.unsaved = False
    win.close()


def test_tour_draws_refits_sweeps_exports_and_records(window, qtbot, tmp_path):
    from core.geometry.toolkit import symmetric_surface_distance

    truth_v, truth_f = demo_tour.truth_surface()
    s = window.state.active
    start = symmetric_surface_distance(s.surface_vertices(), s.model.faces, truth_v, truth_f)
    tour = demo_tour.start_tour(window, record=tmp_path / "rec", interval_ms=1, spacing=8.0)
    with qtbot.waitSignal(tour.finished, timeout=120000) as done:
        pass
    assert done.args == [True]
    caudate = window.state.structures[0]
    pts = caudate.points
    assert pts.n_slices() == 3 and len(pts) > 8
    assert set(pts.frame.tolist()) == {0, 1, 2}          # axial, coronal, sagittal
    # the live refit followed the contours: the fit is closer to the drawn structure
    qtbot.waitUntil(lambda: not window.refit.is_busy, timeout=30000)
    s = caudate
    end = symmetric_surface_distance(s.surface_vertices(), s.model.faces, truth_v, truth_f)
    print(f"\ntour: surface distance to the drawn structure {start:.2f} -> {end:.2f} mm")
    assert end < start
    # the factor sweep ended at 0 SD on factor 1 of the caudate, and the export went to
    # DIR/export (the STN plan came after it, and left a STN active)
    window.state.set_active(caudate)
    assert window.factors_panel.sliders[0].value() == 0
    exported = {p.name for p in (tmp_path / "rec" / "export").iterdir()}
    assert {"segmentation.nii.gz", "surface.vtk", "points.csv"} <= exported
    # then the bilateral STN plan: both STN fitted to a few contours, a lead on each side
    stn = [s for s in window.state.structures if "subthalamic" in s.label.lower()]
    assert len(stn) == 2
    planning = window.plan.planning
    assert planning.frame() is not None
    for s in stn:
        assert len(s.points) >= 6 and s.points.n_slices() == 2
        placed = planning.placed_lead_of(s)
        assert placed is not None and placed.lead.key == "medtronic-3389"
        # the tip STN_LEAD_DEPTH past the target along the trajectory (entry -> target)
        traj = planning.trajectory_of(s)
        direction = (traj.target - traj.entry) / np.linalg.norm(traj.target - traj.entry)
        np.testing.assert_allclose(placed.tip, planning.target_of(s)
                                   + demo_tour.STN_LEAD_DEPTH * direction, atol=1e-9)
        rows = planning.contact_rows(s)
        assert len(rows) == 4 and rows[0]["nearest_structure"] == s.label
        # contacts 0 and 1 (the deepest two) inside the fitted STN
        assert all(r["structure"] == s.label for r in rows[:2]), rows
    # left lead on the left (RAS x < 0), right on the right
    assert planning.placed_lead_of(stn[0]).tip[0] < 0 < planning.placed_lead_of(stn[1]).tip[0]
    frames = sorted((tmp_path / "rec").glob("frame_*.png"))
    assert len(frames) == len(tour.frames) > 8
    assert frames[0].name == "frame_0001.png"


def test_any_key_stops_the_tour_and_leaves_the_session_editable(window, qtbot, tmp_path,
                                                                monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    tour = demo_tour.start_tour(window, interval_ms=5)
    qtbot.waitUntil(lambda: len(window.state.active.points) >= 3, timeout=20000)
    with qtbot.waitSignal(tour.finished, timeout=5000) as done:
        QTest.keyClick(window, Qt.Key.Key_Space)
    assert done.args == [False] and not tour.running
    n = len(window.state.active.points)
    qtbot.wait(100)
    assert len(window.state.active.points) == n                # nothing more is drawn
    window.undo()                                       # and the user can go on
    assert len(window.state.active.points) < n
    # stopped before its export step, the tour leaves no temporary folder behind
    assert not list(tmp_path.glob("ssm-studio-demo-*"))
