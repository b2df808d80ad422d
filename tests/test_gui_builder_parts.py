"""The model builder's parts: sizes, no maths in the widgets, the Qt-free pieces stay Qt-free,
and the Build tab's own defects (issue 17: lighting, explained share, layout, toolbar)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUILDER_MODULES = sorted((ROOT / "app" / "panels").glob("builder*.py"))


def _classes(path: Path):
    tree = ast.parse(path.read_text())
    return [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]


def test_builder_classes_are_small():
    sizes = {f"{p.name}:{c.name}": c.end_lineno - c.lineno + 1
             for p in BUILDER_MODULES for c in _classes(p)}
    assert sizes and max(sizes.values()) < 400, sizes


def test_no_maths_in_the_builder_widgets():
    for path in BUILDER_MODULES:
        text = path.read_text()
        for banned in ("linalg", "np.random", "scipy.spatial", "standard_normal"):
            assert banned not in text, f"{path.name} uses {banned}"


def test_stage_cache_and_builder_state_import_no_qt():
    code = ("import sys; import core.stages, app.panels.builder_state, app.panels.builder_engine;"
            "print([m for m in sys.modules if m.startswith(('PySide6', 'PyQt', 'pyvistaqt'))])")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert out.stdout.strip() == "[]"
