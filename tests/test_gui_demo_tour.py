"""The demo tour (issue 17): the simulated user draws contours slice by slice with the live
refit, sweeps a factor, exports; any key stops it; --record writes PNG frames."""

from __future__ import annotations

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
    pts = window.state.active.points
    assert pts.n_slices() == 3 and len(pts) > 8
    assert set(pts.frame.tolist()) == {0, 1, 2}          # axial, coronal, sagittal
    # the live refit followed the contours: the fit is closer to the drawn structure
    qtbot.waitUntil(lambda: not window.refit.is_busy, timeout=30000)
    s = window.state.active
    end = symmetric_surface_distance(s.surface_vertices(), s.model.faces, truth_v, truth_f)
    print(f"\ntour: surface distance to the drawn structure {start:.2f} -> {end:.2f} mm")
    assert end < start
    # the factor sweep ended at 0 SD on factor 1, and the export went to DIR/export
    assert window.factors_panel.sliders[0].value() == 0
    exported = {p.name for p in (tmp_path / "rec" / "export").iterdir()}
    assert {"segmentation.nii.gz", "surface.vtk", "points.csv"} <= exported
    frames = sorted((tmp_path / "rec").glob("frame_*.png"))
    assert len(frames) == len(tour.frames) > 8
    assert frames[0].name == "frame_0001.png"


def test_any_key_stops_the_tour_and_leaves_the_session_editable(window, qtbot):
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
