"""Benchmark: start-up and per-job overhead of the local process pool (issue 30 item 3).

:func:`core.runtime.parallel.run_jobs` with ``n_jobs=2`` on ``--jobs`` (200) short jobs (a
1-2 ms numpy eigenvalue problem each, ``common`` a small array sent through the initialiser),
in a module that imports :mod:`core.correspondence.batch` (the real job module's imports:
numpy, scipy, VTK). Three pools, each measured in a fresh Python process (a "session") that
runs ``--pools`` (3) pools one after the other, as a command does (reading, grooming,
correspondence, residuals):

- ``loky+forkserver``: today's tree: loky's ProcessPoolExecutor on workers forked from the
  standard library's fork server, which has the job modules preloaded;
- ``stdlib+forkserver``: the tree at ``--baseline`` (f5bd7f0: concurrent.futures'
  ProcessPoolExecutor with the same fork server and a hand-written teardown), exported
  with ``git archive``;
- ``loky context``: today's tree with the start method switched to loky's default context
  (every worker a new interpreter that imports the job modules itself, for every pool).

Reported per pool of a session: the time to the first result (start-up: fork server,
workers, imports), the wall time of all jobs, and the wall time per job after the first
result (2 workers: half a job's compute is the floor), beside the job's time in this process.
The sessions alternate (A, B, C, A, B, C, ...) for ``--rounds`` (2) so that a change of the
machine's load hits all alike; the median over rounds is printed. The outputs of all three
are checked equal to the in-process results.

Run: ``.venv/bin/python benchmarks/bench_pool.py [--jobs 200] [--pools 3] [--rounds 2]``
(about a minute on 2 quiet cores). The machine is shared: times are upper bounds.
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


def short_job(arg: int, common: np.ndarray) -> float:
    """A 20x20 symmetric eigenvalue problem: ~1-2 ms of numpy."""
    rng = np.random.default_rng(arg)
    m = rng.normal(size=(20, 20)) + common
    return float(np.linalg.eigvalsh(m @ m.T).sum())


def session(mode: str, n_items: int, n_pools: int) -> dict:
    """One fresh process: ``n_pools`` runs of the jobs; timings and results as JSON."""
    import core.correspondence.batch  # noqa: F401  (the job module's imports, preloaded)
    from core.runtime.parallel import run_jobs

    if mode == "loky context":
        from loky.backend import get_context

        from core.runtime import pool

        pool._pool_context = lambda fn: get_context("loky")
    common = np.full((20, 20), 0.25)
    items = [(i, i) for i in range(n_items)]
    t0 = time.perf_counter()
    inline = [short_job(i, common) for i in range(n_items)]
    inline_ms = 1000 * (time.perf_counter() - t0) / n_items
    pools = []
    for _ in range(n_pools):
        first: list[float] = []
        start = time.perf_counter()
        results = run_jobs(short_job, items, common=common, n_jobs=2,
                           on_result=lambda k, v, first=first: first.append(time.perf_counter()) or v)
        wall = time.perf_counter() - start
        pools.append({"startup": first[0] - start, "wall": wall,
                      "per_job_ms": 1000 * (first[-1] - first[0]) / (n_items - 1),
                      "equal": [results[i] for i in range(n_items)] == inline})
    return {"inline_ms": inline_ms, "pools": pools}


def _run_session(mode: str, tree: Path, n_items: int, n_pools: int) -> dict:
    code = (f"import json, bench_pool; print(json.dumps(bench_pool.session({mode!r}, "
            f"{n_items}, {n_pools})))")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), str(ROOT / "benchmarks")]))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True, timeout=600)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=200)
    parser.add_argument("--pools", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--baseline", default="f5bd7f0")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline"
        base.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.baseline, "core"],
                                 capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
        modes = {"loky+forkserver": ROOT, "stdlib+forkserver": base, "loky context": ROOT}
        runs: dict[str, list[dict]] = {m: [] for m in modes}
        print(f"load before: {os.getloadavg()[0]:.2f}")
        for _ in range(args.rounds):
            for mode, tree in modes.items():
                runs[mode].append(_run_session(mode, tree, args.jobs, args.pools))
        print(f"load after: {os.getloadavg()[0]:.2f}")
    print(f"\n{args.jobs} short jobs, n_jobs=2, median of {args.rounds} sessions each")
    header = (f"{'pool':<20}{'#':>3}{'start-up s':>12}{'wall s':>9}{'ms/job':>9}"
              f"{'inline ms/job':>15}{'equal':>7}")
    print(header)
    print("-" * len(header))
    for mode, sessions in runs.items():
        inline = np.median([s["inline_ms"] for s in sessions])
        for k in range(args.pools):
            per = [s["pools"][k] for s in sessions]
            print(f"{mode:<20}{k + 1:>3}{np.median([p['startup'] for p in per]):>12.3f}"
                  f"{np.median([p['wall'] for p in per]):>9.3f}"
                  f"{np.median([p['per_job_ms'] for p in per]):>9.2f}{inline:>15.2f}"
                  f"{all(p['equal'] for p in per)!s:>7}")


if __name__ == "__main__":
    main()
