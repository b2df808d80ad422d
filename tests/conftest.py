"""Shared fixtures. GUI tests run under pytest-xvfb's virtual X server with the xcb platform."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "xcb")

ROOT = Path(__file__).resolve().parents[1]
RESOURCES = ROOT / "resources"


@pytest.fixture(scope="session")
def resources_dir() -> Path:
    return RESOURCES
