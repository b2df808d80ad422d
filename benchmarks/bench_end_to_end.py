"""Benchmark: end to end, raw meshes -> correspondence -> PCA model -> fit from contours (issue 27, item 5).

For every family of :mod:`core.datasets.families` (the REPORT half by default) and a few
populations (``--seeds``), two pipelines side by side in ONE run on the same inputs:

- ``today``: this tree, in process: ``core.build.pipeline.build_model(correspond=True,
  method="pca")``, what ``ssm-studio build-model --correspond --method pca --factors 10`` runs
  (the correspondence defaults: grooming with the reference-only remesh, the safeguard);
- ``round 1``: round 1's code (``git archive caedcf2``, extracted to a temporary folder and run
  there in a subprocess with its own ``core`` on PYTHONPATH, as ``bench_protocol.py`` does):
  its ``core.pipeline.build_model(correspond=True, method="pca")`` on the same meshes.

Each model has 10 factors (at most N - 1 for N training shapes). For each of ``--held-out``
shapes of the family (another seed, so not in the training set) a simulated user draws
contours of the TRUE held-out surface (``core.evaluation.simulated_user.simulate_user``: 2 mm
spacing along the contour, 0.2 mm in-plane noise): 3 orthogonal planes through the centre of
the shape's box, or 2 parallel axial planes at +-1/4 of its axial extent from the centre. Both
pipelines' models are fitted with TODAY's ``fit_points`` (gmm-aniso and icp, similarity pose,
with the contour normals), placed at the points' centre as *Place here* does
(``placement="points"``), so only correspondence + model differ; round 1's models are also
fitted with round 1's own ``fit_points`` (placed the same way: round 1 has no ``placement``,
its model's ``world_transform`` is moved). Error: symmetric mean surface distance (mm) between
the fitted surface and the true held-out surface
(:func:`core.geometry.toolkit.symmetric_surface_distance`), averaged over held-out shapes.

LSF locality (the ``ovoid`` family only: 4 bumps planted at the same material points in every
shape, :data:`core.datasets.families.OVOID_CENTRES`): a local-support factor model (LSF,
Bernard et al., CVPR 2016; ``build_model(method="lsf", n_factors=8)``) of each pipeline's
corresponded shapes. The planted supports on the output vertices: the vertices whose mean
material point (over the training shapes) is where the bump moves the surface by more than
10 % of its peak (sigma 2 mm: within 4.29 mm of the bump's centre). Measure:
:func:`core.datasets.factors.support_iou` (per planted bump, the best IoU of any factor's
support, 10 % of its peak), mean over the 4 bumps; with today's LSF on both pipelines'
correspondences, and round 1 end to end (its own LSF); column ``known corr``: today's LSF of
as many ovoids generated on one lattice (known correspondences), the measure's ceiling. Each
column is the mean over :data:`LSF_STARTS` initialisations (``random_state``) of the LSF, as
one start moves the IoU by as much as the pipelines differ.

Run: ``.venv/bin/python benchmarks/bench_end_to_end.py [--families F ...] [--shapes 16]
[--held-out 3] [--seeds 1 | --seed-list S ...] [--jobs 1] [--json OUT] [--cache DIR] [--round1-timeout S]
[--no-mirror-check] [--option KEY=VALUE ...]``; ``--cache``
keeps the built models (the slow part) and reuses them, so a change of the fit code reruns in
seconds; today's models are cached under a key of the correspondence and grooming defaults, so
a changed default builds them again.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "RAYON_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")  # each job on one core

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
for _p in (str(ROOT), str(ROOT / "benchmarks")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from bench_protocol import extract_round1  # noqa: E402

from core.datasets.families import FAMILIES, OVOID_CENTRES, REPORT, ovoid_base, population  # noqa: E402

METHODS = ("gmm-aniso", "icp")
LAYOUTS = ("3 orthogonal", "2 parallel")
PIPELINES = ("today", "round 1", "round 1 own fit")  # the fit columns
LSF_COLUMNS = ("today", "round 1 corr, today's LSF", "round 1 end to end", "known corr")
N_FACTORS, LSF_FACTORS = 10, 8
# LSF starts from a random coordinate initialisation: one start's IoU moves by +-0.05 (SD) on
# the same shapes, as much as the differences between pipelines, so every LSF column is the
# mean over this many starts (``random_state`` 0, 1, ...; both pipelines' LSF take it)
LSF_STARTS = 5
SPACING, NOISE = 2.0, 0.2
HELD_OUT_SEED = 1000  # the held-out shapes' population seed: seed + this
BUMP_RADIUS = 2.0 * np.sqrt(2.0 * np.log(10.0))  # sigma-2 mm bump above 10 % of its peak

# Round 1, in its own tree: build-model --correspond --method pca, its LSF (ovoid), its fit.
ROUND1_SCRIPT = """
import sys, time, numpy as np
from core.io import TriMesh
from core.pipeline import build_model
from core.reconstruction import fit_points
data = np.load(sys.argv[1])
meshes = [TriMesh(data[f"v{k}"], data[f"f{k}"], f"s{k}") for k in range(int(data["n"]))]
t0 = time.perf_counter()
res = build_model(meshes, correspond=True, method="pca", n_factors=int(data["factors"]), n_jobs=1)
seconds = time.perf_counter() - t0
m = res.model
kept = [int(name[1:]) for name in res.names]
out = {"shapes": res.shapes, "faces": res.faces, "kept": np.array(kept), "mean": m.mean,
       "factors": m.factors, "coef_var": m.coef_var, "world": m.world_transform,
       "seconds": seconds}
if int(data["lsf"]):
    t0 = time.perf_counter()
    for start in range(int(data["lsf_starts"])):
        lsf = build_model(res.shapes, faces=res.faces, method="lsf", n_factors=int(data["lsf"]),
                          method_params={"random_state": start})
        out[f"lsf_factors{start}"] = lsf.model.factors
    out["lsf_seconds"] = (time.perf_counter() - t0) / int(data["lsf_starts"])
stored = m.world_transform.copy()
centre = m.to_world(m.mean).mean(axis=0)
for c in range(int(data["cases"])):
    pts, nrm = data[f"p{c}"], data[f"n{c}"]
    world = stored.copy()
    world[:3, 3] += pts.mean(axis=0) - centre  # Place here: the mean's centre at the points'

    m.world_transform = world
    for method in ("gmm-aniso", "icp"):
        t0 = time.perf_counter()
        fit = fit_points(m, pts, nrm, method=method)
        out[f"x{c}_{method}"], out[f"t{c}_{method}"] = fit.vertices, time.perf_counter() - t0
np.savez(sys.argv[2], **out)
"""


# ----------------------------------------------------------------------------- contours

def contour_planes(vertices: np.ndarray, layout: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """3 orthogonal planes through the centre of the shape's box, or 2 parallel axial ones at
    +-1/4 of its axial extent from the centre."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = 0.5 * (lo + hi)
    if layout == "3 orthogonal":
        return [(centre.copy(), np.eye(3)[a]) for a in (2, 1, 0)]
    z = np.eye(3)[2]
    return [(centre + s * 0.25 * (hi[2] - lo[2]) * z, z.copy()) for s in (-1.0, 1.0)]


def held_out_cases(family: str, n_held_out: int, seed: int) -> list[dict]:
    """The held-out shapes (a population of another seed) and their contours per layout."""
    from core.evaluation.simulated_user import simulate_user

    pop = population(family, n_held_out, seed + HELD_OUT_SEED)
    cases = []
    for h, mesh in enumerate(pop.meshes):
        for li, layout in enumerate(LAYOUTS):
            user = simulate_user(mesh.vertices, mesh.faces, 0, spacing=SPACING, noise=NOISE,
                                 rng=np.random.default_rng([seed, h, li]),
                                 planes=contour_planes(mesh.vertices, layout))
            cases.append({"shape": h, "layout": layout, "mesh": mesh, "points": user.points,
                          "normals": user.normals})
    return cases


# ----------------------------------------------------------------------------- measures

def surface_error(vertices: np.ndarray, faces: np.ndarray, truth) -> float:
    """Symmetric mean surface distance (mm) between a fitted surface and the true one."""
    from core.geometry.toolkit import symmetric_surface_distance

    return symmetric_surface_distance(vertices, faces, truth.vertices, truth.faces)


def fit_today(model, cases: list[dict]) -> dict:
    """Today's ``fit_points`` (placed at the points' centre) on every case: errors and times."""
    from core.reconstruction import fit_points

    out: dict = {}
    for c, case in enumerate(cases):
        for method in METHODS:
            t0 = time.perf_counter()
            fit = fit_points(model, case["points"], case["normals"], method=method,
                             placement="points")
            seconds = time.perf_counter() - t0
            out.setdefault(f"{case['layout']}|{method}", []).append(
                (surface_error(fit.vertices, model.faces, case["mesh"]), seconds))
    return out


def planted_supports(pop, shapes: np.ndarray, kept: list[int]) -> np.ndarray:
    """(4, N, 3) displacement fields whose 10 % supports are the planted bumps' on the
    output vertices (their mean material point within :data:`BUMP_RADIUS` of a bump's centre,
    Gaussian fall-off, sigma 2 mm)."""
    from core.datasets.shapes import material_points

    material = np.mean([material_points(s, pop.meshes[k], pop.material[k])
                        for s, k in zip(shapes, kept)], axis=0)
    return bump_fields(material)


def bump_fields(base_points: np.ndarray) -> np.ndarray:
    """(4, N, 3) fields, one a planted bump: a Gaussian of the distance (sigma 2 mm, the
    family's) of each point on the ovoid's base surface from the bump's centre."""
    d2 = ((base_points[None] - ovoid_base(OVOID_CENTRES)[:, None]) ** 2).sum(axis=2)
    field = np.zeros((len(OVOID_CENTRES), len(base_points), 3))
    field[:, :, 0] = np.exp(-d2 / (2 * 2.0 ** 2))
    return field


def lsf_iou(planted: np.ndarray, factors: np.ndarray) -> float:
    from core.datasets.factors import support_iou

    return float(support_iou(planted, factors).mean())


def known_lsf(n_shapes: int, seed: int) -> dict:
    """The measure's ceiling: today's LSF of ``n_shapes`` ovoids generated on ONE lattice
    (1,500 vertices, known correspondences; :func:`ovoid_shape` with the planted centres)."""
    from core.datasets.families import ovoid_shape, sphere_lattice

    m, faces = sphere_lattice(1500)
    rng = np.random.default_rng([seed, 7])
    shapes = np.stack([ovoid_shape(m, faces, rng, OVOID_CENTRES) for _ in range(n_shapes)])
    ious, seconds = today_lsf(bump_fields(ovoid_base(m)), shapes, faces)
    return {"lsf": {"known corr": float(np.mean(ious)), "known corr_sd": float(np.std(ious)),
                    "today_s": seconds}}


def today_lsf(planted: np.ndarray, shapes: np.ndarray, faces: np.ndarray) -> tuple[list[float], float]:
    """Today's LSF of ``shapes`` from :data:`LSF_STARTS` initialisations: the IoU of each
    against ``planted``, and the mean seconds a start."""
    from core.build.pipeline import build_model

    t0 = time.perf_counter()
    ious = []
    for start in range(LSF_STARTS):
        res = build_model(shapes, faces=faces, method="lsf", n_factors=LSF_FACTORS,
                          method_params={"random_state": start})
        ious.append(lsf_iou(planted, res.model.factors))
    return ious, (time.perf_counter() - t0) / LSF_STARTS


# ----------------------------------------------------------------------------- pipelines

def _today_build(pop, n_factors: int, options: dict | None = None) -> dict:
    """Today's build-model --correspond --method pca (``options``: more correspondence
    keywords, e.g. ``mirror_check=False``): the model's arrays, the corresponded shapes, the
    kept inputs and the seconds."""
    from core.build.pipeline import build_model

    t0 = time.perf_counter()
    res = build_model(pop.meshes, correspond=True, method="pca", n_factors=n_factors, n_jobs=1,
                      correspond_options=options)
    index = {m.name: k for k, m in enumerate(pop.meshes)}
    m = res.model
    return {"seconds": time.perf_counter() - t0, "shapes": res.shapes, "faces": res.faces,
            "kept": np.array([index[name] for name in res.names]), "mean": m.mean,
            "factors": m.factors, "coef_var": m.coef_var, "world": m.world_transform}


def _round1_build(pop, cases: list[dict], n_factors: int, with_lsf: bool, folder: str,
                  timeout: float | None = None) -> dict:
    """Round 1's build-model (and LSF, and its own fits of ``cases``) in its own tree; past
    ``timeout`` seconds it is stopped (``{"error": ..., "timeout": 1}``, not cached)."""
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        arrays = {"n": len(pop.meshes), "factors": n_factors, "lsf": LSF_FACTORS if with_lsf else 0,
                  "lsf_starts": LSF_STARTS,
                  "cases": len(cases)}
        for k, m in enumerate(pop.meshes):
            arrays[f"v{k}"], arrays[f"f{k}"] = m.vertices, m.faces
        for c, case in enumerate(cases):
            arrays[f"p{c}"], arrays[f"n{c}"] = case["points"], case["normals"]
        np.savez(src, **arrays)
        env = {**os.environ, "PYTHONPATH": folder}
        t0 = time.perf_counter()
        try:
            done = subprocess.run([sys.executable, "-c", ROUND1_SCRIPT, src, dst], cwd=folder,
                                  env=env, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"error": np.array([f"not finished within --round1-timeout {timeout:.0f} s"]),
                    "seconds": time.perf_counter() - t0, "timeout": 1}
        if done.returncode != 0:
            return {"error": np.array(done.stderr.strip().splitlines()[-1:] or ["no output"]),
                    "seconds": time.perf_counter() - t0}
        return dict(np.load(dst))


def _cached(path: Path | None, make) -> dict:
    """``make()``'s arrays, read from / written to ``path`` (an .npz) when given."""
    if path is not None and path.exists():
        return dict(np.load(path))
    data = make()
    if path is not None and "timeout" not in data:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **data)
    return data


def _evaluate(data: dict, pop, cases: list[dict], with_lsf: bool, own: bool) -> dict:
    """Today's fit (and LSF) on a pipeline's model; round 1's own fits and LSF (``own``)."""
    from core.models.shape_model import ShapeModel

    if "error" in data:
        return {"error": [str(e) for e in data["error"]], "build_s": float(data["seconds"])}
    model = ShapeModel(mean=data["mean"], factors=data["factors"], coef_var=data["coef_var"],
                       faces=data["faces"], world_transform=data["world"], method="pca")
    out = {"build_s": float(data["seconds"]), "kept": len(data["kept"]), "fits": fit_today(model, cases)}
    if own:
        fits: dict = {}
        for c, case in enumerate(cases):
            for method in METHODS:
                fits.setdefault(f"{case['layout']}|{method}", []).append(
                    (surface_error(data[f"x{c}_{method}"], data["faces"], case["mesh"]),
                     float(data[f"t{c}_{method}"])))
        out["own_fits"] = fits
    if with_lsf:
        planted = planted_supports(pop, data["shapes"], [int(k) for k in data["kept"]])
        ious, seconds = today_lsf(planted, data["shapes"], data["faces"])
        col = "round 1 corr, today's LSF" if own else "today"
        out["lsf"] = {col: float(np.mean(ious)), f"{col}_sd": float(np.std(ious)), "today_s": seconds}
        if own:
            own_ious = [lsf_iou(planted, data[f"lsf_factors{start}"]) for start in range(LSF_STARTS)]
            out["lsf"]["round 1 end to end"] = float(np.mean(own_ious))
            out["lsf"]["round 1 end to end_sd"] = float(np.std(own_ious))
            out["lsf"]["own_s"] = float(data["lsf_seconds"])
    return out


def _defaults_key() -> str:
    """Eight hex digits naming today's correspondence and grooming defaults."""
    import hashlib

    from core.correspondence.grooming import DEFAULT_GROOMING
    from core.correspondence.pair import DEFAULT_CPD_PARAMS

    text = repr(sorted(DEFAULT_CPD_PARAMS.items())) + repr(sorted(DEFAULT_GROOMING.items()))
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def run_one(family: str, seed: int, n_shapes: int, n_held_out: int, folder: str,
            cache: Path | None = None, timeout: float | None = None,
            options: dict | None = None) -> dict:
    """Both pipelines on one population of ``family``: {"today": ..., "round 1": ...}; the
    built models are kept in ``cache`` (a folder) when given and reused from it; ``options``:
    more correspondence keywords for today's build."""
    pop = population(family, n_shapes, seed)
    cases = held_out_cases(family, n_held_out, seed)
    n_factors = min(N_FACTORS, n_shapes - 1)
    with_lsf = family == "ovoid"
    stem = None if cache is None else cache / f"{family}_seed{seed}_n{n_shapes}_h{n_held_out}"
    # the correspondence defaults are part of the key: a model cached before a default
    # changed is not reused as today's
    suffix = "".join(f"_{k}-{v}" for k, v in sorted((options or {}).items())) + f"_{_defaults_key()}"
    today = _cached(None if stem is None else stem.with_name(stem.name + f"_today{suffix}.npz"),
                    lambda: _today_build(pop, n_factors, options))
    round1 = _cached(None if stem is None else stem.with_name(stem.name + "_round1.npz"),
                     lambda: _round1_build(pop, cases, n_factors, with_lsf, folder, timeout))
    return {"today": _evaluate(today, pop, cases, with_lsf, own=False),
            "round 1": _evaluate(round1, pop, cases, with_lsf, own=True),
            "known": known_lsf(n_shapes, seed) if with_lsf else {},
            "points": {layout: float(np.mean([len(c["points"]) for c in cases if c["layout"] == layout]))
                       for layout in LAYOUTS}}


def _task(task: tuple) -> tuple:
    family, seed, n_shapes, n_held_out, folder, cache, timeout, options = task
    return family, seed, run_one(family, seed, n_shapes, n_held_out, folder, cache, timeout,
                                 options)


# ----------------------------------------------------------------------------- tables

def _fit_cells(run: dict, key: str) -> dict:
    """Per pipeline column: (mean error, median seconds) of one layout|method, or None."""
    cells = {}
    for col, (name, field) in zip(PIPELINES, (("today", "fits"), ("round 1", "fits"),
                                              ("round 1", "own_fits"))):
        vals = run.get(name, {}).get(field, {}).get(key)
        cells[col] = (float(np.mean([v[0] for v in vals])), float(np.median([v[1] for v in vals]))) \
            if vals else None
    return cells


def summarise(results: dict) -> dict:
    """Per family: fit errors (layout|method -> column -> mean error, median fit s) averaged
    over seeds, build seconds and kept shapes per pipeline, LSF IoU per column."""
    summary = {}
    for family, runs in results.items():
        runs = list(runs.values())
        if not runs:
            continue
        fits = {}
        for layout in LAYOUTS:
            for method in METHODS:
                key = f"{layout}|{method}"
                per = [_fit_cells(r, key) for r in runs]
                fits[key] = {col: [float(np.mean([p[col][i] for p in per if p[col]])) for i in (0, 1)]
                             if any(p[col] for p in per) else None for col in PIPELINES}
        build = {name: [float(np.mean([r[name]["build_s"] for r in runs if "build_s" in r[name]]
                                      or [np.nan])),
                        int(sum(r[name].get("kept", 0) for r in runs))] for name in ("today", "round 1")}
        lsf = {}
        for col, name in zip(LSF_COLUMNS, ("today", "round 1", "round 1", "known")):
            vals = [r[name]["lsf"][col] for r in runs if "lsf" in r.get(name, {})]
            sds = [r[name]["lsf"].get(f"{col}_sd", np.nan) for r in runs if "lsf" in r.get(name, {})]
            lsf[col] = float(np.mean(vals)) if vals else None
            lsf[f"{col}_sd"] = float(np.mean(sds)) if sds else None
        summary[family] = {"fits": fits, "build": build, "lsf": lsf,
                           "errors": [r["round 1"]["error"] for r in runs if "error" in r["round 1"]]}
    return summary


def tables(summary: dict, header: str) -> str:
    """The markdown tables: fit errors per method, build times, LSF locality."""
    out = [header]
    for method in METHODS:
        out += ["", f"{method}: symmetric surface distance (mm) of the fit to the true held-out "
                "surface, today's fit on each pipeline's model (round 1's own fit last)", "",
                "| family | contours | " + " | ".join(PIPELINES) + " |",
                "|---|---|" + "---|" * len(PIPELINES)]
        for family, s in summary.items():
            for layout in LAYOUTS:
                cells = [f"{c[0]:.3f}" if c else "-" for c in
                         (s["fits"][f"{layout}|{method}"][col] for col in PIPELINES)]
                out.append(f"| {family} | {layout} | " + " | ".join(cells) + " |")
    out += ["", "Time: build (correspondence + PCA model, s, mean per population; shapes kept) and "
            "fit (median s per fit, gmm-aniso / icp)", "",
            "| family | today build | round 1 build | " + " | ".join(f"{c} fit" for c in PIPELINES) + " |",
            "|---|---|---|" + "---|" * len(PIPELINES)]
    for family, s in summary.items():
        b = s["build"]
        fit_s = []
        for col in PIPELINES:
            t = [s["fits"][f"{lay}|{m}"][col] for m in METHODS for lay in LAYOUTS]
            fit_s.append(" / ".join(f"{np.mean([x[1] for x in t[2 * i:2 * i + 2] if x]):.2f}"
                                    for i in range(len(METHODS))) if all(t) else "-")
        out.append(f"| {family} | {b['today'][0]:.0f} ({b['today'][1]}) | {b['round 1'][0]:.0f} "
                   f"({b['round 1'][1]}) | " + " | ".join(fit_s) + " |")
    lsf_rows = [(f, s["lsf"]) for f, s in summary.items() if any(v is not None for v in s["lsf"].values())]
    if lsf_rows:
        out += ["", f"LSF locality: mean over the 4 planted bumps of the best support IoU of "
                f"{LSF_FACTORS} LSF factors; mean +- SD over {LSF_STARTS} starts (SD: mean over "
                "populations)", "", "| family | " + " | ".join(LSF_COLUMNS) + " |",
                "|---|" + "---|" * len(LSF_COLUMNS)]
        for family, lsf in lsf_rows:
            out.append(f"| {family} | " + " | ".join(
                f"{lsf[c]:.2f} +- {lsf[c + '_sd']:.2f}" if lsf[c] is not None else "-"
                for c in LSF_COLUMNS) + " |")
    for family, s in summary.items():
        for err in s["errors"]:
            out.append(f"round 1 failed on {family}: {err}")
    return "\n".join(out) + "\n"


def merged(paths: list[Path]) -> dict:
    """The runs of several ``--json`` files, {family: {seed: run}}: for each population, each
    pipeline from the last file that has it without an error (a rerun of today's pipeline
    replaces an earlier one; round 1's result stays where a later run timed it out)."""
    results: dict = {}
    for path in paths:
        for family, runs in json.loads(Path(path).read_text())["runs"].items():
            for seed, run in runs.items():
                into = results.setdefault(family, {}).setdefault(int(seed), {})
                for name, part in run.items():
                    if name not in into or (isinstance(part, dict) and "error" not in part):
                        into[name] = part
    return results


def paired_differences(results: dict) -> str:
    """Today's end to end minus round 1's end to end (its model and its own fit), and on round
    1's model today's fit minus its own, paired by population and held-out shape: mean +-
    standard error, per family, layout and method."""
    out = ["", "today minus round 1 end to end (mm), paired by population and held-out shape; "
           "last: on round 1's model, today's fit minus round 1's own", "",
           "| family | fit | contours | populations | today | round 1 | difference | "
           "fit only |", "|---|---|---|---|---|---|---|---|"]

    def mean_se(d: np.ndarray) -> str:
        return f"{d.mean():+.3f} +- {d.std(ddof=1) / np.sqrt(len(d)):.3f}"

    for family, runs in results.items():
        for method in METHODS:
            for layout in LAYOUTS:
                key, cols, n = f"{layout}|{method}", ([], [], []), 0
                for run in runs.values():
                    three = (run.get("today", {}).get("fits", {}).get(key),
                             run.get("round 1", {}).get("own_fits", {}).get(key),
                             run.get("round 1", {}).get("fits", {}).get(key))
                    if all(three) and len({len(x) for x in three}) == 1:
                        for col, fits in zip(cols, three):
                            col += [v[0] for v in fits]
                        n += 1
                if len(cols[0]) > 1:
                    today, own, theirs_today = (np.asarray(c) for c in cols)
                    out.append(f"| {family} | {method} | {layout} | {n} | {today.mean():.3f} | "
                               f"{own.mean():.3f} | {mean_se(today - own)} | "
                               f"{mean_se(theirs_today - own)} |")
    return "\n".join(out) + "\n"


def run(families: list[str], seeds, n_shapes: int, n_held_out: int, jobs: int, folder: str,
        on_result=None, cache: Path | None = None, timeout: float | None = None,
        options: dict | None = None) -> dict:
    """Every (family, seed) task, ``jobs`` at a time: {family: {seed: run_one(...)}}."""
    tasks = [(f, s, n_shapes, n_held_out, folder, cache, timeout, options)
             for f in families for s in seeds]
    results: dict = {f: {} for f in families}
    t0 = time.perf_counter()
    if jobs <= 1:
        done = map(_task, tasks)
    else:
        import multiprocessing as mp

        pool = mp.get_context("forkserver").Pool(jobs, maxtasksperchild=1)
        done = pool.imap_unordered(_task, tasks)
    for i, (family, seed, out) in enumerate(done):
        results[family][seed] = out
        print(f"[{i + 1}/{len(tasks)} {time.perf_counter() - t0:6.0f} s] {family} seed {seed}", flush=True)
        if on_result is not None:
            on_result(results)
    if jobs > 1:
        pool.close()
    return results


def _keyword(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--option``: the value as a number or boolean where it reads as one."""
    key, _, value = text.partition("=")
    for convert in (int, float):
        try:
            return key, convert(value)
        except ValueError:
            pass
    return key, {"true": True, "false": False}.get(value.lower(), value)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(REPORT), choices=FAMILIES)
    parser.add_argument("--shapes", type=int, default=16, help="training shapes a population")
    parser.add_argument("--held-out", type=int, default=3, help="held-out shapes a population")
    parser.add_argument("--seeds", type=int, default=1, help="populations a family (seeds 0, 1, ...)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (each on 1 core)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here (as they come)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="keep the built models in this folder and reuse them (only the fits rerun)")
    parser.add_argument("--round1-timeout", type=float, default=None, metavar="S",
                        help="stop round 1's build of a population after S seconds (reported, not cached)")
    parser.add_argument("--no-mirror-check", action="store_true",
                        help="today's build keeps the inputs the mirror check would leave out")
    parser.add_argument("--seed-list", type=int, nargs="+", default=None, metavar="S",
                        help="these populations instead of 0 .. --seeds - 1")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="a correspondence keyword for today's build (cached apart), e.g. "
                             "rigid_fine_sampling=random")
    parser.add_argument("--merge", type=Path, nargs="+", default=None, metavar="JSON",
                        help="no run: the tables of these --json files together (merged)")
    args = parser.parse_args(argv)
    if args.merge:
        results = merged(args.merge)
        print(tables(summarise(results), f"merged: {', '.join(str(p) for p in args.merge)}")
              + paired_differences(results))
        return
    if args.shapes < 4 or args.held_out < 1 or args.seeds < 1:
        raise SystemExit("need --shapes >= 4, --held-out >= 1 and --seeds >= 1")
    t0 = time.perf_counter()

    def dump(results: dict) -> None:
        if args.json:
            args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                             "summary": summarise(results),
                                             "runs": {f: {str(s): v for s, v in r.items()}
                                                      for f, r in results.items()}}, indent=1))

    with tempfile.TemporaryDirectory(prefix="round1_") as folder:
        extract_round1(folder)
        options = dict(_keyword(text) for text in args.option)
        if args.no_mirror_check:
            options["mirror_check"] = False
        seeds = args.seed_list if args.seed_list else range(args.seeds)
        results = run(args.families, seeds, args.shapes, args.held_out, args.jobs,
                      folder, on_result=dump, cache=args.cache, timeout=args.round1_timeout,
                      options=options or None)
    print(tables(summarise(results),
                 f"\n{len(seeds)} population(s) a family, {args.shapes} training shapes, "
                 f"{args.held_out} held-out shapes, PCA-{min(N_FACTORS, args.shapes - 1)}, "
                 f"{args.jobs} job(s), {time.perf_counter() - t0:.0f} s, load "
                 f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}"))


if __name__ == "__main__":
    main()
