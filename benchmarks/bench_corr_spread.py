"""Benchmark: how well SSM Studio's correspondences find the true homologues, and what limits it.

On known-homology populations (:mod:`core.datasets.shapes`: bean, tube, ring; ``--population``
bumps or features), the spread of the corresponded points' material points around their
mean (mm; 0 is perfect). Tables:

- ``spread``: plain rustcpd CPD-then-project (raw and groomed inputs) vs SSM Studio refine 0
  and 1, the gain and the assignment's share (:func:`spread_table`);
- ``limits``: how far the surfaces alone determine the homologies, with the exact bump-free
  base surface as the template (:func:`limits_table`);
- ``diagnostics``: why the groupwise refinement does not get further (:func:`diagnostics_table`);
- ``model``: each shape fitted by the PCA model of the others (:func:`model_fit_table`).

Held-out seeds 100+ unless ``--tuning`` (seeds 2+, where parameter choices were made).

Run: ``.venv/bin/python benchmarks/bench_corr_spread.py [--only spread|limits|diagnostics|model]
[--spread-shapes 8] [--spread-seeds 1] [--population bumps|features] [--param NAME=VALUE]
[--jobs 2] [--tuning]`` (also ``bench_correspondence.py --only ...``; the default runs
``spread`` and ``limits``).
"""

from __future__ import annotations

import argparse

import numpy as np
from correspondence_common import (
    POPULATIONS,
    groomed_meshes,
    load_averages,
    normalised,
    plain_batch,
    populations,
    true_points,
)

from core.io import TriMesh

TABLES = ("spread", "limits", "diagnostics", "model")


def _title(what: str, n_shapes: int, vertices: int, seed: int, repeats: int = 1,
           population: str = "bumps") -> None:
    per = f"{n_shapes} shapes per population, {repeats} populations per kind" if repeats > 1 \
        else f"{n_shapes} shapes per kind"
    print(f"\n{what}; {population} population, {per}, ~{vertices} vertices; "
          f"{'held-out' if seed >= 100 else 'TUNING'} seeds {seed}-{seed + 3 * repeats - 1}; "
          f"load {load_averages()}")


def spread_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 100,
                 repeats: int = 1, population: str = "bumps", params: dict | None = None) -> None:
    """Spread of corresponded points around their true material points, per shape kind.

    The generator's own tessellations sample every shape with the same density per unit of
    the material parameter (a cue that CPD's density matching uses and real meshes do not
    have); grooming remeshes uneven inputs (the tubes) to an even density. So plain CPD is run
    twice: on the raw meshes, and on the same groomed meshes ours gets; both with ours'
    chosen reference (groomed). Held-out seeds 100+ (reported); ``--tuning`` runs the same
    table on tuning seeds 2+ (what parameter choices were made on). With ``repeats`` R
    (``--spread-seeds``), R independent populations a kind: the columns are the means over
    them, the gain is that of the means, and each population's own gain is listed (with 6
    shapes a population, one population's gain moves by +-10 points from seed to seed).
    """
    from core.correspondence import DEFAULT_CPD_PARAMS, establish_correspondence

    _title("spread vs truth (mean distance of homologous points' material points from their "
           "mean, mm)" + (f"; SSM Studio with {params}" if params else ""),
           n_shapes, vertices, seed, repeats, population)
    print(f"{'kind':<6}{'plain raw':>11}{'plain groomed':>15}{'ours refine 0':>15}{'ours refine 1':>15}"
          f"{'gain vs best plain':>20}{'assign % of pair':>18}{'dropped':>9}"
          + ("   gain per population" if repeats > 1 else ""))
    rows: dict[str, list] = {}
    for kind, pop in populations(n_shapes, vertices, seed, repeats, population):
        outputs, dropped = {}, set()
        for refine in (0, 1):
            res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=refine,
                                           vertices=vertices, **(params or {}))
            outputs[refine] = [m.vertices if m is not None else None for m in res.meshes]
            dropped |= {k for k, m in enumerate(res.meshes) if m is None}
            share = 100 * res.timings["assignment_total"] / max(res.timings["cpu_total"], 1e-9)
            if refine == 0:
                ref = res.reference_index
                reference = res.meshes[ref]  # the groomed reference
        groomed = groomed_meshes(pop.meshes, vertices)
        plain = {}
        for label, inputs in (("raw", pop.meshes), ("groomed", groomed)):
            others = [m for k, m in enumerate(inputs) if k != ref]
            out, _ = plain_batch(reference, others, dict(DEFAULT_CPD_PARAMS), jobs)
            it = iter(out)
            plain[label] = [reference.vertices if k == ref else next(it) for k in range(n_shapes)]
        # Every column over the same shapes: a shape ours dropped (flagged as bad input) is
        # left out of the plain columns too, and counted.
        spreads = {key: pop.spread([v if k not in dropped else None for k, v in enumerate(vs)]).mean()
                   for key, vs in [*outputs.items(), *plain.items()]}
        rows.setdefault(kind, []).append((spreads, share, len(dropped)))
        if len(rows[kind]) < repeats:
            continue
        mean = {key: float(np.mean([r[0][key] for r in rows[kind]])) for key in spreads}
        gains = [100 * (1 - r[0][1] / min(r[0]["raw"], r[0]["groomed"])) for r in rows[kind]]
        best = min(mean["raw"], mean["groomed"])
        print(f"{kind:<6}{mean['raw']:>11.3f}{mean['groomed']:>15.3f}"
              f"{mean[0]:>15.3f}{mean[1]:>15.3f}"
              f"{100 * (1 - mean[1] / best):>19.0f}%{np.mean([r[1] for r in rows[kind]]):>18.1f}"
              f"{sum(r[2] for r in rows[kind]):>9}"
              + ("   " + " / ".join(f"{g:.0f}%" for g in gains) if repeats > 1 else ""))


def _base_template(pop, vertices: int) -> TriMesh:
    """The exact bump-free base surface, remeshed as grooming remeshes every input: a
    template that differs from the one ours and plain CPD get only in being exact. (Until
    2026-12-02 it was the base at shape 0's own lattice, a different kind of mesh: its
    density follows the material parameter, and CPD matches densities.)"""
    from core.correspondence.grooming import remesh

    v, f = remesh(pop.material[0], pop.meshes[0].faces, vertices)
    return TriMesh(v, f, "base")


def diagnostics_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 2,
                      population: str = "bumps") -> None:
    """Why the groupwise refinement does not get further (the README's "what limits it";
    run on the tuning seeds). Per kind, spread (mm) unless said:

    - ours with 1, 2 and 3 refinement passes;
    - the total variance (mm^2) after similarity GPA of ours' correspondences and of the true
      ones (the true homologues of ours' consensus material points): the truth less compact
      than ours means a compactness (MDL, entropy) criterion moves away from it;
    - one more pass against the mean, against each of the other shapes (as templates) with
      the results averaged: equal spreads mean the error belongs to the shape;
    - the affine map fitted to ours' correspondence, then projection;
    - groupwise sliding (the trace-minimising step): the mean of the similarity GPA posed on
      every shape and projected onto it, after 1 and 6 iterations;
    - rings: nonrigid CPD of the exact base surface from the true similarity pose turned
      about the ring's axis by 10, 20 and 30 degrees: the mean distance (mm) of its points
      from their true homologues.
    """
    from core.alignment.transforms import apply_transform, fit_transform, generalized_procrustes
    from core.correspondence import DEFAULT_CPD_PARAMS, correspond_pair, establish_correspondence
    from core.datasets.shapes import material_points
    from core.geometry.toolkit import SurfaceProjector, rodrigues

    def variance(shapes: list) -> float:
        gpa = generalized_procrustes(np.stack(shapes), "similarity", max_iter=50, tol=1e-8)
        return float(((gpa.aligned - gpa.mean) ** 2).sum(axis=2).sum(axis=1).mean())

    _title("what limits the groupwise refinement (diagnostics)", n_shapes, vertices, seed,
           population=population)
    print(f"{'kind':<6}{'refine 1 / 2 / 3':>22}{'GPA var ours / truth':>24}{'to mean / others avg':>23}"
          f"{'affine fit+proj':>17}{'sliding it 1 / 6':>18}")
    one_pass = dict(DEFAULT_CPD_PARAMS, max_iterations=DEFAULT_CPD_PARAMS["refine_iterations"],
                    pair_residual=False)
    for kind, pop in populations(n_shapes, vertices, seed, population=population):
        refined = {}
        for passes in (1, 2, 3):
            res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=passes,
                                           vertices=vertices)
            refined[passes] = pop.spread([m.vertices for m in res.meshes]).mean()
            if passes == 1:
                ours, faces = [m.vertices for m in res.meshes], res.faces
        groomed = groomed_meshes(pop.meshes, vertices)
        project = [SurfaceProjector(g.vertices, g.faces) for g in groomed]
        consensus = np.mean([material_points(v, pop.meshes[k], pop.material[k])
                             for k, v in enumerate(ours)], axis=0)
        truth = [true_points(pop, k, consensus) for k in range(len(ours))]
        mean = generalized_procrustes(np.stack(ours), "similarity", max_iter=20, tol=1e-6).mean
        to_mean, averaged, affine = [], [], []
        for k, current in enumerate(ours):
            def posed(template: np.ndarray, how: str = "similarity") -> np.ndarray:
                return apply_transform(fit_transform(template, current, how), template)
            to_mean.append(correspond_pair(TriMesh(mean, faces), groomed[k], one_pass,
                                           posed=posed(mean))["vertices"])
            others = [correspond_pair(TriMesh(ours[j], faces), groomed[k], one_pass,
                                      posed=posed(ours[j]))["vertices"]
                      for j in range(len(ours)) if j != k]
            averaged.append(project[k](np.mean(others, axis=0))[0])
            affine.append(project[k](posed(mean, "affine"))[0])
        sliding, slid = [], list(ours)
        for _ in range(6):
            mean_now = generalized_procrustes(np.stack(slid), "similarity", max_iter=20, tol=1e-6).mean
            slid = [project[k](apply_transform(fit_transform(mean_now, v, "similarity"), mean_now))[0]
                    for k, v in enumerate(slid)]
            sliding.append(pop.spread(slid).mean())
        print(f"{kind:<6}{refined[1]:>10.3f} / {refined[2]:.3f} / {refined[3]:.3f}"
              f"{variance(ours):>14.0f} / {variance(truth):<7.0f}"
              f"{pop.spread(to_mean).mean():>14.3f} / {pop.spread(averaged).mean():<6.3f}"
              f"{pop.spread(affine).mean():>17.3f}{sliding[0]:>11.3f} / {sliding[-1]:.3f}")
        if kind == "ring":  # the base ring's axis is z; turned about it, in the base frame
            template = _base_template(pop, vertices)
            ends = []
            for degrees in (0, 10, 20, 30):
                turn = rodrigues(np.deg2rad(degrees) * np.array([0.0, 0.0, 1.0]))
                outs = []
                for k in range(len(ours)):
                    start = template.vertices @ turn.T
                    true = true_points(pop, k, template.vertices)
                    pose = apply_transform(fit_transform(template.vertices, true, "similarity"), start)
                    outs.append(correspond_pair(template, groomed[k], dict(DEFAULT_CPD_PARAMS,
                                                labelling=False, pair_residual=False),
                                                posed=pose)["vertices"])
                    outs.append(np.linalg.norm(outs.pop() - true, axis=1).mean())
                ends.append(float(np.mean(outs)))
            # (not the spread: a turn shared by every shape would cancel in it)
            print("      ring, nonrigid CPD of the exact base from the true pose turned by "
                  "0 / 10 / 20 / 30 degrees, mean distance from the true homologues: "
                  + " / ".join(f"{e:.2f}" for e in ends) + " mm")


def model_fit_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 2,
                    repeats: int = 3, population: str = "bumps") -> None:
    """A population-based pass (diagnostic): each shape fitted by the PCA model of the *other*
    shapes' correspondences, then projected onto it (what model-based registration, as in
    Scalismo, does with a learnt model). The model: similarity GPA of the other shapes'
    refine-1 correspondences, all K - 2 PCA modes; its mean posed on the shape by the Umeyama
    fit over the shape's own correspondence; the fit: core.reconstruction.fit_points to the
    shape's groomed vertices (gmm-aniso, similarity pose, the default shape prior). Spread (mm),
    mean over ``repeats`` populations a kind, and each population's. Not in SSM Studio's
    pipeline: see the README for why.
    """
    from core.alignment.transforms import generalized_procrustes
    from core.correspondence import establish_correspondence
    from core.geometry.toolkit import SurfaceProjector, umeyama
    from core.models.pca import PCA
    from core.reconstruction import fit_points

    _title("a population-based pass: each shape fitted by the model of the others (diagnostic)",
           n_shapes, vertices, seed, repeats, population)
    print(f"{'kind':<6}{'ours refine 1':>15}{'+ model fit of the others':>27}   per population")
    rows: dict[str, list] = {}
    for kind, pop in populations(n_shapes, vertices, seed, repeats, population):
        res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=1, vertices=vertices)
        keys = [k for k, m in enumerate(res.meshes) if m is not None]
        groomed = groomed_meshes(pop.meshes, vertices)
        ours = {k: res.meshes[k].vertices for k in keys}
        fitted = dict(ours)
        for k in keys:
            others = np.stack([ours[j] for j in keys if j != k])
            aligned = generalized_procrustes(others, "similarity", max_iter=30, tol=1e-7).aligned
            model = PCA().fit(aligned).to_shape_model(res.faces)
            s, r, t = umeyama(model.mean, ours[k])
            placement = np.eye(4)
            placement[:3, :3], placement[:3, 3] = s * r, t
            fit = fit_points(model, np.asarray(groomed[k].vertices), placement=placement, pose_sd=None)
            fitted[k] = SurfaceProjector(groomed[k].vertices, groomed[k].faces)(fit.vertices)[0]
        spreads = [pop.spread([v.get(k) for k in range(n_shapes)]).mean() for v in (ours, fitted)]
        rows.setdefault(kind, []).append(spreads)
        if len(rows[kind]) == repeats:
            mean = np.mean(rows[kind], axis=0)
            print(f"{kind:<6}{mean[0]:>15.3f}{mean[1]:>27.3f}   "
                  + " / ".join(f"{a:.3f} -> {b:.3f}" for a, b in rows[kind]))


def limits_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 100,
                 population: str = "bumps") -> None:
    """How far the surfaces alone determine the homologies (why the spread table's gain stops).

    The template is the exact bump-free base surface (:func:`_base_template`, even density),
    and every shape's true homologous points are known. Columns: SSM Studio's
    spread (refine 1, its own reference, for scale); the true affine map of the template onto
    each shape, then nearest-point projection (the floor of any global fit + projection);
    nonrigid CPD from the true similarity pose (plain CPD-then-project with a perfect
    template and a perfect start); rigid CPD with scale and affine CPD started *at the true
    affine map* (where the surfaces' own optimum lies). All on the groomed meshes ours gets.
    """
    from core.alignment.transforms import apply_transform, fit_transform
    from core.correspondence import DEFAULT_CPD_PARAMS, correspond_pair, establish_correspondence
    from core.correspondence.cpd import cpd_affine, cpd_rigid
    from core.geometry.toolkit import SurfaceProjector

    _title("what the surfaces determine: spread (mm) with the exact bump-free base surface as "
           "template", n_shapes, vertices, seed, population=population)
    print(f"{'kind':<6}{'ours refine 1':>15}{'true affine+proj':>18}{'CPD from true sim':>19}"
          f"{'rigid CPD from truth':>22}{'affine CPD from truth':>23}"
          f"{'offsets from truth / least-objective turn':>43}")
    plain_cpd = dict(DEFAULT_CPD_PARAMS, labelling=False, pair_residual=False)
    for kind, pop in populations(n_shapes, vertices, seed, population=population):
        ours = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=1, vertices=vertices)
        groomed = groomed_meshes(pop.meshes, vertices)
        template = _base_template(pop, vertices)
        columns: dict[str, list] = {k: [] for k in ("affine", "cpd", "rigid", "aff_cpd")}
        for k in range(len(pop.meshes)):
            truth = true_points(pop, k, template.vertices)
            project = SurfaceProjector(groomed[k].vertices, groomed[k].faces)
            affine, similar = (apply_transform(fit_transform(template.vertices, truth, how),
                                               template.vertices) for how in ("affine", "similarity"))
            columns["affine"].append(project(affine)[0])
            columns["cpd"].append(correspond_pair(template, groomed[k], plain_cpd, posed=similar)["vertices"])
            target = np.asarray(groomed[k].vertices)
            columns["rigid"].append(project(cpd_rigid(target, affine, scaling=True).points)[0])
            columns["aff_cpd"].append(project(cpd_affine(target, affine).points)[0])
            if kind == "ring":
                fits = _turned_offset_fits(template, groomed[k], truth)
                columns.setdefault("offsets", []).append(project(fits[0][1])[0])
                least = min(fits, key=lambda fit: fit[0])
                columns.setdefault("turn", []).append(project(least[1])[0])
        ours_spread = pop.spread([m.vertices if m is not None else None for m in ours.meshes]).mean()
        s = {k: pop.spread(v).mean() for k, v in columns.items()}
        turns = f"{s['offsets']:.3f} / {s['turn']:.3f}" if "turn" in s else "-"
        print(f"{kind:<6}{ours_spread:>15.3f}{s['affine']:>18.3f}{s['cpd']:>19.3f}{s['rigid']:>22.3f}"
              f"{s['aff_cpd']:>23.3f}{turns:>43}")


def _turned_offset_fits(template: TriMesh, target: TriMesh, truth: np.ndarray,
                        turns_deg=range(0, 35, 5)) -> list[tuple[float, np.ndarray]]:
    """SSM Studio's offsets' fit of the exact base ring, started at the true affine map with
    the template turned about the ring's own axis by 0, +-5, ..., +-30 degrees: (objective,
    fitted points, mm) per start, the unturned first. The least objective is where the
    fit's own posterior puts the turn, given a perfect template and a search over the turn."""
    from core.alignment.transforms import apply_transform, fit_transform
    from core.correspondence import DEFAULT_CPD_PARAMS
    from core.correspondence.pair import offsets_fit
    from core.geometry.toolkit import rodrigues

    pose = fit_transform(template.vertices, truth, "affine")
    xn, centre, scale = normalised(target.vertices)
    fits = []
    for deg in sorted({d for t in turns_deg for d in (t, -t)}, key=abs):
        turned = template.vertices @ rodrigues(np.deg2rad(deg) * np.array([0.0, 0.0, 1.0])).T
        start = (apply_transform(pose, turned) - centre) / scale
        fit = offsets_fit(start, template.faces, xn, target.faces, DEFAULT_CPD_PARAMS)
        fits.append((fit.objective, fit.points * scale + centre))
    return fits


def param_value(text: str) -> int | float | str:
    """NAME=VALUE of --param: an int, a float, or the string."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def add_options(parser: argparse.ArgumentParser) -> None:
    """The options of these tables (``bench_correspondence.py`` has them too)."""
    parser.add_argument("--spread-shapes", type=int, default=8, help="shapes per kind, spread table")
    parser.add_argument("--spread-seeds", type=int, default=1,
                        help="independent populations per kind in the spread table (1)")
    parser.add_argument("--population", choices=tuple(POPULATIONS), default="bumps",
                        help="known-homology shapes of the spread, limits and diagnostics tables: "
                             "independent bumps (default) or consistent features")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="an SSM Studio correspondence parameter in the spread table, e.g. "
                             "refine_deformation=cpd (the former refinement pass); repeatable")
    parser.add_argument("--tuning", action="store_true",
                        help="spread table on the tuning seeds 2-4 instead of the held-out 100-102")


def run(table: str, args: argparse.Namespace) -> None:
    """One table with the options of :func:`add_options` (and ``--jobs``)."""
    seed = 2 if args.tuning else 100
    if table == "spread":
        params = {k: param_value(v) for k, v in (p.split("=", 1) for p in args.param)}
        spread_table(args.spread_shapes, args.jobs, seed=seed, repeats=args.spread_seeds,
                     population=args.population, params=params)
    elif table == "limits":
        limits_table(args.spread_shapes, args.jobs, seed=seed, population=args.population)
    elif table == "diagnostics":
        diagnostics_table(args.spread_shapes, args.jobs, seed=seed, population=args.population)
    elif table == "model":
        model_fit_table(args.spread_shapes, args.jobs, seed=seed, repeats=args.spread_seeds,
                        population=args.population)
    else:
        raise ValueError(f"table must be one of {TABLES}, got {table!r}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", choices=TABLES, default=None,
                        help="one table (default: spread and limits; diagnostics and model "
                             "explain and run only when asked)")
    add_options(parser)
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (2)")
    args = parser.parse_args(argv)
    for table in (args.only,) if args.only else ("spread", "limits"):
        run(table, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
