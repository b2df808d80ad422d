"""Benchmark: the issue-17 tools' cost on the workspace's budgets (label fill on vs off).

Side by side in one run, on the demo image and model (slice views only, no 3D view, so that
the difference is the overlay's):

- refit round trip (click -> refit in the worker -> result applied and the slice views
  repainted; ``bench_gui.bench_refit``, gmm-aniso) with the filled label overlay off and on
  (on: the label map is voxelised once per new surface and resampled per view);
- slice step (Page Up in the axial view: resample, window, cross-section, repaint) with the
  overlay off and on;
- one brush dab (3 mm) on the label map, from press to repaint.

Budgets (issue 17): click to repainted contour p50 < 60 ms at low load; slice step < 10 ms.

Run: ``QT_QPA_PLATFORM=xcb xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python
benchmarks/bench_tools.py [--edits 15]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

from app.window import MainWindow  # noqa: E402
from bench_gui import _stats, bench_refit  # noqa: E402


def slice_steps(window, app, steps: int = 40) -> list[float]:
    view = window.workspace.views["axial"]
    out = []
    for i in range(steps):
        t0 = time.perf_counter()
        window.state.step_slice("axial", 1 if i % 2 == 0 else -1)
        view.repaint()
        out.append(time.perf_counter() - t0)
    return out


def brush_dabs(window, app, count: int = 20) -> list[float]:
    view = window.workspace.views["axial"]
    window.set_tool("brush")
    window.label_panel.radius.setValue(3.0)
    centre = window.state.active.surface_vertices().mean(axis=0)
    out = []
    for i in range(count):
        x, y = view.world_to_screen(centre + [20.0 + i, 0.0, 0.0])
        t0 = time.perf_counter()
        QTest.mousePress(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                         QPoint(int(x), int(y)))
        QTest.mouseRelease(view, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                           QPoint(int(x), int(y)))
        view.repaint()
        out.append(time.perf_counter() - t0)
    window.set_tool("navigate")
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edits", type=int, default=15, help="timed edits per setting")
    args = parser.parse_args()
    os.environ.setdefault("SSM_STUDIO_NO_DIALOGS", "1")
    app = QApplication.instance() or QApplication(sys.argv[:1])
    window = MainWindow(recovery=False, with_3d=False)
    window.resize(1400, 900)
    window.load_demo()
    window.show()
    window.render_now()
    rows = []
    for fill in (False, True):
        window.labels.set_fill(fill)
        window.render_now()
        (row,) = bench_refit(window, app, args.edits, ("gmm-aniso",))
        steps = slice_steps(window, app)
        rows.append((fill, row[1], steps))      # row: (method, round-trip times, ...)
    dabs = brush_dabs(window, app)
    window.unsaved = False
    window.close()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (shared machine: "
          "times are upper bounds)")
    print(f"{'label fill':<12}{'what':<34}{'p50 ms':>8} {'p90 ms':>8} {'max ms':>8}")
    for fill, refit, steps in rows:
        name = "on" if fill else "off"
        print(f"{name:<12}{'click -> refit -> repainted':<34}{_stats(refit)}")
        print(f"{name:<12}{'slice step (axial)':<34}{_stats(steps)}")
    print(f"{'on':<12}{'brush dab (3 mm) -> repainted':<34}{_stats(dabs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
