"""The model builder's parts: sizes, no maths in the widgets, the Qt-free pieces stay Qt-free,
and the Build tab's own defects (issue 17: lighting, explained share, layout, toolbar)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BUILDER_MODULES = sorted((ROOT / "app" / "panels").glob("builder*.py"))


def _classes(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]


def test_builder_classes_are_small():
    sizes = {f"{p.name}:{c.name}": c.end_lineno - c.lineno + 1
             for p in BUILDER_MODULES for c in _classes(p)}
    assert sizes and max(sizes.values()) < 400, sizes


def test_no_maths_in_the_builder_widgets():
    for path in BUILDER_MODULES:
        text = path.read_text(encoding="utf-8")
        for banned in ("linalg", "np.random", "scipy.spatial", "standard_normal"):
            assert banned not in text, f"{path.name} uses {banned}"


def test_stage_cache_and_builder_state_import_no_qt():
    code = ("import sys; import core.build.stages, app.panels.builder_state, app.panels.builder_engine;"
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
    from core.datasets.factors import ellipsoid_surface

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


# ------------------------------------------------------------------------------------------
# Issue 17 defects 4 (explained share per factor) and 8 (Build tab layout and opening)
# ------------------------------------------------------------------------------------------


def _planted_meshes(n_shapes=12, n_factors=3):
    from core.datasets.factors import ellipsoid_surface, planted_shapes
    from core.io import TriMesh

    base, faces = ellipsoid_surface(2)
    planted = planted_shapes(base, faces, n_shapes=n_shapes, n_factors=n_factors, noise=0.02,
                             random_state=4)
    return [TriMesh(x, faces, f"s{k:02d}.vtk") for k, x in enumerate(planted.shapes)]


def _built_model(method="pca", **params):
    from core.build.stages import NO_CORRESPONDENCE, BuildSettings, StagedBuild

    build = StagedBuild()
    model = build.run(BuildSettings(_planted_meshes(), reference=NO_CORRESPONDENCE,
                                    align_method="none", method=method, params=params))
    return model, build.cache["alignment"].result.aligned


@pytest.fixture
def panel(qtbot):
    from PySide6.QtWidgets import QMainWindow

    from app.panels.builder import BuilderPanel

    window = QMainWindow()
    panel = BuilderPanel()
    window.setCentralWidget(panel)
    window.resize(1200, 800)
    qtbot.addWidget(window)
    window.show()
    qtbot.waitExposed(window)
    yield panel
    panel.close_views()
    window.close()


def _list_percentages(view) -> list[float]:
    import re

    return [float(re.match(r"\d+: +([\d.]+)% var", view.factor_list.item(i).text()).group(1))
            for i in range(view.factor_list.count())]


def test_factor_list_shows_each_factors_share_of_the_training_variance(panel, qtbot):
    import numpy as np

    model, aligned = _built_model("pca")
    panel.show_model(model)
    panel.tabs.setCurrentWidget(panel.factor_view)
    shown = np.array(_list_percentages(panel.factor_view))
    # PCA: the shares are the eigenvalue ratios of the training shapes' covariance
    centred = (aligned - aligned.mean(axis=0)).reshape(len(aligned), -1)
    s = np.linalg.svd(centred, compute_uv=False)
    truth = 100 * s[:model.n_factors] ** 2 / np.sum(s ** 2)
    np.testing.assert_allclose(shown, truth, atol=0.051)  # one decimal shown
    assert "of the training shapes' variance" in panel.factor_view.factor_list.item(0).toolTip()
    assert f"{truth.sum():.1f}%" in panel.factor_view.total_label.text()
    # LSF with more factors than the 3 planted ones: the extra ones show as explaining little,
    # and the total stays at most the training variance (not renormalised to 100% each time)
    lsf, _ = _built_model("lsf", n_factors=8)
    panel.show_model(lsf)
    shares = np.array(_list_percentages(panel.factor_view))
    assert len(shares) == lsf.n_factors and shares.sum() < 100.5
    assert np.sort(shares)[:3].max() < 0.5 * shares.max()


def test_model_form_is_as_tall_as_the_shown_method(panel):
    box = panel.pipeline
    for name in ("pca", "lsf", "pca"):
        panel.model_method.setCurrentText(name)
        panel.layout().activate()
        panel.repaint()
        form = panel.current_form()
        # the stack used to take the tallest form's height (LSF), leaving a blank gap under PCA
        assert box.model_forms.sizeHint().height() <= form.sizeHint().height() + 4


def test_mirror_check_box_sets_the_build_setting(panel):
    from core.io import TriMesh

    box = panel.pipeline
    tetra = TriMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]],
                    [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], "t")
    entries = [type("Entry", (), {"mesh": tetra, "path": "t.vtk", "name": "t"})()]
    assert box.mirror_check.isChecked() and box.settings(entries).mirror_check
    changed = []
    box.changed.connect(lambda *a: changed.append(a))
    box.mirror_check.setChecked(False)
    assert changed and box.settings(entries).mirror_check is False


def test_build_tab_hides_the_segmentation_toolbar(qtbot, tmp_path, monkeypatch):
    from app.window import MainWindow

    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1000, 700)
    win.show()
    qtbot.waitExposed(win)
    try:
        assert win.toolbar.isVisible()
        win.tabs.setCurrentIndex(1)
        assert win.builder is not None and not win.toolbar.isVisible()
        # the 3D views are not built until there is something to draw
        assert not win.builder.tabs.meshes_view.created
        assert win.builder.tabs.meshes_view.hint.isVisible()
        win.tabs.setCurrentIndex(0)
        assert win.toolbar.isVisible()
    finally:
        win.close()


def test_opening_the_builder_does_not_load_the_correspondence_engine():
    # importing core.correspondence (scipy.optimize) took ~1.8 s of the ~2 s tab switch
    from core.build.stages import DEFAULT_N_REFERENCES

    code = ("import sys; from PySide6.QtWidgets import QApplication; app = QApplication([]);"
            "from app.panels.builder import BuilderPanel; p = BuilderPanel();"
            "print(p.n_references.value(), 'core.correspondence.batch' in sys.modules,"
            " 'scipy.optimize' in sys.modules)")
    import os

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True, env=env)
    assert out.stdout.split()[-3:] == [str(DEFAULT_N_REFERENCES), "False", "False"], out.stdout + out.stderr


def test_builder_is_prepared_in_the_background_without_leaving_the_segment_tab(qtbot, tmp_path,
                                                                               monkeypatch):
    from app.window import MainWindow

    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(tmp_path / "state"))
    win = MainWindow(with_3d=False, recovery=False)
    qtbot.addWidget(win)
    win.resize(1000, 700)
    win.show()
    qtbot.waitExposed(win)
    try:
        assert win.builder is None
        win.tabs.prepare_builder()               # run_gui calls this 1.5 s after the first paint
        assert win.builder is not None
        assert win.tabs.currentWidget() is win.workspace and win.toolbar.isVisible()
        assert win.tabs.tabText(1) == "Build model" and win.tabs.widget(1) is win.builder
        win.tabs.setCurrentIndex(1)
        assert win.tabs.currentWidget() is win.builder and not win.toolbar.isVisible()
        win.tabs.prepare_builder()               # idempotent
        assert win.tabs.count() == 2
    finally:
        win.close()


# ------------------------------------------------------------------------------------------
# Issue 13: Add label maps...
# ------------------------------------------------------------------------------------------


def test_add_label_maps_makes_training_surfaces_in_a_worker(panel, qtbot, tmp_path):
    pytest.importorskip("core.correspondence.mesh_labels")
    import numpy as np

    from core.io import save_volume

    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    affine[:3, 3] = [-20.0, -20.0, -20.0]
    ijk = np.indices((40, 40, 40)).reshape(3, -1).T + affine[:3, 3]
    inside = (np.sum(ijk ** 2, axis=1) <= 8.0 ** 2).reshape(40, 40, 40)
    labels = np.where(inside, 3, 0).astype(np.uint8)
    good = tmp_path / "sphere.nii.gz"
    save_volume(good, labels, affine)
    empty = tmp_path / "nothing.nii.gz"
    save_volume(empty, np.zeros_like(labels), affine)
    assert panel.meshes_box.labels_button.isVisible()
    panel.add_label_maps([good, empty], 3, 600)
    assert panel.is_busy and panel.cancel_button.isEnabled()   # a worker, cancellable
    qtbot.waitUntil(lambda: not panel.is_busy, timeout=60000)
    first, second = panel.state.entries
    assert first.mesh is not None and second.mesh is None
    assert "nothing.nii.gz" in second.problems[0] and "3" in second.problems[0]
    v, f = first.mesh.vertices, first.mesh.faces
    a, b, c = (v[f[:, i]] for i in range(3))
    volume = abs(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0
    assert abs(volume / (4 / 3 * np.pi * 8.0 ** 3) - 1) < 0.05
    assert abs(len(v) - 600) < 0.2 * 600
    item = panel.mesh_list.topLevelItem(1)
    assert item.text(3) and item.text(1) == ""   # the error is listed, nothing aborted
