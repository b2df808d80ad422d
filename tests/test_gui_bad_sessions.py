"""Issue 28, item 5, in the GUI: sessions the workspace saved, then damaged, are refused whole
with the one-line error of :func:`core.session.document.load_session` (before: a pose holding 1e200
raised an IndexError in core/geometry/toolkit.py while the session was being applied)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from app import demo  # noqa: E402
from app.window import MainWindow  # noqa: E402
from core.io import DataFileError  # noqa: E402


@pytest.fixture
def saved_session(qtbot, tmp_path, monkeypatch):
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.load_demo()
    path = tmp_path / "s.json"
    assert win.save_session(path=path)
    fresh = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(fresh)
    return path, fresh


def _damage(path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("change, word", [
    (lambda d: d.update(pose=[[1e200, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     "pose scales by up to 1e+200"),
    (lambda d: d.update(pose=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 3, 0], [0, 0, 0, 1]]),
     "not a similarity"),
    (lambda d: d["info"].update(planning={"structures": 5}), "info.planning structures"),
    (lambda d: d.update(image="scan\u0000.nii.gz"), "null byte"),
], ids=["pose 1e200", "anisotropic pose", "garbage planning", "null byte"])
def test_a_damaged_session_is_refused_before_it_is_applied(saved_session, change, word):
    path, window = saved_session
    _damage(path, change)
    before = window.state.image_path
    with pytest.raises(DataFileError) as info:
        window.open_session(path)
    assert str(info.value).startswith(f"{path}: invalid session") or str(path) in str(info.value)
    assert word in str(info.value) and "\n" not in str(info.value)
    assert window.state.image_path == before  # nothing of it applied


def test_the_undamaged_session_opens(saved_session):
    path, window = saved_session
    window.open_session(path)
    assert window.state.image_path is not None
    assert np.all(np.isfinite(window.state.crosshair))
