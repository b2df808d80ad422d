"""Does the correspondence safeguard pick the option with the lower true spread? (issue 27, item 3)

For every known-truth population (``core.datasets.shapes`` kinds in two tessellation styles,
and the families of ``core.datasets.families`` when present: the TUNING ones by default,
``--report`` for the REPORT ones), runs ``establish_correspondence``:

- ``before``: round 2's defaults (every input remeshed, one normal-offsets pass, no safeguard);
- ``after``: the defaults with the safeguard (:mod:`core.correspondence.safeguard`);
- ``r0 remesh`` / ``r0 plain``: reference-based only (``refine=0``), with and without the
  remesh (``r0 plain`` is plain reference-based correspondence);
- ``r1 offsets`` / ``r1 cpd``: one refinement pass from the labelled reference-based result
  with the remesh choice the safeguard kept (the states the safeguard judged);
- ``nogroom cpd``: ``groom=False, refine_deformation="cpd"``.

Per population it prints the safeguard's criterion (leave-one-out generalisation against the
raw inputs, mm) for each option it judged, the options' true spreads (mean distance of
homologous output vertices' material points from their mean, mm), its pick and whether the
pick was the truth's best among the options judged; then the hit rate, and per family the
mean of the populations' mean and p95 spreads for every run. The truth of a decision: the
option that left out the fewest inputs (the mirror check may leave out members of a
two-handed population, and every input here is a genuine member), then the lowest true spread
over the shapes that every option compared kept (a mean over different shapes is no
comparison). The hit rate by the spread alone is printed beside it.

    PYTHONPATH=. python benchmarks/bench_safeguard.py --jobs 2 [--report] [--seeds 2 | --seed-list 4 5]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.correspondence import establish_correspondence  # noqa: E402
from core.datasets.shapes import known_homology_shapes, unevenly_decimated  # noqa: E402

KINDS = ("bean", "tube", "ring")
STYLES = ("uneven", "even")
QUICK = ("bean-uneven", "tube-uneven", "global", "concave", "coarse", "labels_1mm")


def populations(report: bool, seeds, n_shapes: int, only: list[str] | None):
    """(family label, seed, population) of the chosen half, for each seed in ``seeds``."""
    out = []
    if not report:
        for kind in KINDS:
            for style in STYLES:
                label = f"{kind}-{style}"
                for seed in seeds:
                    if only and label not in only:
                        continue
                    if style == "even":
                        pop = known_homology_shapes(kind, n_shapes, seed=100 + seed,
                                                    n_points=(1000, 1600), retessellate=True)
                    else:
                        pop = unevenly_decimated(known_homology_shapes(
                            kind, n_shapes, seed=100 + seed, n_points=(2000, 3000)), seed=seed)
                    out.append((label, seed, pop))
    try:
        from core.datasets import families
    except ImportError:
        return out
    for fam in (families.REPORT if report else families.TUNING):
        for seed in seeds:
            if only and fam not in only:
                continue
            out.append((fam, seed, families.population(fam, n_shapes, 100 + seed)))
    return out


def _spread(pop, result) -> tuple[float, float]:
    s = pop.spread([m.vertices if m is not None else None for m in result.meshes])
    return float(s.mean()), float(np.percentile(s, 95))


def evaluate(pop, n_jobs: int, save: Path | None = None) -> dict:
    """Every run of the module docstring on one population: spreads, the record, the checks;
    with ``save`` (an .npz path), the judged runs' correspondences and the raw inputs, for
    trying other criteria offline."""
    runs: dict = {}
    arrays: dict = {}
    kept_shapes: dict = {}

    def run(label: str, judge: bool = False, **kw):
        t = time.perf_counter()
        res = establish_correspondence(pop.meshes, n_jobs=n_jobs, **kw)
        runs[label] = dict(zip(("mean", "p95"), _spread(pop, res)), seconds=time.perf_counter() - t)
        kept_shapes[label] = [None if m is None else m.vertices for m in res.meshes]
        runs[label]["dropped"] = [k for k, v in enumerate(kept_shapes[label]) if v is None]
        if judge:
            runs[label]["criteria"] = _criteria(pop, res)
            if save is not None:
                key = label.replace(" ", "_")
                arrays[f"{key}_faces"] = res.faces
                for k, m in enumerate(res.meshes):
                    if m is not None:
                        arrays[f"{key}_{k}"] = m.vertices
                arrays[f"{key}_spread"] = pop.spread([m.vertices if m is not None else None
                                                      for m in res.meshes])
        return res

    run("before", groom={"keep_tessellation_above": None}, safeguard=False)  # round 2's defaults
    guarded = run("after")
    run("r0 remesh", True, refine=0, safeguard=False)
    run("r0 plain", True, refine=0, groom={"remesh": False}, safeguard=False)
    stages = {s["stage"]: s for s in guarded.safeguard["stages"]}
    kept_remesh = stages.get("remesh", {}).get("kept", "remesh") == "remesh"
    groom = {} if kept_remesh else {"remesh": False}
    run("r1 offsets", True, groom=groom, labelling=True, safeguard=False)
    run("r1 cpd", True, groom=groom, labelling=True, refine_deformation="cpd", safeguard=False)
    run("nogroom cpd", groom=False, refine_deformation="cpd", safeguard=False)
    checks = []
    base = "r0 remesh" if kept_remesh else "r0 plain"
    if "remesh" in stages:
        st = stages["remesh"]
        options = {"remesh": "r0 remesh", "no remesh": "r0 plain"}
        checks.append(_check("remesh", st["criterion_mm"], _truth(pop, kept_shapes, options),
                             st["kept"]))
    if "refinement" in stages and stages["refinement"]["passes"]:
        p = stages["refinement"]["passes"][0]
        crit = {"none": p["before_mm"], **p["criterion_mm"]}
        options = {"none": base, "normal_offsets": "r1 offsets", "cpd": "r1 cpd"}
        kept = "none" if p["kept"].startswith("none") else p["kept"]
        checks.append(_check("refinement", crit,
                             _truth(pop, kept_shapes, {k: options[k] for k in crit}), kept))
    if save is not None:
        for k, m in enumerate(pop.meshes):
            arrays[f"raw_{k}_v"], arrays[f"raw_{k}_f"] = m.vertices, m.faces
        np.savez_compressed(save, **arrays)
    return {"runs": runs, "checks": checks, "safeguard": guarded.safeguard,
            "offline": _offline(runs, base)}


def _criteria(pop, result) -> dict:
    """Candidate criteria on one run's correspondences (lower is better)."""
    from core.correspondence.reference import compactness
    from core.correspondence.safeguard import loo_generalisation

    ok = [k for k, m in enumerate(result.meshes) if m is not None]  # a shape may be dropped
    shapes = [result.meshes[k].vertices for k in ok]
    loo = loo_generalisation(shapes, result.faces, [pop.meshes[k] for k in ok])
    return {"point+raw": loo["value"], "surface": loo["surface_mm"],
            "compactness": compactness(np.stack(shapes))}


def _offline(runs: dict, base: str) -> dict:
    """Per candidate criterion: was its remesh pick, and its refinement pick (the
    safeguard's rule, :func:`core.correspondence.safeguard.refinement_choice`), the truth's
    best? (The refinement from the remesh choice the run's safeguard kept; the truth here is
    each run's mean over its own kept shapes, not :func:`_truth`'s common ones.)"""
    from core.correspondence.safeguard import KEEP_MARGIN, refinement_choice

    keep = 1.0 - KEEP_MARGIN
    out = {}
    for name in runs["r0 plain"]["criteria"]:
        c = {k: runs[k]["criteria"][name] for k in ("r0 remesh", "r0 plain", "r1 offsets", "r1 cpd")}
        t = {k: runs[k]["mean"] for k in c}
        rem = "r0 remesh" if c["r0 remesh"] < keep * c["r0 plain"] else "r0 plain"
        kept = refinement_choice(c[base], {"normal_offsets": c["r1 offsets"], "cpd": c["r1 cpd"]},
                                 "normal_offsets")
        pick = {None: base, "normal_offsets": "r1 offsets", "cpd": "r1 cpd"}[kept]
        # the pick is right when no option is truly lower: identical runs (nothing to remesh)
        # tie, and until 2026-12-07 such a tie counted as a miss whichever label came first
        out[name] = {"remesh": t[rem] <= min(t["r0 remesh"], t["r0 plain"]),
                     "refinement": t[pick] <= min(t[base], t["r1 offsets"], t["r1 cpd"])}
    return out


TIE = 0.03  # options whose true spreads differ by less than this share: a tie, either is right


def _truth(pop, kept_shapes: dict, options: dict) -> dict:
    """Per option of one decision (option -> run label): the true spread over the shapes
    that every option compared kept (the mirror check may leave out different members of a
    two-handed population in different runs, and a mean over different shapes is no
    comparison), and how many genuine members the option's run left out (every input of
    these populations is one). ``kept_shapes``: run label -> per input, its corresponded
    vertices or None where the run left it out."""
    dropped = {o: {k for k, v in enumerate(kept_shapes[label]) if v is None}
               for o, label in options.items()}
    common = set(range(len(pop.meshes))) - set().union(*dropped.values())
    out = {}
    for o, label in options.items():
        shapes = [v if k in common else None for k, v in enumerate(kept_shapes[label])]
        out[o] = {"mean": float(pop.spread(shapes).mean()), "dropped": len(dropped[o]),
                  "common": len(common)}
    return out


def _check(stage: str, criterion: dict, truth: dict, kept: str) -> dict:
    """One decision against the truth: ``right`` when the kept option has the lowest true
    spread over the shapes all options kept, with the fewest genuine members left out
    first (``right_spread_only``: by the spread alone, as until 2026-12-07)."""
    spread = {o: t["mean"] for o, t in truth.items()}
    order = {o: (t["dropped"], t["mean"]) for o, t in truth.items()}
    best = min(order, key=order.get)
    fewest = min(t["dropped"] for t in truth.values())
    tie = truth[kept]["dropped"] == fewest and spread[kept] <= (1.0 + TIE) * min(
        spread[o] for o, t in truth.items() if t["dropped"] == fewest)
    return {"stage": stage, "criterion_mm": criterion, "truth_mm": spread,
            "dropped": {o: t["dropped"] for o, t in truth.items()},
            "common_shapes": next(iter(truth.values()))["common"], "kept": kept, "best": best,
            # identical options (nothing to remesh: the same run) are both right
            "right": bool(order[kept] <= order[best]),
            "right_spread_only": bool(spread[kept] <= min(spread.values())),
            "within_tie": bool(tie)}


RUNS = ("before", "after", "r0 plain", "r0 remesh", "r1 offsets", "r1 cpd", "nogroom cpd")


def wilson_interval(hits: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a hit rate (95 % for z = 1.96)."""
    if n == 0:
        return 0.0, 1.0
    p, z2 = hits / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return float(centre - half), float(centre + half)


def summary(results: list[dict]) -> None:
    checks = [c for r in results for c in r["checks"]]
    hits = sum(c["right"] for c in checks)
    lo, hi = wilson_interval(hits, len(checks))
    print(f"\nsafeguard hit rate: {hits}/{len(checks)} decisions "
          f"({100 * hits / max(len(checks), 1):.0f} %; Wilson 95 % interval {100 * lo:.0f}-"
          f"{100 * hi:.0f} %, the true rates these decisions cannot rule out)")
    spread_only = sum(c["right_spread_only"] for c in checks)
    print(f"by the common shapes' spread alone (dropped members not counted): {spread_only}/"
          f"{len(checks)}")
    near = sum(c["within_tie"] for c in checks)
    print(f"picks within {100 * TIE:.0f} % of the best option's true spread: {near}/{len(checks)}")
    for name in results[0]["offline"] if results else ():
        for stage in ("remesh", "refinement"):
            got = [r["offline"][name][stage] for r in results]
            print(f"offline, criterion {name:12s} {stage:10s}: {sum(got)}/{len(got)} right")
    print("\nper family, mean over populations of the spread mean / p95 (mm):")
    print(f"{'family':18s}" + "".join(f"{r:>18s}" for r in RUNS))
    for fam in dict.fromkeys(r["family"] for r in results):
        rows = [r for r in results if r["family"] == fam]
        cells = [f"{np.mean([x['runs'][k]['mean'] for x in rows]):.3f}/"
                 f"{np.mean([x['runs'][k]['p95'] for x in rows]):.3f}" for k in RUNS]
        a, p = (np.mean([x["runs"]["after"][q] for x in rows]) for q in ("mean", "p95"))
        b, bp = (np.mean([x["runs"]["r0 plain"][q] for x in rows]) for q in ("mean", "p95"))
        flag = "" if a <= 1.05 * b and p <= 1.05 * bp else "   after > 1.05 x r0 plain"
        print(f"{fam:18s}" + "".join(f"{c:>18s}" for c in cells) + flag)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seeds", type=int, default=1, help="populations a family: seeds 0, 1, ...")
    ap.add_argument("--seed-list", type=int, nargs="+", default=None, metavar="S",
                    help="these seeds instead of --seeds")
    ap.add_argument("--shapes", type=int, default=8)
    ap.add_argument("--report", action="store_true", help="the REPORT families (else TUNING)")
    ap.add_argument("--only", nargs="*", help="family labels to run")
    ap.add_argument("--json", type=Path, help="write every result here")
    ap.add_argument("--save", type=Path, help="a folder: each population's judged runs (.npz)")
    args = ap.parse_args()
    results = []
    seeds = args.seed_list if args.seed_list else range(args.seeds)
    for fam, seed, pop in populations(args.report, seeds, args.shapes, args.only):
        save = None
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            save = args.save / f"{fam}_{seed}.npz"
        out = evaluate(pop, args.jobs, save)
        out.update(family=fam, seed=seed)
        results.append(out)
        runs = out["runs"]
        print(f"\n{fam} seed {seed}: " + ", ".join(f"{k} {runs[k]['mean']:.3f}/{runs[k]['p95']:.3f}"
                                               for k in RUNS), flush=True)
        for c in out["checks"]:
            print(f"  {c['stage']:10s} criterion " + ", ".join(f"{k} {v:.4f}" for k, v in
                                                           c["criterion_mm"].items())
                  + " | truth " + ", ".join(f"{k} {v:.3f}" for k, v in c["truth_mm"].items())
                  + f" | kept {c['kept']} | {'right' if c['right'] else 'WRONG'}"
                  + f" | dropped {c['dropped']}, {c['common_shapes']} common shapes", flush=True)
        if args.json:
            args.json.write_text(json.dumps(results, indent=1))
    summary(results)


if __name__ == "__main__":
    main()
