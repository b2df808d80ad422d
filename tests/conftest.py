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
