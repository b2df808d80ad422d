"""Benchmark: the engine before and after the round-2 redesign (issue 16), side by side.

Issue 16 split the engine into packages (reconstruction, correspondence, io, models) with
behaviour unchanged and asked that refit latency and correspondence time stay within 10% of
before. This script exports the tree of an earlier commit (default ``caedcf2``, the last
commit before the redesign) with ``git archive`` and runs the same workload in both trees,
each in its own Python process, alternating the trees ``--rounds`` times so that a change of
machine load hits both equally:

- refit: ``core.reconstruction.fit_points`` on the demo model (the current tree's file, read
  by each tree's own loader) to 30 noisy points sampled from a random model instance,
  cold fits (no warm start), per method; p50 over the fits;
- correspondence: ``core.correspondence.establish_correspondence`` of 6 known-homology bean
  shapes (own tessellations, ~1,000 vertices) to the first one, one process (``n_jobs=1``),
  after an untimed warm-up call (imports);
  the current tree twice: with its defaults (grooming, the mirror check and the groupwise
  refinement of issue 13 on: more work by design) and with them off (the same work as before).

Run: ``.venv/bin/python benchmarks/bench_redesign.py [--before caedcf2] [--rounds 2]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# The workload, run by ``python -c`` inside each tree (only APIs both trees have).
WORKLOAD = r"""
import json, sys, time
import numpy as np
from core.io import TriMesh, load_model
from core.reconstruction import fit_points
from core.correspondence import establish_correspondence

data = np.load(sys.argv[1])
options = json.loads(sys.argv[2])
out = {}
model = load_model(sys.argv[3])
for method in ("gmm-aniso", "icp"):
    times = []
    for i in range(int(data["n_fits"])):
        pts = data["points"][i]
        t0 = time.perf_counter()
        fit_points(model, pts, method=method, pose="similarity")
        times.append(time.perf_counter() - t0)
    out["refit " + method] = times
meshes = [TriMesh(data[f"v{i}"], data[f"f{i}"], f"bean_{i:02d}") for i in range(int(data["n_meshes"]))]
establish_correspondence(meshes[:2], reference=0, n_jobs=1)   # imports and caches, untimed
for label, extra in options.items():
    t0 = time.perf_counter()
    establish_correspondence(meshes, reference=0, n_jobs=1, **extra)
    out["correspond " + label] = [time.perf_counter() - t0]
print("RESULT " + json.dumps(out))
"""


def _export_tree(commit: str, into: Path) -> Path:
    tree = into / commit
    tree.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "core", "resources/make_demo.py"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    return tree


def _inputs(path: Path, n_fits: int = 30) -> Path:
    from app.demo import demo_model
    from core.datasets.shapes import known_homology_shapes
    from core.io import load_model

    model = load_model(demo_model())
    rng = np.random.default_rng(7)
    points = []
    for _ in range(n_fits):
        coef = rng.standard_normal(model.n_factors) * np.sqrt(model.coef_var)
        surface = model.world_instance(coef) + rng.normal(0, 1.0, 3)
        pick = rng.choice(len(surface), 30, replace=False)
        points.append(surface[pick] + rng.normal(0, 0.3, (30, 3)))
    shapes = known_homology_shapes("bean", 6, seed=301, n_points=(900, 1100))
    arrays = {"points": np.stack(points), "n_fits": n_fits, "n_meshes": len(shapes.meshes)}
    for i, mesh in enumerate(shapes.meshes):
        arrays[f"v{i}"], arrays[f"f{i}"] = mesh.vertices, mesh.faces
    np.savez(path, **arrays)
    return path


def _run(tree: Path, inputs: Path, model: Path, options: dict) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", WORKLOAD, str(inputs), json.dumps(options), str(model)],
                          cwd=tree, env=env, capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"workload failed in {tree}:\n{proc.stderr[-2000:]}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="caedcf2", help="commit before the redesign")
    parser.add_argument("--rounds", type=int, default=2, help="alternations of the two trees")
    args = parser.parse_args()
    from app.demo import demo_model

    same_work = {"groom": False, "refine": 0, "mirror_check": False}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        before = _export_tree(args.before, tmp)
        inputs = _inputs(tmp / "inputs.npz")
        results: dict[str, dict[str, list[float]]] = {"before": {}, "after": {}}
        t0 = time.perf_counter()
        for _ in range(args.rounds):
            for label, tree, options in (("before", before, {"": {}}),
                                         ("after", ROOT, {"": same_work, "defaults": {}})):
                for key, values in _run(tree, inputs, demo_model(), options).items():
                    results[label].setdefault(key, []).extend(values)
        load = os.getloadavg()[0]
    print(f"\nEngine before ({args.before}) and after the redesign, {args.rounds} alternating "
          f"rounds, {time.perf_counter() - t0:.0f} s, load average {load:.1f} on {os.cpu_count()} cores")
    print(f"  {'workload':<46} {'before':>10} {'after':>10} {'after/before':>13}")
    b, a = results["before"], results["after"]
    rows = [("refit gmm-aniso, p50 of cold fits (ms)", "refit gmm-aniso", "refit gmm-aniso", 1000),
            ("refit icp, p50 of cold fits (ms)", "refit icp", "refit icp", 1000),
            ("correspond 6 beans, same work (s)", "correspond ", "correspond ", 1),
            ("correspond 6 beans, current defaults (s)", "correspond ", "correspond defaults", 1)]
    for text, kb, ka, scale in rows:
        vb, va = scale * np.median(b[kb]), scale * np.median(a[ka])
        print(f"  {text:<46} {vb:10.1f} {va:10.1f} {va / vb:13.2f}")
    print("  (same work: grooming, mirror check and groupwise refinement off: the steps the earlier "
          "tree lacks)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
