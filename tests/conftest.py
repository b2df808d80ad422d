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
