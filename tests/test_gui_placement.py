"""*Place models automatically* (issue 14 item 3 GUI): registration in a worker, then placement."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("SimpleITK")
pytestmark = pytest.mark.gui

from app import demo  # noqa: E402
from app.window import MainWindow  # noqa: E402


@pytest.fixture
def window(qtbot, tmp_path, monkeypatch):
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1200, 850)
    yield win
    win.auto_place.cancel()
    win.auto_place.wait()
    win.close()


def test_place_models_automatically_recovers_a_known_shift(window, moved_case, qtbot):
    template, patient, shift = moved_case
    window.load_image(patient)
    window.load_model(demo.demo_model())
    before = window.state.active.surface_vertices().mean(axis=0)
    done = []
    window.auto_place.finished.connect(done.append)
    assert window.place_automatically(template, levels_mm=(8.0,), polish=False)
    assert window.auto_place.is_running
    qtbot.waitUntil(lambda: bool(done), timeout=60000)
    after = window.state.active.surface_vertices().mean(axis=0)
    assert np.linalg.norm(after - (before + shift)) < 2.0, (after - before, shift)
    assert np.allclose(window.state.active.placement, window.state.active.pose)
    assert "Placed 1 structure" in window.statusBar().currentMessage()
    window.undo()                                    # one undo step puts it back
    assert window.state.active.surface_vertices().mean(axis=0) == pytest.approx(before, abs=1e-6)


def test_cancelled_placement_moves_nothing(window, moved_case, qtbot):
    template, patient, _ = moved_case
    window.load_image(patient)
    window.load_model(demo.demo_model())
    pose = window.state.active.pose.copy()
    failed = []
    window.auto_place.failed.connect(failed.append)
    window.place_automatically(template, levels_mm=(8.0, 4.0))
    window.auto_place.cancel()
    qtbot.waitUntil(lambda: bool(failed), timeout=60000)
    assert "cancelled" in failed[0] and np.array_equal(window.state.active.pose, pose)
    assert not window.auto_place.is_running


def test_placement_needs_an_image_and_a_model(window):
    messages = []
    window.auto_place.failed.connect(messages.append)
    assert not window.place_automatically()
    assert "open an image first" in messages[-1]
