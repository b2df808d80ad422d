"""Benchmark: the correspondence validation protocol of issue 27 (item 2).

Every family of :mod:`core.datasets.families` (known-truth populations from 8 different
generators, in a TUNING and a REPORT half fixed before any number was looked at), several
populations a family, and on each the same inputs corresponded by every option side by side in
ONE run:

- ``defaults``: ``establish_correspondence(meshes, "auto")`` as the product ships it (grooming
  with the remesh to a common vertex count, 1 refinement pass, normal offsets);
- ``refine 0``, ``no-remesh`` (``groom={"remesh": False}``), ``no-remesh, refine 0`` and
  ``no-groom, cpd`` (``groom=False, refine_deformation="cpd"``): the CLI's
  ``--refine 0``, ``--no-remesh``, ``--no-remesh --refine 0``, ``--no-groom
  --refine-deformation cpd``;
- ``plain rustcpd``: the plain peer, rustcpd rigid + nonrigid CPD of the reference onto each
  raw input then nearest-point projection (``bench_correspondence.plain_rustcpd``), with the
  raw input the defaults chose as reference (``--reference auto``);
- ``round 1``: round 1's pipeline (``git archive caedcf2``, extracted to a temporary folder and
  run there in a subprocess with its own ``core`` on PYTHONPATH), its defaults and
  ``reference="auto"`` (3 candidates by compactness).

Measure: the spread (mm) of every output vertex's material points over the shapes around
their mean (:func:`core.datasets.shapes.homology_spread`), mean and 95th percentile per
population, averaged over a family's populations. The rule: defaults are chosen on the tuning
half only and reported on the report half.

Run: ``.venv/bin/python benchmarks/bench_protocol.py [--families F ...] [--populations 3]
[--first-seed 0] [--shapes 7] [--jobs 2] [--json OUT]``; ``--merge A.json B.json``: the
tables of several runs' populations together.
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
for _p in (str(ROOT), str(ROOT / "benchmarks")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from core.datasets.families import FAMILIES, REPORT, TUNING, population  # noqa: E402

ROUND1 = "caedcf2"
OPTIONS = {  # label: establish_correspondence keywords
    "defaults": {},
    "refine 0": {"refine": 0},
    "no-remesh": {"groom": {"remesh": False}},
    "no-remesh, refine 0": {"groom": {"remesh": False}, "refine": 0},
    "no-groom, cpd": {"groom": False, "refine_deformation": "cpd"},
}
PEERS = ("plain rustcpd", "round 1")
COLUMNS = (*OPTIONS, *PEERS)

ROUND1_SCRIPT = """
import sys, numpy as np
from core.correspondence import establish_correspondence
from core.io import TriMesh
data = np.load(sys.argv[1])
meshes = [TriMesh(data[f"v{k}"], data[f"f{k}"], f"s{k}") for k in range(int(data["n"]))]
res = establish_correspondence(meshes, "auto", n_jobs=1)
out = {f"v{k}": m.vertices for k, m in enumerate(res.meshes) if m is not None}
np.savez(sys.argv[2], **out)
"""


def _spread(pop, vertices: list) -> dict:
    """Spread mean and p95 (mm), shapes dropped, and per shape the mean distance (mm) of its
    material points from the per-vertex median over the shapes (a flipped shape stands out)."""
    from core.datasets.shapes import homology_spread, material_points

    material = [material_points(v, pop.meshes[k], pop.material[k])
                for k, v in enumerate(vertices) if v is not None]
    s = homology_spread(material)
    median = np.median(np.stack(material), axis=0)
    return {"mean": float(s.mean()), "p95": float(np.percentile(s, 95)),
            "dropped": int(sum(v is None for v in vertices)),
            "per_shape": [round(float(np.linalg.norm(m - median, axis=1).mean()), 3) for m in material]}


def _kept(record: dict) -> dict:
    """What the safeguard kept at each stage (``correspondence.json``'s record, abridged)."""
    kept = {}
    for stage in record.get("stages", []):
        if stage["stage"] == "refinement":
            kept["refinement"] = [p["kept"] for p in stage.get("passes", [])]
        else:
            kept[stage["stage"]] = stage.get("kept")
    return kept


def _ours_and_plain(family: str, seed: int, n_shapes: int) -> dict:
    """The defaults, then the plain peer with the defaults' (raw) reference."""
    from bench_correspondence import plain_rustcpd

    from core.correspondence import DEFAULT_CPD_PARAMS, establish_correspondence

    pop = population(family, n_shapes, seed)
    t0 = time.perf_counter()
    res = establish_correspondence(pop.meshes, "auto", n_jobs=1)
    out = {"defaults": {**_spread(pop, [m.vertices if m is not None else None for m in res.meshes]),
                        "seconds": time.perf_counter() - t0,
                        "safeguard_kept": _kept(res.safeguard)}}
    ref = res.reference_index
    reference = pop.meshes[ref]
    t0 = time.perf_counter()
    verts = [reference.vertices if k == ref else plain_rustcpd(reference, m, dict(DEFAULT_CPD_PARAMS))
             for k, m in enumerate(pop.meshes)]
    out["plain rustcpd"] = {**_spread(pop, verts), "seconds": time.perf_counter() - t0}
    return out


def _option(family: str, seed: int, n_shapes: int, label: str) -> dict:
    from core.correspondence import establish_correspondence

    pop = population(family, n_shapes, seed)
    t0 = time.perf_counter()
    res = establish_correspondence(pop.meshes, "auto", n_jobs=1, **OPTIONS[label])
    verts = [m.vertices if m is not None else None for m in res.meshes]
    return {label: {**_spread(pop, verts), "seconds": time.perf_counter() - t0}}


def _round1(family: str, seed: int, n_shapes: int, folder: str) -> dict:
    """Round 1's establish_correspondence (its own code) in a subprocess."""
    pop = population(family, n_shapes, seed)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        arrays = {"n": len(pop.meshes)}
        for k, m in enumerate(pop.meshes):
            arrays[f"v{k}"], arrays[f"f{k}"] = m.vertices, m.faces
        np.savez(src, **arrays)
        env = {**os.environ, "PYTHONPATH": folder, "OMP_NUM_THREADS": "1"}
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", ROUND1_SCRIPT, src, dst], cwd=folder, env=env,
                              capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        if done.returncode != 0:
            return {"round 1": {"error": done.stderr.strip().splitlines()[-1:], "seconds": seconds}}
        data = np.load(dst)
        verts = [data[f"v{k}"] if f"v{k}" in data else None for k in range(len(pop.meshes))]
    return {"round 1": {**_spread(pop, verts), "seconds": seconds}}


def _task(task: tuple) -> tuple:
    kind, family, seed, n_shapes, extra = task
    if kind == "defaults":
        out = _ours_and_plain(family, seed, n_shapes)
    elif kind == "round 1":
        out = _round1(family, seed, n_shapes, extra)
    else:
        out = _option(family, seed, n_shapes, kind)
    return family, seed, out


def extract_round1(folder: str) -> None:
    """Round 1's tree (``git archive`` of :data:`ROUND1`) into ``folder``."""
    archive = subprocess.run(["git", "archive", ROUND1], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", folder], input=archive.stdout, check=True)


def run(families: list[str], n_populations: int, n_shapes: int, jobs: int, folder: str,
        progress=print, on_result=None, first_seed: int = 0, kinds: list[str] | None = None) -> dict:
    """Every option on every population: {family: {seed: {option: result}}};
    ``on_result(results)`` after each finished run (the JSON is written as the run goes)."""
    import multiprocessing as mp

    seeds = range(first_seed, first_seed + n_populations)
    tasks = [(kind, family, seed, n_shapes, folder if kind == "round 1" else None)
             for family in families for seed in seeds
             for kind in (kinds or ("defaults", "round 1", *[o for o in OPTIONS if o != "defaults"]))]
    results: dict = {f: {s: {} for s in seeds} for f in families}
    t0 = time.perf_counter()
    with mp.get_context("forkserver").Pool(jobs, maxtasksperchild=4) as pool:
        for i, (family, seed, out) in enumerate(pool.imap_unordered(_task, tasks)):
            results[family][seed].update(out)
            progress(f"[{i + 1}/{len(tasks)} {time.perf_counter() - t0:6.0f} s] {family} seed {seed}: "
                     + ", ".join(f"{k} {v.get('mean', float('nan')):.3f}" for k, v in out.items()))
            if on_result is not None:
                on_result(results)
    return results


def summarise(results: dict) -> dict:
    """Per family and option: spread mean and p95 averaged over the populations, the number
    of dropped shapes and of failed runs, and the option with the lowest mean (p95 breaks ties)."""
    summary = {}
    for family, pops in results.items():
        row = {}
        for col in COLUMNS:
            runs = [p[col] for p in pops.values() if col in p and "mean" in p[col]]
            row[col] = {"mean": float(np.mean([r["mean"] for r in runs])) if runs else None,
                        "p95": float(np.mean([r["p95"] for r in runs])) if runs else None,
                        "dropped": int(sum(r["dropped"] for r in runs)),
                        "failed": int(sum(1 for p in pops.values() if col in p and "mean" not in p[col])),
                        "populations": len(runs),
                        "seconds": float(np.mean([p[col]["seconds"] for p in pops.values() if col in p]
                                                 or [np.nan]))}
        ranked = sorted((c for c in COLUMNS if row[c]["mean"] is not None),
                        key=lambda c: (round(row[c]["mean"], 3), row[c]["p95"]))
        summary[family] = {"options": row, "winner": ranked[0] if ranked else None,
                           "best_product_option": next((c for c in ranked if c in OPTIONS), None),
                           "half": "tuning" if family in TUNING else "report"}
    return summary


def table(summary: dict, half: tuple, title: str) -> str:
    """A markdown table: family rows, option columns (mean / p95 mm), the winner."""
    fams = [f for f in half if f in summary]
    if not fams:
        return ""
    lines = [f"{title}", "", "| family | " + " | ".join(COLUMNS) + " | best |",
             "|---" * (len(COLUMNS) + 2) + "|"]
    for f in fams:
        row = summary[f]["options"]
        cells = [f"{row[c]['mean']:.3f} / {row[c]['p95']:.3f}" + ("*" if row[c]["dropped"] else "")
                 if row[c]["mean"] is not None else ("failed" if row[c]["failed"] else "-")
                 for c in COLUMNS]
        lines.append(f"| {f} | " + " | ".join(cells) + f" | {summary[f]['winner']} |")
    return "\n".join(lines) + "\n"


def report(summary: dict, header: str) -> None:
    """The two tables and each family's best option, printed."""
    print(header)
    print(table(summary, TUNING, "TUNING half (defaults may be chosen on these)"))
    print(table(summary, REPORT, "REPORT half (reported, never tuned on)"))
    for half in (TUNING, REPORT):
        for f in half:
            if f in summary:
                print(f"{f}: best overall {summary[f]['winner']}, best product option "
                      f"{summary[f]['best_product_option']}")


def merged(paths: list[Path]) -> dict:
    """The runs of several ``--json`` files together, population by population (family and
    seed): different ``--first-seed`` add populations; a later file's run of an option on the
    same population replaces an earlier one's (e.g. the defaults re-run after a change, beside
    round 1's unchanged code), and a family missing from a file keeps what it had."""
    results: dict = {}
    for path in paths:
        for family, pops in json.loads(path.read_text())["runs"].items():
            for seed, out in pops.items():
                key = str(seed).rsplit(":", 1)[-1]  # merged files name theirs "file:seed"
                results.setdefault(family, {}).setdefault(key, {}).update(out)
    return results


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    parser.add_argument("--populations", type=int, default=3, help="populations a family")
    parser.add_argument("--first-seed", type=int, default=0, help="seeds first-seed, first-seed + 1, ...")
    parser.add_argument("--shapes", type=int, default=7, help="shapes a population")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (each run on 1 core)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here (as they come)")
    parser.add_argument("--runs", nargs="+", default=None, choices=("round 1", *OPTIONS),
                        help="only these runs (\"defaults\" includes plain rustcpd)")
    parser.add_argument("--merge", type=Path, nargs="+", default=None,
                        help="no run: the tables of these --json files' runs together")
    args = parser.parse_args(argv)
    if args.merge:
        report(summarise(merged(args.merge)), f"merged: {', '.join(str(p) for p in args.merge)}\n")
        return
    for name in ("OMP_NUM_THREADS", "RAYON_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(name, "1")  # each job on one core
    t0 = time.perf_counter()

    def dump(results: dict) -> None:
        if args.json:
            args.json.write_text(json.dumps({
                "populations": args.populations, "shapes": args.shapes, "tuning": TUNING,
                "report": REPORT, "summary": summarise(results),
                "runs": {f: {str(s): v for s, v in p.items()} for f, p in results.items()}}, indent=1))

    with tempfile.TemporaryDirectory(prefix="round1_") as folder:
        extract_round1(folder)
        results = run(args.families, args.populations, args.shapes, args.jobs, folder,
                      progress=lambda s: print(s, flush=True), on_result=dump,
                      first_seed=args.first_seed, kinds=args.runs)
    report(summarise(results),
           f"\n{args.populations} populations a family, {args.shapes} shapes each, {args.jobs} jobs, "
           f"{time.perf_counter() - t0:.0f} s, load {', '.join(f'{x:.2f}' for x in os.getloadavg())}; "
           f"spread mean / p95 (mm), averaged over populations; * a shape dropped\n")

if __name__ == "__main__":
    main()
