"""Benchmark: the crash-recovery autosave, written after every edit in the GUI.

Peers, on the same session in the same run (median and 95th percentile of 200 writes):

- ``write_recovery``: :meth:`core.session.recovery.CrashRecovery.write` (arrays packed as base64, two
  alternating slots, no rename over an existing file);
- ``save_session``: :func:`core.session.document.save_session` (readable JSON, relative paths, atomic
  rename over the previous file);
- ``naive json``: ``json.dumps(indent=2)`` of nested lists + ``os.replace``, the obvious way.

Run: ``.venv/bin/python benchmarks/bench_session.py``
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.session import document as sessions  # noqa: E402
from core.session.recovery import CrashRecovery  # noqa: E402


def _session(n_points: int) -> sessions.Session:
    rng = np.random.default_rng(0)
    points = rng.normal(scale=20.0, size=(n_points, 3))
    return sessions.Session(image="/data/t1.nii.gz", model="/data/stn.npz", points=points,
                            point_slices=[("axial", float(z)) for z in points[:, 2]],
                            coef=rng.normal(size=12), pose=np.eye(4), window=(400.0, 40.0),
                            crosshair=[0.0, 0.0, 0.0], fit={"method": "gmm-iso"})


def _time(fn, repeats: int = 200) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times)), 1e3 * float(np.percentile(times, 95))


def main() -> None:
    with tempfile.TemporaryDirectory() as folder:
        recovery = CrashRecovery(Path(folder) / "state")
        print(f"{'points':>7} {'method':<16} {'median ms':>10} {'p95 ms':>8} {'bytes':>8}")
        for n in (100, 500, 5000):
            session = _session(n)
            target = Path(folder) / "s.json"
            naive = Path(folder) / "naive.json"

            def naive_write():
                doc = {"points": session.points.tolist(), "coef": session.coef.tolist(),
                       "point_slices": session.point_slices, "pose": session.pose.tolist()}
                tmp = naive.with_suffix(".tmp")
                tmp.write_text(json.dumps(doc, indent=2))
                os.replace(tmp, naive)

            rows = [("write_recovery", lambda: recovery.write(session),
                     lambda: recovery.path),
                    ("save_session", lambda: sessions.save_session(target, session),
                     lambda: target),
                    ("naive json", naive_write, lambda: naive)]
            for name, fn, path in rows:
                median, p95 = _time(fn)
                print(f"{n:>7} {name:<16} {median:>10.2f} {p95:>8.2f} {path().stat().st_size:>8}")
        recovery.clear()


if __name__ == "__main__":
    main()
