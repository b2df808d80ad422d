"""Shared fixtures. GUI tests run under pytest-xvfb's virtual X server with the xcb platform."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "xcb")
# The main window shows errors and "save before closing?" in modal dialogs, which would
# block a test run forever; with this set it reports in the status bar only.
os.environ.setdefault("SSM_STUDIO_NO_DIALOGS", "1")

ROOT = Path(__file__).resolve().parents[1]
RESOURCES = ROOT / "resources"


@pytest.fixture(scope="session")
def resources_dir() -> Path:
    return RESOURCES


@pytest.fixture
def window(qtbot, tmp_path, monkeypatch):
    """The main window on the demo data, without the 3D view (GUI tests; a test module may
    define its own ``window``)."""
    from app import demo
    from app.window import MainWindow

    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1300, 900)
    win.load_demo()
    win.show()
    qtbot.waitExposed(win)
    yield win
    win.refit.cancel()
    win.refit.wait()
    win.close()


@pytest.fixture
def make_window(qtbot, tmp_path, monkeypatch):
    """Main windows, shown: ``make(load_demo=True, size=(1300, 900), with_3d=False,
    recovery=False)``; at the end their workers are stopped and they close without asking."""
    from app import demo
    from app.window import MainWindow

    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setenv("SSM_STUDIO_NO_DIALOGS", "1")
    made = []

    def make(load_demo=True, size=(1300, 900), with_3d=False, recovery=False):
        if load_demo and (demo.demo_image() is None or demo.demo_model() is None):
            pytest.skip("demo image or model missing from resources/")
        win = MainWindow(with_3d=with_3d, recovery=recovery)
        qtbot.addWidget(win)
        win.resize(*size)
        if load_demo:
            win.load_demo()
        win.show()
        qtbot.waitExposed(win)
        made.append(win)
        return win

    yield make
    for win in made:
        win.auto_place.cancel()
        win.auto_place.wait()
        win.refit.cancel()
        win.refit.wait()
        win.unsaved = False
        win.close()


@pytest.fixture
def moved_case(tmp_path):
    """A 4 mm copy of the demo template, and the same image moved by a known shift (a
    patient whose models must be placed): (template path, patient path, shift mm)."""
    import numpy as np

    from app import demo
    from core.io import load_volume, save_volume

    if demo.demo_image() is None or demo.demo_model() is None:
        pytest.skip("demo image or model missing from resources/")
    image = load_volume(demo.demo_image())
    coarse = image.affine @ np.diag([4.0, 4.0, 4.0, 1.0])
    data = image.data[::4, ::4, ::4].astype(np.float32)
    template = tmp_path / "template.nii.gz"
    save_volume(template, data, coarse)
    shift = np.array([9.0, -6.0, 4.0])
    moved = coarse.copy()
    moved[:3, 3] += shift
    patient = tmp_path / "patient.nii.gz"
    save_volume(patient, data, moved)
    return template, patient, shift
