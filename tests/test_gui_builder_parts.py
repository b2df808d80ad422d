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


# ------------------------------------------------------------------------------------------
# Issue 17 defect 3: the Build tab's 3D views are lit
# ------------------------------------------------------------------------------------------


def _shading_spread(plotter) -> float:
    """Spread (std of grey levels) over the pixels of the drawn object: ~0 when unlit."""
    import numpy as np

    image = np.asarray(plotter.screenshot(return_img=True), dtype=np.float64)[..., :3]
    grey = image.mean(axis=2)
    inside = np.abs(image - 255.0).max(axis=2) > 30  # not the white background
    assert inside.mean() > 0.05  # the object covers part of the view
    return float(grey[inside].std())


def test_builder_views_keep_their_lights_when_redrawn(qtbot):
    import numpy as np
    from PySide6.QtWidgets import QMainWindow

    from app.panels.builder_views import MeshesView
    from core.models.synthetic import ellipsoid_surface

    vertices, faces = ellipsoid_surface(3, radii=(20.0, 20.0, 20.0))
    window = QMainWindow()
    view = MeshesView()
    window.setCentralWidget(view)
    window.resize(400, 400)
    qtbot.addWidget(window)
    window.show()
    qtbot.waitExposed(window)
    try:
        for _ in range(2):  # the second draw clears the first
            view.show_meshes([("sphere", vertices, faces)], layout="grid")
        assert len(view.plotter.renderer.lights) > 0
        spread = _shading_spread(view.plotter)
        print(f"\ngrey-level spread over the lit sphere: {spread:.1f}")
        assert spread > 8.0  # unlit: one flat colour (spread ~0)
        # scalars too (factor maps, samples)
        view.show_meshes([("sphere", vertices, faces)], layout="grid",
                         scalars=[np.zeros(len(vertices))], clim=(0.0, 1.0))
        assert len(view.plotter.renderer.lights) > 0
        assert _shading_spread(view.plotter) > 8.0
    finally:
        view.close_view()
        window.close()
