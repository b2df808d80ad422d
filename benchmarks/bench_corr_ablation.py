"""Benchmark: an ablation of the reference-based pair step on the protocol's families (issue 27).

Why is the reference-based step (:func:`core.correspondence.correspond_pair`: multi-start rigid
CPD, nonrigid CPD, bijective labelling by linear assignment, fairing) worse than plain
CPD-then-project on staircase label-map surfaces? Each option below changes ONE thing of the
product's pipeline, in two modes:

- ``refine 0``: ``establish_correspondence(meshes, "auto", refine=0, safeguard=False)``, the
  reference-based step alone;
- ``defaults``: ``establish_correspondence(meshes, "auto")`` as shipped (grooming, the
  safeguard, one refinement pass).

Beside them, in the same run and on the same inputs, the plain peer ``plain rustcpd``
(``correspondence_common.plain_rustcpd``: rustcpd rigid + nonrigid CPD of the raw reference
the ``refine 0`` base chose onto each raw input, then nearest-point projection).

Measure: the spread (mm) of every output vertex's true material points over the shapes
(:meth:`core.datasets.families.FamilyPopulation.spread`), mean and 95th percentile per
population, averaged over the seeds. The protocol's rule: options are chosen on the TUNING
families (default here) with seeds that are not the protocol's (100, 101, 102); the REPORT
families are only for reporting a choice already made.

``--size LO HI``: the populations' vertex-count range instead of each family's own
(``population(..., size=)``), e.g. 4,500-5,500 for dense tuning meshes: every tuning family is
under the CPD subsample's size at its own resolution, so ``cpd_points`` changes nothing there.

Run: ``.venv/bin/python benchmarks/bench_corr_ablation.py [--families F ...] [--seeds 100 101 102]
[--shapes 6] [--size LO HI] [--modes "refine 0" defaults] [--options O ...] [--jobs 1]
[--json OUT]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for _p in (str(ROOT), str(ROOT / "benchmarks")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from core.datasets.families import FAMILIES, TUNING, population  # noqa: E402

MODES = {"refine 0": {"refine": 0, "safeguard": False}, "defaults": {}}
OPTIONS = {  # label: establish_correspondence keywords (one change each)
    "base": {},
    "no labelling (project)": {"labelling": False},
    "no fairing": {"fairing_iterations": 0},
    "fairing 10": {"fairing_iterations": 10},
    "fairing 30": {"fairing_iterations": 30},  # the default until 2026-12-03
    "fairing 60": {"fairing_iterations": 60},
    "fairing 120": {"fairing_iterations": 120},
    "identity start": {"pose_starts": "identity", "mirror_check": False},
    "rigid all points": {"rigid_points": 100000, "rigid_fine_points": 100000},
    "rigid fine all points": {"rigid_fine_points": 100000},  # the chosen start only
    "rigid fine all points 100 it": {"rigid_fine_points": 100000,  # (and 100 for a lone start
                                     "rigid_iterations": 100},      # or the identity re-run)
    "rigid from start all points": {"rigid_fine_from": "start", "rigid_fine_points": 100000},
    "rigid from start": {"rigid_fine_from": "start"},
    "rigid even sampling": {"rigid_sampling": "even", "rigid_fine_sampling": "even"},
    "rigid even fine sampling": {"rigid_fine_sampling": "even"},
    "rigid fine 2000": {"rigid_fine_points": 2000},
    "rigid fine 3000": {"rigid_fine_points": 3000},
    "exact kernel": {"low_rank": None},
    "cpd all points": {"cpd_points": None},
    "cpd 3000 points": {"cpd_points": 3000},  # the default until 2026-12-03 (now 6,000)
    "no remesh": {"groom": {"remesh": False}},
    # mode "defaults" only (they set what "refine 0" sets)
    "two passes": {"refine": 2},
    "cpd pass first": {"refine_deformation": "cpd"},
}
PLAIN = "plain rustcpd"


def _spread(pop, vertices: list) -> tuple[float, float]:
    s = pop.spread(vertices)
    return float(s.mean()), float(np.percentile(s, 95))


def _run(task: tuple) -> tuple:
    """(family, seed, shapes, mode, option, size) -> (family, seed, mode, option, result)."""
    from core.correspondence import establish_correspondence

    family, seed, n_shapes, mode, option, size = task
    pop = population(family, n_shapes, seed, size=size)
    t0 = time.perf_counter()
    res = establish_correspondence(pop.meshes, "auto", n_jobs=1, **MODES[mode], **OPTIONS[option])
    verts = [m.vertices if m is not None else None for m in res.meshes]
    if sum(v is not None for v in verts) < 2:
        return family, seed, mode, option, {"error": str(res.failures)[:200],
                                            "seconds": time.perf_counter() - t0}
    mean, p95 = _spread(pop, verts)  # over the shapes kept (a dropped one is counted)
    out = {"mean": mean, "p95": p95, "seconds": time.perf_counter() - t0,
           "reference": int(res.reference_index), "dropped": sum(v is None for v in verts),
           # what the safeguard tried, its criterion values and what it kept (when on)
           "safeguard": [{k: v for k, v in st.items() if k != "shapes"}
                         for st in (res.safeguard or {}).get("stages", [])]}
    return family, seed, mode, option, out


def _plain(family: str, seed: int, n_shapes: int, ref: int, size: tuple | None) -> dict:
    """The plain peer with the raw input ``ref`` as reference."""
    from correspondence_common import plain_rustcpd

    from core.correspondence import DEFAULT_CPD_PARAMS

    pop = population(family, n_shapes, seed, size=size)
    t0 = time.perf_counter()
    reference = pop.meshes[ref]
    verts = [reference.vertices if k == ref else plain_rustcpd(reference, m, dict(DEFAULT_CPD_PARAMS))
             for k, m in enumerate(pop.meshes)]
    mean, p95 = _spread(pop, verts)
    return {"mean": mean, "p95": p95, "seconds": time.perf_counter() - t0}


def _task(task: tuple) -> list[tuple]:
    """One option's run; the ``refine 0`` base also runs the plain peer with its reference."""
    family, seed, n_shapes, mode, option, size = task
    done = [_run(task)]
    if mode == "refine 0" and option == "base" and "reference" in done[0][4]:
        done.append((family, seed, "", PLAIN,
                     _plain(family, seed, n_shapes, done[0][4]["reference"], size)))
    return done


def run(families: list[str], seeds: list[int], n_shapes: int, modes: list[str], options: list[str],
        jobs: int, progress=print, on_result=None, size: tuple | None = None) -> dict:
    """{(mode, option): {family: {seed: result}}} for every mode, option, family and seed."""
    import multiprocessing as mp

    tasks = [(f, s, n_shapes, m, o, size) for f in families for s in seeds for m in modes
             for o in options]
    if "refine 0" not in modes or "base" not in options:  # the peer needs the refine 0 base
        tasks += [(f, s, n_shapes, "refine 0", "base", size) for f in families for s in seeds]
    results: dict = {}
    t0 = time.perf_counter()

    def absorb(done: list[tuple], i: int) -> None:
        for family, seed, mode, option, out in done:
            results.setdefault((mode, option), {}).setdefault(family, {})[seed] = out
            progress(f"[{i + 1}/{len(tasks)} {time.perf_counter() - t0:6.0f} s] {family} {seed} "
                     f"{mode or '-'} / {option}: {out.get('mean', float('nan')):.3f} / "
                     f"{out.get('p95', float('nan')):.3f} ({out['seconds']:.0f} s)")
        if on_result is not None:
            on_result(results)

    if jobs <= 1:
        for i, task in enumerate(tasks):
            absorb(_task(task), i)
    else:
        with mp.get_context("forkserver").Pool(jobs, maxtasksperchild=4) as pool:
            for i, done in enumerate(pool.imap_unordered(_task, tasks)):
                absorb(done, i)
    return results


def table(results: dict, families: list[str]) -> str:
    """Markdown: a row per (mode, option), a column per family (mean / p95 mm over the seeds,
    and the change of the mean against the mode's base in %)."""
    lines = ["| mode | option | " + " | ".join(families) + " |", "|---" * (len(families) + 2) + "|"]
    for (mode, option), fams in sorted(results.items(), key=lambda kv: (kv[0][0] == "", kv[0][0],
                                                                        list(OPTIONS).index(kv[0][1])
                                                                        if kv[0][1] in OPTIONS else 99)):
        base = results.get((mode, "base"), {})
        cells = []
        for f in families:
            runs = [r for r in fams.get(f, {}).values() if "mean" in r]
            if not runs:
                cells.append("failed" if fams.get(f) else "-")
                continue
            mean, p95 = np.mean([r["mean"] for r in runs]), np.mean([r["p95"] for r in runs])
            base_runs = (results.get(("refine 0", "base"), {}) if mode == "" else base).get(f, {})
            common = [s for s, r in fams.get(f, {}).items() if "mean" in r and "mean" in base_runs.get(s, {})]
            if common:
                change = 100 * (np.mean([fams[f][s]["mean"] for s in common])
                                / np.mean([base_runs[s]["mean"] for s in common]) - 1)
            pct = f" ({change:+.1f} %)" if common else ""
            fail = len(fams.get(f, {})) - len(runs)
            dropped = sum(r.get("dropped", 0) for r in runs)
            cells.append(f"{mean:.3f} / {p95:.3f}{pct}" + (f" {fail} failed" if fail else "")
                         + (f" {dropped} dropped" if dropped else ""))
        lines.append(f"| {mode or '-'} | {option} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def merged(paths: list[Path]) -> dict:
    """The runs of several ``--json`` files together (a later file's run of the same mode,
    option, family and seed wins)."""
    results: dict = {}
    for path in paths:
        for r in json.loads(path.read_text())["runs"]:
            key = (r.pop("mode"), r.pop("option"))
            results.setdefault(key, {}).setdefault(r.pop("family"), {})[r.pop("seed")] = r
    return results


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(TUNING), choices=FAMILIES)
    parser.add_argument("--seeds", nargs="+", type=int, default=[100, 101, 102])
    parser.add_argument("--shapes", type=int, default=6, help="shapes a population")
    parser.add_argument("--size", type=int, nargs=2, default=None, metavar=("LO", "HI"),
                        help="vertex-count range of every shape (default: the family's own)")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--options", nargs="+", default=list(OPTIONS), choices=list(OPTIONS))
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (each run on 1 core)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here (as they come)")
    parser.add_argument("--merge", type=Path, nargs="+", default=None,
                        help="no run: the table of these --json files' runs together")
    args = parser.parse_args(argv)
    if args.merge:
        results = merged(args.merge)
        print(table(results, [f for f in FAMILIES if any(f in v for v in results.values())]))
        return
    for name in ("OMP_NUM_THREADS", "RAYON_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(name, "1")  # each job on one core
    t0 = time.perf_counter()

    def dump(results: dict) -> None:
        if args.json:
            args.json.write_text(json.dumps({"seeds": args.seeds, "shapes": args.shapes,
                                             "size": args.size, "runs": [
                {"mode": m, "option": o, "family": f, "seed": s, **r}
                for (m, o), fams in results.items() for f, seeds in fams.items()
                for s, r in seeds.items()]}, indent=1))

    results = run(args.families, args.seeds, args.shapes, args.modes, args.options, args.jobs,
                  progress=lambda s: print(s, flush=True), on_result=dump,
                  size=tuple(args.size) if args.size else None)
    print(f"\nseeds {args.seeds}, {args.shapes} shapes each"
          f"{f', {args.size[0]}-{args.size[1]} vertices' if args.size else ''}, {args.jobs} jobs, "
          f"{time.perf_counter() - t0:.0f} s; spread mean / p95 (mm) averaged over the seeds "
          f"(the mean's change against the mode's base; the peer against refine 0's base)\n")
    print(table(results, args.families))


if __name__ == "__main__":
    main()
