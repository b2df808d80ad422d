"""Benchmark: GUI responsiveness of the segmentation workspace.

Measured in one run, under a virtual X server (needs a display for the 3D view):

- start-up: Python + Qt/VTK imports, then main window construction, demo loading and the
  first complete paint of the four views (slice views painted, 3D view rendered);
- refit round trip: one contour point added by a simulated click -> refit in the worker ->
  result applied, cross-section contours recomputed and the slice views repainted; per
  fitting method, on the demo model, for point sets growing from 15 to 40 points; then the
  same with three structures loaded (the demo model plus two library models: right caudate
  and left thalamus), refitting the active one (issue 14's budget: p50 < 60 ms); each row
  also gives the GUI thread's CPU time per edit (click to repaint, ``time.thread_time``),
  which other processes on a loaded machine inflate far less than the wall-clock times;
- slice scrolling on a 256^3 volume: one Page Up step = resampling the slice, windowing,
  the model's cross-section and a synchronous repaint of the view; axis-aligned (voxel
  slice) vs oblique affine (trilinear resampling), plus the 3D view's three textured planes.

Run: ``QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python
benchmarks/bench_gui.py [--edits 25]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

T_START = time.perf_counter()

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from PySide6.QtCore import QEventLoop, QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

from app.window import MainWindow  # noqa: E402
from core.geometry.slicing import polylines, sample_polyline  # noqa: E402
from core.io import Volume  # noqa: E402

T_IMPORTED = time.perf_counter()


def _stats(values: list[float]) -> str:
    ms = 1000 * np.asarray(values)
    return f"{np.median(ms):8.1f} {np.percentile(ms, 90):8.1f} {ms.max():8.1f}"


def _print_row(method, times, residual, fit_times, iterations, cpu) -> None:
    print(f"  {method:<10} {_stats(times)}  {1000 * np.median(fit_times):8.1f} "
          f"{np.median(iterations):8.0f}  {residual:.2f} mm  {1000 * np.median(cpu):8.1f} ms")


def _truth_points(window: MainWindow, seed: int = 0) -> list[tuple[str, float, np.ndarray]]:
    model = window.state.active.model
    rng = np.random.default_rng(seed)
    coef = rng.standard_normal(model.n_factors) * np.sqrt(model.coef_var)
    truth = model.world_instance(coef) + rng.normal(0, 1.0, 3)
    centre = np.rint(truth.mean(axis=0))
    out = []
    for name, axis, offset in (("axial", 2, 0.0), ("coronal", 1, 0.0), ("sagittal", 0, 0.0),
                               ("axial", 2, 5.0), ("coronal", 1, -8.0)):
        normal = np.eye(3)[axis]
        lines = polylines(truth, model.faces, centre + offset * normal, normal)
        pts, _ = sample_polyline(lines[0], spacing=3.0)
        out.append((name, float(centre[axis] + offset), pts))
    return out


def bench_refit(window: MainWindow, app: QApplication, n_edits: int,
                methods=("gmm-aniso", "gmm-iso", "icp")) -> list[tuple]:
    """Per method: click -> contours of the new fit painted in the slice views (ms)."""
    rows = []
    window.set_tool("draw")
    slices = _truth_points(window)
    sequence = [(name, depth, p) for name, depth, pts in slices for p in pts]
    painted: dict[str, float] = {}

    def on_applied(result) -> None:          # runs in the GUI thread, right after set_surface
        # the views have scheduled their repaint (update()); paint them as the event loop
        # would: one backing-store flush for all three
        app.processEvents(QEventLoop.ProcessEventsFlag.ExcludeUserInputEvents)
        painted["t"] = time.perf_counter()
        painted["cpu"] = time.thread_time()

    window.refit_applied.connect(on_applied)
    for method in methods:
        window.state.active.clear_points()
        window.wait_for_refit()
        window.state.active.reset_placement()
        window.fit_panel.set_settings(method=method)
        times, fit_times, iterations, cpu = [], [], [], []
        residual = float("nan")
        for i, (name, depth, p) in enumerate(sequence[: 15 + n_edits]):
            axis = {"sagittal": 0, "coronal": 1, "axial": 2}[name]
            cross = window.state.crosshair.copy()
            cross[axis] = depth
            window.state.set_crosshair(cross)
            view = window.workspace.views[name]
            x, y = view.world_to_screen(p)
            window.wait_for_refit()
            window.render_now()                  # no 3D render pending from the last edit
            painted.clear()
            t0, c0 = time.perf_counter(), time.thread_time()
            QTest.mouseClick(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                             QPoint(int(round(x)), int(round(y))))
            window.wait_for_refit(20000)
            if i >= 15 and "t" in painted:       # time edits once 15 points exist
                times.append(painted["t"] - t0)
                cpu.append(painted["cpu"] - c0)
                residual = window.state.active.fit_info.residual_mm
                fit_times.append(window.state.active.fit_info.fit_seconds)
                iterations.append(window.state.active.fit_info.n_iter)
        rows.append((method, times, residual, fit_times, iterations, cpu))
    window.refit_applied.disconnect(on_applied)
    window.state.active.clear_points()
    window.wait_for_refit()
    return rows


def bench_scroll(app: QApplication, oblique: bool, with_3d: bool,
                 steps: int = 60) -> tuple[list[float], list[float]]:
    rng = np.random.default_rng(0)
    x = np.linspace(-1, 1, 256, dtype=np.float32)
    data = (np.sin(6 * x)[:, None, None] * np.cos(4 * x)[None, :, None] + x[None, None, :]) * 100
    data += rng.normal(0, 5, data.shape).astype(np.float32)
    affine = np.diag([0.9, 0.9, 0.9, 1.0])
    affine[:3, 3] = -115
    if oblique:
        c, s = np.cos(0.2), np.sin(0.2)
        affine[:3, :3] = 0.9 * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    window = MainWindow(recovery=False, with_3d=with_3d)
    window.resize(1400, 900)
    window.state.set_image(Volume(data, affine))
    window.show()
    window.render_now()
    view = window.workspace.views["axial"]
    per_step = []
    for _ in range(steps):
        t0 = time.perf_counter()
        window.state.step_slice("axial", 1)
        view.repaint()
        per_step.append(time.perf_counter() - t0)
    planes = []
    vv = window.workspace.volume_view
    for _ in range(10 if vv is not None else 0):
        window.state.step_slice("axial", -1)
        t0 = time.perf_counter()
        vv.flush()
        planes.append(time.perf_counter() - t0)
    window.close()
    app.processEvents()
    return per_step, planes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edits", type=int, default=25, help="timed edits per method")
    parser.add_argument("--skip-scroll", action="store_true", help="only start-up and refit")
    args = parser.parse_args()
    os.environ.setdefault("SSM_STUDIO_NO_DIALOGS", "1")
    app = QApplication.instance() or QApplication([])
    t0 = time.perf_counter()
    window = MainWindow(recovery=False)
    window.resize(1600, 1000)
    window.load_demo()
    window.show()
    window.render_now()
    t_paint = time.perf_counter() - t0
    print("\nStart-up")
    print(f"  imports (Python, numpy, Qt, VTK, app)    {T_IMPORTED - T_START:6.2f} s")
    print(f"  window + demo data + first full paint    {t_paint:6.2f} s")
    print(f"  total to first paint                     {T_IMPORTED - T_START + t_paint:6.2f} s")
    model = window.state.active.model
    print(f"\nRefit round trip (click -> new contours painted in the slice views), demo model "
          f"{model.n_vertices} vertices, {model.n_factors} factors, 15..{15 + args.edits} points")
    print(f"  {'method':<10} {'p50 ms':>8} {'p90 ms':>8} {'max ms':>8}  {'fit p50':>8} "
          f"{'iter p50':>8}  residual   GUI-thread CPU p50")
    for row in bench_refit(window, app, args.edits):
        _print_row(*row)
    window.close()
    app.processEvents()
    window = MainWindow(recovery=False, with_3d=False)
    window.resize(1600, 1000)
    window.load_demo()
    window.show()
    window.render_now()
    print("  same, window without the 3D view (no OpenGL composition of the window):")
    for row in bench_refit(window, app, args.edits):
        _print_row(*row)
    window.close()
    app.processEvents()
    if not hasattr(window, "add_structure"):    # an older tree (the before column)
        return 0 if args.skip_scroll else bench_scroll_table(app)
    from core.io.model_library import list_library

    for with_3d in (True, False):
        window = MainWindow(recovery=False, with_3d=with_3d)
        window.resize(1600, 1000)
        window.load_demo()
        added = [window.add_structure(e.path) for e in list_library()
                 if e.structure is not None and e.path.stem in ("right_caudate", "left_thalamus")]
        window.state.set_active(0)
        window.show()
        window.render_now()
        print(f"  three structures loaded ({len(window.state.structures)}: demo + {sum(added)} "
              "library models), refitting the active one, window "
              f"{'with the 3D view' if with_3d else 'without the 3D view'}:")
        for row in bench_refit(window, app, args.edits, ("gmm-aniso", "icp")):
            _print_row(*row)
        window.close()
        app.processEvents()
    if args.skip_scroll:
        return 0
    return bench_scroll_table(app)


def bench_scroll_table(app: QApplication) -> int:
    print("\nSlice scrolling, 256^3 float32 volume (one Page Up = resample + window + repaint)")
    print(f"  {'affine':<8} {'window':<14} {'p50 ms':>8} {'p90 ms':>8} {'max ms':>8}   "
          "3D planes update p50")
    for oblique in (False, True):
        for with_3d in (False, True):
            steps, planes = bench_scroll(app, oblique, with_3d)
            extra = f"{1000 * np.median(planes):6.1f} ms" if planes else "     -"
            print(f"  {'oblique' if oblique else 'aligned':<8} "
                  f"{'slices + 3D' if with_3d else 'slices only':<14} {_stats(steps)}   {extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
