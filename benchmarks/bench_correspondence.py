"""Benchmark: the whole correspondence step per shape, SSM Studio vs plain CPD pipelines.

Peers, on the same inputs in the same run:

- ``ssm-studio``: :func:`core.correspondence.correspond_pair` (rustcpd rigid + nonrigid CPD,
  log-posterior linear assignment, fairing on the target surface);
- ``rustcpd``: rustcpd rigid + nonrigid CPD with the same parameters, then each deformed
  reference vertex projected to its nearest point on the target surface;
- ``pycpd``: the same plain pipeline on pycpd 2.x (pure numpy; benchmark-only dependency).

Quality is measured on shapes with known homologues (synthetic, or the demo set's ground truth
when present): the distance of every corresponded vertex to its true homologue (mean and max,
mm), the share of degenerate triangles and the area distortion against the reference's
triangulation. Then the whole batch (``establish_correspondence``, fixed and auto reference)
is timed on 2 workers.

Run: ``.venv/bin/python benchmarks/bench_correspondence.py [--shapes 6] [--pycpd 2]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.geometry.toolkit import random_rotation  # noqa: E402
from core.io import TriMesh  # noqa: E402


# ----------------------------------------------------------------------------- synthetic data

def _sphere_mesh(n_points: int, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Near-uniform sphere triangulation: a Fibonacci lattice of ``n_points`` and its hull."""
    from scipy.spatial import ConvexHull

    i = np.arange(n_points) + 0.5
    z = 1.0 - 2.0 * i / n_points
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    r = np.sqrt(1.0 - z ** 2)
    pts = np.column_stack([r * np.cos(phi), r * np.sin(phi), z]) @ rotation.T
    faces = ConvexHull(pts).simplices
    # Orient counter-clockwise seen from outside.
    v = pts[faces]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", normal, v.mean(axis=1)) < 0
    faces[flip] = faces[flip][:, ::-1]
    return pts, faces


def bean(u: np.ndarray) -> np.ndarray:
    """Base shape from unit vectors: a bent, tapered ellipsoid with a one-sided bulge.

    About 36 x 20 x 15 mm, caudate-like, and without rotational symmetry, so that its pose
    is well defined.
    """
    x = 18.0 * u[:, 0]
    taper = 1.0 - 0.5 * u[:, 0]
    y = 8.0 * u[:, 1] * taper + 0.012 * (x + 18.0) ** 2
    z = 6.0 * u[:, 2] * taper + 5.0 * np.exp(-((x - 9.0) ** 2) / 30.0) * (1.0 + u[:, 2]) / 2.0
    return np.column_stack([x, y, z])


def bean_normals(u: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """Outward unit normals of :func:`bean` at unit vectors ``u`` (P, 3), by finite differences."""
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(u, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(u, t1)
    d1 = bean(u + eps * t1) - bean(u - eps * t1)
    d2 = bean(u + eps * t2) - bean(u - eps * t2)
    n = np.cross(d1, d2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n * np.sign(np.einsum("ij,ij->i", n, bean(u) - bean(u).mean(axis=0)))[:, None]


def smooth_deformation(rng: np.random.Generator, n_bumps: int = 6, amplitude: float = 1.5,
                       width: float = 7.0):
    """A random smooth shape change: Gaussian bumps along the surface normal, then an
    anisotropic scaling. Maps unit vectors (P, 3) to points (P, 3).

    The bumps move material points along the normal only, so the true homologues are
    determined by the geometry (a tangential field would make them unobservable).
    """
    centres = bean(rng.normal(size=(n_bumps, 3)) / 1.7)
    heights = rng.normal(size=n_bumps) * amplitude
    scale = rng.uniform(0.9, 1.1, size=3)

    def f(u: np.ndarray) -> np.ndarray:
        p = bean(u)
        d2 = ((p[:, None, :] - centres[None]) ** 2).sum(axis=2)
        bump = np.exp(-d2 / (2 * width ** 2)) @ heights
        return (p + bump[:, None] * bean_normals(u)) * scale

    return f


def synthetic_population(n_shapes: int = 20, *, seed: int = 0, max_angle_deg: float = 45.0,
                         translation_mm: float = 40.0,
                         n_points: tuple[int, int] = (1800, 2300)) -> tuple[list[TriMesh], tuple]:
    """Remeshed, permuted and posed smooth deformations of one bean shape, with known truth.

    Returns the meshes and, per mesh, ``truth(u)``: the posed position on that shape of the
    material point with unit-sphere parameter(s) ``u`` (P, 3), plus each mesh's own parameters
    in ``params[k]``. Two meshes' points are homologous when their parameters are equal.
    """
    rng = np.random.default_rng(seed)
    meshes, truths, params = [], [], []
    for k in range(n_shapes):
        u, faces = _sphere_mesh(int(rng.integers(*n_points)), random_rotation(rng, 180.0))
        perm = rng.permutation(len(u))
        inverse = np.argsort(perm)
        u = u[perm]
        faces = inverse[faces]
        deform = smooth_deformation(rng)
        rot = random_rotation(rng, max_angle_deg)
        trans = rng.uniform(-translation_mm, translation_mm, size=3)

        def truth(uu, deform=deform, rot=rot, trans=trans):
            return deform(uu) @ rot.T + trans

        meshes.append(TriMesh(truth(u), faces, f"synthetic_{k:02d}"))
        truths.append(truth)
        params.append(u)
    return meshes, (truths, params)


# ----------------------------------------------------------------------------- data sets

def demo_population(folder: Path):
    """The demo set (``resources/demo``): meshes and a truth function per reference.

    Returns meshes and ``truth(ref, k) -> (N_ref, 3)``: the true homologues on mesh k of the
    vertices of mesh ``ref`` (through the barycentric remeshing record of ground_truth.npz).
    """
    from core.io import load_mesh

    gt = np.load(folder / "ground_truth.npz")
    names = [str(n) for n in gt["mesh_names"]]
    meshes = []
    for name in names:
        mesh = load_mesh(folder / "meshes" / name)
        mesh.name = name
        meshes.append(mesh)
    offsets, tris, bary = gt["remesh_offsets"], gt["remesh_triangles"], gt["remesh_barycentric"]
    base_faces, shapes = gt["base_faces"], gt["corresponded_shapes"]

    def truth(ref: int, k: int) -> np.ndarray:
        rows = np.arange(offsets[ref], offsets[ref + 1])
        corners = base_faces[tris[rows]]  # (N_ref, 3)
        return np.einsum("nl,nlc->nc", bary[rows], shapes[k][corners])

    return meshes, truth


def synthetic_truth(n_shapes: int, seed: int = 0):
    meshes, (truths, params) = synthetic_population(n_shapes, seed=seed)
    return meshes, lambda ref, k: truths[k](params[ref])


# ----------------------------------------------------------------------------- peers

def _normalised(points: np.ndarray):
    centre = points.mean(axis=0)
    scale = float(np.sqrt(((points - centre) ** 2).sum(axis=1).mean()))
    return (points - centre) / scale, centre, scale


def plain_rustcpd(reference: TriMesh, target: TriMesh, params: dict) -> np.ndarray:
    """rustcpd alone: rigid + nonrigid CPD on all points, then nearest-point projection."""
    import rustcpd

    from core.geometry.toolkit import SurfaceProjector

    xn, centre, scale = _normalised(target.vertices)
    yn, _, _ = _normalised(reference.vertices)
    rigid = rustcpd.register_rigid(xn, yn, scale=True, tolerance=params["tolerance"],
                                   max_iterations=params["rigid_iterations"])
    nonrigid = rustcpd.register_deformable(xn, rigid.points, alpha=params["lam"], beta=params["beta"],
                                           low_rank=params["low_rank"], low_rank_method="pivoted_cholesky",
                                           tolerance=params["tolerance"],
                                           max_iterations=params["max_iterations"])
    moved = np.asarray(nonrigid.points) * scale + centre
    return SurfaceProjector(target.vertices, target.faces)(moved)[0]


def plain_pycpd(reference: TriMesh, target: TriMesh, params: dict) -> np.ndarray:
    """pycpd: rigid + nonrigid CPD (pure numpy), then nearest-point projection."""
    from pycpd import DeformableRegistration, RigidRegistration

    from core.geometry.toolkit import SurfaceProjector

    xn, centre, scale = _normalised(target.vertices)
    yn, _, _ = _normalised(reference.vertices)
    rigid = RigidRegistration(X=xn, Y=yn, tolerance=params["tolerance"],
                              max_iterations=params["rigid_iterations"])
    posed, _ = rigid.register()
    nonrigid = DeformableRegistration(X=xn, Y=posed, alpha=params["lam"], beta=params["beta"],
                                      tolerance=params["tolerance"],
                                      max_iterations=params["max_iterations"])
    moved, _ = nonrigid.register()
    return SurfaceProjector(target.vertices, target.faces)(moved * scale + centre)[0]


def ours(reference: TriMesh, target: TriMesh, params: dict) -> np.ndarray:
    from core.correspondence import correspond_pair

    return correspond_pair(reference, target, params)["vertices"]


def area_distortion(vertices: np.ndarray, reference: np.ndarray, faces: np.ndarray) -> float:
    """Mean |log| ratio of each triangle's share of the total area, output vs reference.

    0 when the output reproduces the reference's vertex distribution on the new shape;
    grows where vertices bunch up or spread out (the irregularities fairing removes).
    """
    def shares(v):
        t = v[faces]
        a = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        return np.maximum(a, 1e-12) / a.sum()

    return float(np.abs(np.log(shares(vertices) / shares(reference))).mean())


def flipped_fraction(vertices: np.ndarray, faces: np.ndarray, target: TriMesh) -> float:
    """Fraction of output triangles facing inwards (normal against the target's local normal):
    fold-overs, where the output surface doubles back on itself."""
    from scipy.spatial import cKDTree

    from core.geometry.toolkit import face_normals, vertex_normals

    centroids = vertices[faces].mean(axis=1)
    _, nearest = cKDTree(target.vertices).query(centroids)
    target_normals = vertex_normals(target.vertices, target.faces)[nearest]
    return float((np.einsum("ij,ij->i", face_normals(vertices, faces), target_normals) < 0).mean())


def degenerate_fraction(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Fraction of triangles with less than 5 % of the mean triangle area (slivers, collapses)."""
    v = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return float((area < 0.05 * area.mean()).mean())


def alignment_on_demo(folder: Path) -> None:
    """Pose removal on the demo set's true correspondences: sync vs GPA vs reference-based.

    The demo shapes are s_k R_k y_k + t_k with known unposed shapes y_k; the error is the RMS
    distance between the aligned shapes and the y_k after one common similarity (the gauge).
    """
    from core.alignment.transforms import (align_shapes, apply_transform, fit_transform,
                                pairwise_transforms, reference_transforms)

    gt = np.load(folder / "ground_truth.npz")
    posed = gt["corresponded_shapes"]
    unposed = gt["base_vertices"][None] + np.einsum("km,mnc->knc", gt["coefficients"], gt["factors"])

    def error(aligned: np.ndarray) -> float:
        gauge = fit_transform(aligned.reshape(-1, 3), unposed.reshape(-1, 3), "similarity")
        return float(np.sqrt(((apply_transform(gauge, aligned) - unposed) ** 2).sum(-1).mean()))

    print("\nalignment of the demo set's true correspondences (similarity), RMS error vs unposed truth")
    for method in ("sync", "gpa"):
        t0 = time.perf_counter()
        result = align_shapes(posed, method=method, transform="similarity")
        print(f"  {method:<16}{error(result.aligned):8.3f} mm  {time.perf_counter() - t0:6.2f} s")
    ref = reference_transforms(pairwise_transforms(posed, "similarity"), 0)
    print(f"  {'to shape 0':<16}{error(apply_transform(ref, posed)):8.3f} mm")


# ----------------------------------------------------------------------------- issue 13 tables

def _plain_batch(reference: TriMesh, meshes: list, params: dict, jobs: int) -> tuple[list, float]:
    """Plain rustcpd CPD-then-project of every mesh onto the reference, ``jobs`` processes."""
    import multiprocessing as mp

    out, wall, _ = _plain_batch_timed(reference, meshes, params, jobs)
    return out, wall


def _plain_timed(reference: TriMesh, target: TriMesh, params: dict) -> tuple[np.ndarray, float]:
    """:func:`plain_rustcpd` and its seconds in the worker (as ours' per-shape task seconds)."""
    t0 = time.perf_counter()
    out = plain_rustcpd(reference, target, params)
    return out, time.perf_counter() - t0


def _plain_batch_timed(reference: TriMesh, meshes: list, params: dict, jobs: int
                       ) -> tuple[list, float, float]:
    """:func:`_plain_batch` with the sum of the per-shape task seconds (the ``cpu s`` column,
    measured as ours' ``cpu_total``: inside the workers, so less sensitive to the pool's
    start-up and to other users' load than the wall time)."""
    import multiprocessing as mp

    t0 = time.perf_counter()
    ctx = mp.get_context("forkserver")
    with ctx.Pool(jobs) as pool:
        done = pool.starmap(_plain_timed, [(reference, m, params) for m in meshes])
    return [d[0] for d in done], time.perf_counter() - t0, float(sum(d[1] for d in done))


def _load() -> str:
    """The 1, 5 and 15 minute load averages (times on a shared machine are upper bounds)."""
    import os

    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def _spread_of(pop, vertices: list) -> np.ndarray:
    return pop.spread(vertices)


def pipeline_table(kind: str, n_shapes: int, jobs: int, seed: int = 7) -> None:
    """Whole pipeline on raw meshes, reference auto, vs plain rustcpd CPD-then-project."""
    from core.correspondence import DEFAULT_CPD_PARAMS, establish_correspondence
    from core.datasets.shapes import known_homology_shapes

    pop = known_homology_shapes(kind, n_shapes, seed=seed, n_points=(1800, 2300))
    scanner = np.array([-96.0, 131.0, 58.0])  # mm: where a structure sits in scanner coordinates
    for m in pop.meshes:
        m.vertices = m.vertices + scanner
    counts = [m.n_vertices for m in pop.meshes]
    print(f"\n{n_shapes} raw {kind} meshes ({min(counts)}-{max(counts)} vertices, own tessellations, "
          f"planted bumps, centred near {scanner.tolist()} mm), {jobs} worker processes; "
          f"shared machine: times are upper bounds")
    print(f"{'pipeline':<34}{'wall s':>8}{'task s':>8}{'assign s':>10}{'assign %':>9}"
          f"{'spread mean':>13}{'p95 mm':>8}{'fails':>6}")
    rows = {}
    for label, refine in (("ssm-studio (groom, auto, refine 1)", 1), ("ssm-studio, refine 0", 0)):
        t0 = time.perf_counter()
        res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=refine)
        wall = time.perf_counter() - t0
        verts = [m.vertices if m is not None else None for m in res.meshes]
        spread = _spread_of(pop, verts)
        t = res.timings
        rows[label] = (wall, res)
        print(f"{label:<34}{wall:>8.1f}{t['cpu_total']:>8.1f}{t['assignment_total']:>10.2f}"
              f"{100 * t['assignment_total'] / max(t['cpu_total'], 1e-9):>9.1f}"
              f"{spread.mean():>13.3f}{np.percentile(spread, 95):>8.3f}{len(res.failures):>6}")
    ref_index = rows["ssm-studio, refine 0"][1].reference_index
    reference = pop.meshes[ref_index]
    others = [m for k, m in enumerate(pop.meshes) if k != ref_index]
    out, wall, task_s = _plain_batch_timed(reference, others, dict(DEFAULT_CPD_PARAMS), jobs)
    verts = []
    it = iter(out)
    for k in range(n_shapes):
        verts.append(reference.vertices if k == ref_index else next(it))
    spread = _spread_of(pop, verts)
    print(f"{'rustcpd CPD-then-project':<34}{wall:>8.1f}{task_s:>8.1f}{'-':>10}{'-':>9}"
          f"{spread.mean():>13.3f}{np.percentile(spread, 95):>8.3f}{0:>6}")
    ours = rows['ssm-studio (groom, auto, refine 1)']
    print(f"load average during the run: {_load()}")
    print(f"time ratio ssm-studio / rustcpd CPD-then-project: wall {ours[0] / wall:.2f}, "
          f"sum of per-shape task seconds {ours[1].timings['cpu_total'] / max(task_s, 1e-9):.2f} "
          f"(ours' grooming, reference choice and GPA are not in the latter); reference "
          f"{rows['ssm-studio (groom, auto, refine 1)'][1].reference_name}: "
          f"{rows['ssm-studio (groom, auto, refine 1)'][1].reference_reason}")


def scaling_table(seed: int = 3) -> None:
    """One pair at ~2,500 and ~10,000 vertices: pair time and assignment time."""
    from core.correspondence import correspond_pair
    from core.datasets.shapes import known_homology_shapes

    print(f"\nscaling, one bean pair with own tessellations (times: shared machine, upper bounds)")
    print(f"{'vertices':>9}{'pair s':>9}{'cpd s':>8}{'assign s':>10}{'assign %':>9}")
    totals = {}
    for n in (2500, 10000):
        pop = known_homology_shapes("bean", 2, seed=seed, n_points=(n, n + 1))
        t0 = time.process_time()
        out = correspond_pair(pop.meshes[0], pop.meshes[1])
        cpu = time.process_time() - t0
        t = out["timings"]
        totals[n] = t["total"]
        print(f"{n:>9}{t['total']:>9.2f}{t['rigid'] + t['nonrigid']:>8.2f}{t['assignment']:>10.3f}"
              f"{100 * t['assignment'] / t['total']:>9.1f}   (cpu {cpu:.2f} s)")
    print(f"10,000 / 2,500 pair time: {totals[10000] / totals[2500]:.2f}x")


def _title(what: str, n_shapes: int, vertices: int, seed: int, repeats: int = 1) -> None:
    per = f"{n_shapes} shapes per population, {repeats} populations per kind" if repeats > 1 \
        else f"{n_shapes} shapes per kind"
    print(f"\n{what}; {population} population, {per}, ~{vertices} vertices; "
          f"{'held-out' if seed >= 100 else 'TUNING'} seeds {seed}-{seed + 3 * repeats - 1}; load {_load()}")


# The two populations of core.datasets.shapes: "bumps", independent random bumps
# on every shape (the generator's defaults); "features", six consistent features a kind whose
# size varies between shapes, smaller independent bumps, and independent even remeshes.
POPULATIONS = {"bumps": {},
               "features": {"features": 6, "n_bumps": 3, "bump_mm": 0.5, "retessellate": True}}
population = "bumps"  # set by --population
ours_params: dict = {}  # SSM Studio's correspondence parameters in the spread table, --param


def _param_value(text: str):
    """NAME=VALUE of --param: an int, a float, or the string."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _populations(n_shapes: int, vertices: int, seed: int, repeats: int = 1):
    """(kind, known-homology population) for the bean, tube and ring, seeds seed, seed+1,
    seed+2; with ``repeats`` R, R populations a kind (seeds seed + i + 3 r), kind by kind."""
    from core.datasets.shapes import known_homology_shapes

    for i, kind in enumerate(("bean", "tube", "ring")):
        for r in range(repeats):
            yield kind, known_homology_shapes(kind, n_shapes, seed=seed + i + 3 * r,
                                              n_points=(vertices - 100, vertices + 100),
                                              **POPULATIONS[population])


def spread_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 100,
                 repeats: int = 1) -> None:
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
    from core.correspondence.batch import _prepare

    _title("spread vs truth (mean distance of homologous points' material points from their "
           "mean, mm)" + (f"; SSM Studio with {ours_params}" if ours_params else ""),
           n_shapes, vertices, seed, repeats)
    print(f"{'kind':<6}{'plain raw':>11}{'plain groomed':>15}{'ours refine 0':>15}{'ours refine 1':>15}"
          f"{'gain vs best plain':>20}{'assign % of pair':>18}{'dropped':>9}"
          + ("   gain per population" if repeats > 1 else ""))
    rows: dict[str, list] = {}
    for kind, pop in _populations(n_shapes, vertices, seed, repeats):
        outputs, dropped = {}, set()
        for refine in (0, 1):
            res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=refine,
                                           vertices=vertices, **ours_params)
            outputs[refine] = [m.vertices if m is not None else None for m in res.meshes]
            dropped |= {k for k, m in enumerate(res.meshes) if m is None}
            share = 100 * res.timings["assignment_total"] / max(res.timings["cpu_total"], 1e-9)
            if refine == 0:
                ref = res.reference_index
                reference = res.meshes[ref]  # the groomed reference
        groomed, _, _ = _prepare(pop.meshes, [m.name for m in pop.meshes], True, vertices)
        plain = {}
        for label, inputs in (("raw", pop.meshes), ("groomed", groomed)):
            others = [m for k, m in enumerate(inputs) if k != ref]
            out, _ = _plain_batch(reference, others, dict(DEFAULT_CPD_PARAMS), jobs)
            it = iter(out)
            plain[label] = [reference.vertices if k == ref else next(it) for k in range(n_shapes)]
        # Every column over the same shapes: a shape ours dropped (flagged as bad input) is
        # left out of the plain columns too, and counted.
        spreads = {key: _spread_of(pop, [v if k not in dropped else None for k, v in enumerate(vs)]).mean()
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


def _true_points(pop, k: int, material: np.ndarray) -> np.ndarray:
    """The points of shape ``k`` whose material points are ``material`` (P, 3): a template's
    true homologous points there."""
    from core.geometry.toolkit import surface_coordinates

    mesh = pop.meshes[k]
    tri, bary, _ = surface_coordinates(material, pop.material[k], mesh.faces)
    return np.einsum("pj,pjc->pc", bary, mesh.vertices[mesh.faces[tri]])


def diagnostics_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 2) -> None:
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
    from core.correspondence.batch import _prepare
    from core.datasets.shapes import material_points
    from core.geometry.toolkit import SurfaceProjector, rodrigues

    def variance(shapes: list) -> float:
        gpa = generalized_procrustes(np.stack(shapes), "similarity", max_iter=50, tol=1e-8)
        return float(((gpa.aligned - gpa.mean) ** 2).sum(axis=2).sum(axis=1).mean())

    _title("what limits the groupwise refinement (diagnostics)", n_shapes, vertices, seed)
    print(f"{'kind':<6}{'refine 1 / 2 / 3':>22}{'GPA var ours / truth':>24}{'to mean / others avg':>23}"
          f"{'affine fit+proj':>17}{'sliding it 1 / 6':>18}")
    one_pass = dict(DEFAULT_CPD_PARAMS, max_iterations=DEFAULT_CPD_PARAMS["refine_iterations"],
                    pair_residual=False)
    for kind, pop in _populations(n_shapes, vertices, seed):
        refined = {}
        for passes in (1, 2, 3):
            res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=passes,
                                           vertices=vertices)
            refined[passes] = _spread_of(pop, [m.vertices for m in res.meshes]).mean()
            if passes == 1:
                ours, faces = [m.vertices for m in res.meshes], res.faces
        groomed, _, _ = _prepare(pop.meshes, [m.name for m in pop.meshes], True, vertices)
        project = [SurfaceProjector(g.vertices, g.faces) for g in groomed]
        consensus = np.mean([material_points(v, pop.meshes[k], pop.material[k])
                             for k, v in enumerate(ours)], axis=0)
        truth = [_true_points(pop, k, consensus) for k in range(len(ours))]
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
            sliding.append(_spread_of(pop, slid).mean())
        print(f"{kind:<6}{refined[1]:>10.3f} / {refined[2]:.3f} / {refined[3]:.3f}"
              f"{variance(ours):>14.0f} / {variance(truth):<7.0f}"
              f"{_spread_of(pop, to_mean).mean():>14.3f} / {_spread_of(pop, averaged).mean():<6.3f}"
              f"{_spread_of(pop, affine).mean():>17.3f}{sliding[0]:>11.3f} / {sliding[-1]:.3f}")
        if kind == "ring":  # the base ring's axis is z; turned about it, in the base frame
            template = _base_template(pop, vertices)
            ends = []
            for degrees in (0, 10, 20, 30):
                turn = rodrigues(np.deg2rad(degrees) * np.array([0.0, 0.0, 1.0]))
                outs = []
                for k in range(len(ours)):
                    start = template.vertices @ turn.T
                    true = _true_points(pop, k, template.vertices)
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
                    repeats: int = 3) -> None:
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
    from core.correspondence.batch import _prepare
    from core.geometry.toolkit import SurfaceProjector, umeyama
    from core.models.pca import PCA
    from core.reconstruction import fit_points

    _title("a population-based pass: each shape fitted by the model of the others (diagnostic)",
           n_shapes, vertices, seed, repeats)
    print(f"{'kind':<6}{'ours refine 1':>15}{'+ model fit of the others':>27}   per population")
    rows: dict[str, list] = {}
    for kind, pop in _populations(n_shapes, vertices, seed, repeats):
        res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=1, vertices=vertices)
        keys = [k for k, m in enumerate(res.meshes) if m is not None]
        groomed, _, _ = _prepare(pop.meshes, [m.name for m in pop.meshes], True, vertices)
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
        spreads = [_spread_of(pop, [v.get(k) for k in range(n_shapes)]).mean() for v in (ours, fitted)]
        rows.setdefault(kind, []).append(spreads)
        if len(rows[kind]) == repeats:
            mean = np.mean(rows[kind], axis=0)
            print(f"{kind:<6}{mean[0]:>15.3f}{mean[1]:>27.3f}   "
                  + " / ".join(f"{a:.3f} -> {b:.3f}" for a, b in rows[kind]))


def limits_table(n_shapes: int, jobs: int, vertices: int = 1200, seed: int = 100) -> None:
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
    from core.correspondence.batch import _prepare
    from core.correspondence.cpd import cpd_affine, cpd_rigid
    from core.geometry.toolkit import SurfaceProjector

    _title("what the surfaces determine: spread (mm) with the exact bump-free base surface as "
           "template", n_shapes, vertices, seed)
    print(f"{'kind':<6}{'ours refine 1':>15}{'true affine+proj':>18}{'CPD from true sim':>19}"
          f"{'rigid CPD from truth':>22}{'affine CPD from truth':>23}"
          f"{'offsets from truth / least-objective turn':>43}")
    for kind, pop in _populations(n_shapes, vertices, seed):
        ours = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=1, vertices=vertices)
        groomed, _, _ = _prepare(pop.meshes, [m.name for m in pop.meshes], True, vertices)
        template = _base_template(pop, vertices)
        columns: dict[str, list] = {k: [] for k in ("affine", "cpd", "rigid", "aff_cpd")}
        for k, mesh in enumerate(pop.meshes):
            truth = _true_points(pop, k, template.vertices)
            project = SurfaceProjector(groomed[k].vertices, groomed[k].faces)
            affine = apply_transform(fit_transform(template.vertices, truth, "affine"), template.vertices)
            similar = apply_transform(fit_transform(template.vertices, truth, "similarity"), template.vertices)
            columns["affine"].append(project(affine)[0])
            columns["cpd"].append(correspond_pair(template, groomed[k], dict(DEFAULT_CPD_PARAMS, labelling=False,
                                                  pair_residual=False), posed=similar)["vertices"])
            target = np.asarray(groomed[k].vertices)
            columns["rigid"].append(project(cpd_rigid(target, affine, scaling=True).points)[0])
            columns["aff_cpd"].append(project(cpd_affine(target, affine).points)[0])
            if kind == "ring":
                fits = _turned_offset_fits(template, groomed[k], truth)
                columns.setdefault("offsets", []).append(project(fits[0][1])[0])
                least = min(fits, key=lambda fit: fit[0])
                columns.setdefault("turn", []).append(project(least[1])[0])
        ours_spread = _spread_of(pop, [m.vertices if m is not None else None for m in ours.meshes]).mean()
        s = {k: _spread_of(pop, v).mean() for k, v in columns.items()}
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
    xn, centre, scale = _normalised(target.vertices)
    fits = []
    for deg in sorted({d for t in turns_deg for d in (t, -t)}, key=abs):
        turned = template.vertices @ rodrigues(np.deg2rad(deg) * np.array([0.0, 0.0, 1.0])).T
        start = (apply_transform(pose, turned) - centre) / scale
        fit = offsets_fit(start, template.faces, xn, target.faces, DEFAULT_CPD_PARAMS)
        fits.append((fit.objective, fit.points * scale + centre))
    return fits


def _ellipsoid_error(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray,
                     axes: np.ndarray) -> tuple[float, float]:
    """Volume error (%) against the analytic ellipsoid and mean distance (mm) of the vertices
    to its surface (first-order distance |F - 1| / |grad F|, F = sum((x - c)^2 / a^2)^(1/2))."""
    from core.geometry import mesh as meshops

    q = (vertices - centre) / axes
    r = np.linalg.norm(q, axis=1)
    grad = np.linalg.norm(q / axes / np.maximum(r[:, None], 1e-12), axis=1)
    volume = 4.0 / 3.0 * np.pi * np.prod(axes)
    return (100.0 * (meshops.volume(vertices, faces) / volume - 1.0),
            float(np.mean(np.abs(r - 1.0) / grad)))


def labels_table(repeats: int = 3) -> None:
    """``mesh-labels`` on a 256^3 label map with one structure: the CLI end to end (a fresh
    process: imports, NIfTI read, Surface Nets, smoothing, remesh to 2,000 vertices, write),
    the same in-process, and plain VTK discrete flying edges (marching cubes on the whole
    volume, no smoothing, no remesh) as the peer."""
    import resource
    import subprocess
    import tempfile

    import nibabel as nib
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    from core.io import load_volume
    from core.correspondence.mesh_labels import label_map_surface
    from core.correspondence.mesh_labels import polydata_arrays

    print("\nmesh-labels, 256^3 uint8 label map (1 mm voxels), one structure, --vertices 2000; "
          "best of %d; shared machine: times are upper bounds" % repeats)
    print("(wall s is inflated by the other users' load; cpu s = user + system CPU of the "
          "process, all threads)")
    print(f"{'structure':<30}{'method':<34}{'wall s':>7}{'cpu s':>7}{'vertices':>10}"
          f"{'volume %':>10}{'dist mm':>9}")
    n = 256
    i, j, k = np.ogrid[:n, :n, :n]
    for label, axes in (("ellipsoid 120 x 80 x 60 mm", (60.0, 40.0, 30.0)),
                        ("ellipsoid 24 x 16 x 12 mm", (12.0, 8.0, 6.0))):
        axes = np.array(axes)
        centre = np.array([128.3, 120.6, 130.2])
        data = ((((i - centre[0]) / axes[0]) ** 2 + ((j - centre[1]) / axes[1]) ** 2
                 + ((k - centre[2]) / axes[2]) ** 2) <= 1.0).astype(np.uint8) * 17
        with tempfile.TemporaryDirectory() as tmp:
            path = f"{tmp}/labels.nii.gz"
            nib.save(nib.Nifti1Image(data, np.eye(4)), path)
            rows = []
            best, best_cpu = np.inf, np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                subprocess.run([sys.executable, "-m", "core.cli", "mesh-labels", path, "--label", "17",
                                "--out", f"{tmp}/out"], check=True, cwd=ROOT, capture_output=True)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                best = min(best, time.perf_counter() - t0)
                best_cpu = min(best_cpu, after.ru_utime - before.ru_utime
                               + after.ru_stime - before.ru_stime)
            from core.io import load_mesh

            mesh = load_mesh(f"{tmp}/out/labels_label_17.vtk") if Path(
                f"{tmp}/out/labels_label_17.vtk").exists() else load_mesh(
                next(Path(f"{tmp}/out").glob("*.vtk")))
            rows.append(("ssm-studio CLI (fresh process)", best, best_cpu, mesh))
            times, cpus = [], []
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                mesh = label_map_surface(path, 17)
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            rows.append(("ssm-studio in-process", min(times), min(cpus), mesh))
            volume = load_volume(path)
            times, cpus = [], []
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                mask = (np.asarray(volume.data) == 17).astype(np.uint8)
                image = vtk.vtkImageData()
                image.SetDimensions(*mask.shape)
                image.GetPointData().SetScalars(numpy_to_vtk(mask.ravel(order="F"), deep=True))
                fe = vtk.vtkDiscreteFlyingEdges3D()
                fe.SetInputData(image)
                fe.SetValue(0, 1)
                fe.Update()
                v, f = polydata_arrays(fe.GetOutput())
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            rows.append(("VTK discrete flying edges", min(times), min(cpus), TriMesh(v, f)))
        for method, seconds, cpu, m in rows:
            vol_err, dist = _ellipsoid_error(m.vertices, m.faces, centre, axes)
            print(f"{label:<30}{method:<34}{seconds:>7.2f}{cpu:>7.2f}{m.n_vertices:>10}"
                  f"{vol_err:>10.2f}{dist:>9.3f}")


# ----------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shapes", type=int, default=18, help="meshes in the pipeline table (18)")
    parser.add_argument("--spread-shapes", type=int, default=8, help="shapes per kind, spread table")
    parser.add_argument("--spread-seeds", type=int, default=1,
                        help="independent populations per kind in the spread table (1)")
    parser.add_argument("--population", choices=tuple(POPULATIONS), default="bumps",
                        help="known-homology shapes of the spread, limits and diagnostics tables: "
                             "independent bumps (default) or consistent features")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="an SSM Studio correspondence parameter in the spread table, e.g. "
                             "refine_deformation=cpd (the former refinement pass); repeatable")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--tuning", action="store_true",
                        help="spread table on the tuning seeds 2-4 instead of the held-out 100-102")
    parser.add_argument("--only", choices=("pipeline", "scaling", "spread", "limits", "diagnostics", "model",
                                           "labels", "legacy"),
                        default=None)
    args = parser.parse_args(argv)
    global population
    population = args.population
    ours_params.update({k: _param_value(v) for k, v in (p.split("=", 1) for p in args.param)})
    if args.only in (None, "scaling"):
        scaling_table()
    if args.only in (None, "spread"):
        spread_table(args.spread_shapes, args.jobs, seed=2 if args.tuning else 100,
                     repeats=args.spread_seeds)
    if args.only in (None, "limits"):
        limits_table(args.spread_shapes, args.jobs, seed=2 if args.tuning else 100)
    if args.only == "diagnostics":  # not in the default run: it explains, it reports nothing
        diagnostics_table(args.spread_shapes, args.jobs, seed=2 if args.tuning else 100)
    if args.only == "model":  # not in the default run either
        model_fit_table(args.spread_shapes, args.jobs, seed=2 if args.tuning else 100,
                        repeats=args.spread_seeds)
    if args.only in (None, "pipeline"):
        pipeline_table("ring", args.shapes, args.jobs)
    if args.only in (None, "labels"):
        labels_table()
    if args.only == "legacy":
        return legacy_main([])
    return 0


def legacy_main(argv: list[str] | None = None) -> int:
    """The earlier per-pair table (demo set or beans, vs rustcpd and pycpd)."""
    from core.correspondence import DEFAULT_CPD_PARAMS, establish_correspondence

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shapes", type=int, default=6, help="targets per method (default 6)")
    parser.add_argument("--pycpd", type=int, default=2, help="targets for pycpd (slow; default 2)")
    parser.add_argument("--batch", type=int, default=20, help="meshes in the batch timing (default 20)")
    parser.add_argument("--synthetic", action="store_true", help="ignore the demo set")
    args = parser.parse_args(argv)

    demo = ROOT / "resources" / "demo"
    if not args.synthetic and (demo / "ground_truth.npz").exists():
        meshes, truth = demo_population(demo)
        source = f"demo set ({demo.relative_to(ROOT)}, {len(meshes)} caudate meshes)"
    else:
        meshes, truth = synthetic_truth(max(args.batch, args.shapes + 1))
        source = "synthetic bean shapes"
    counts = [m.n_vertices for m in meshes]
    print(f"data: {source}; vertices {min(counts)}-{max(counts)}")
    params = dict(DEFAULT_CPD_PARAMS)
    ref = 0
    reference = meshes[ref]
    targets = list(range(1, min(len(meshes), args.shapes + 1)))
    peers = [("ssm-studio", ours, targets), ("rustcpd alone", plain_rustcpd, targets),
             ("pycpd", plain_pycpd, targets[:args.pycpd])]
    rows = []
    for name, fn, tgts in peers:
        if name == "pycpd":
            try:
                import pycpd  # noqa: F401
            except ImportError:
                print("pycpd not installed (pip install .[bench]); skipped")
                continue
        if not tgts:
            continue
        times, means, maxes, degen, distortion, flipped = [], [], [], [], [], []
        for k in tgts:
            t0 = time.perf_counter()
            out = fn(reference, meshes[k], params)
            times.append(time.perf_counter() - t0)
            err = np.linalg.norm(out - truth(ref, k), axis=1)
            means.append(err.mean())
            maxes.append(err.max())
            degen.append(degenerate_fraction(out, reference.faces))
            distortion.append(area_distortion(out, reference.vertices, reference.faces))
            flipped.append(flipped_fraction(out, reference.faces, meshes[k]))
        rows.append((name, len(tgts), np.mean(times), np.mean(means), np.max(maxes), 100 * np.mean(degen),
                     np.mean(distortion), 100 * np.mean(flipped)))
    print(f"\nper shape, reference {reference.name} ({reference.n_vertices} vertices), "
          f"same targets, same CPD parameters")
    print(f"{'method':<15}{'shapes':>7}{'s/shape':>9}{'mean err mm':>13}{'max err mm':>12}"
          f"{'degenerate %':>14}{'area distortion':>17}{'flipped %':>11}")
    for r in rows:
        print(f"{r[0]:<15}{r[1]:>7}{r[2]:>9.2f}{r[3]:>13.3f}{r[4]:>12.3f}{r[5]:>14.2f}{r[6]:>17.3f}"
              f"{r[7]:>11.2f}")
    if len(rows) >= 2:
        print(f"time ratio ssm-studio / rustcpd alone: {rows[0][2] / rows[1][2]:.2f}")

    if (demo / "ground_truth.npz").exists() and not args.synthetic:
        alignment_on_demo(demo)

    batch = meshes[:args.batch]
    if len(batch) < 2:
        return 0
    for label, reference_arg, n_refs in (("fixed reference", 0, 1), ("auto, 3 candidates", "auto", 3)):
        t0 = time.perf_counter()
        result = establish_correspondence(batch, reference_arg, n_references=n_refs, n_jobs=2)
        wall = time.perf_counter() - t0
        r = result.reference_index
        errs = [np.linalg.norm(m.vertices - truth(r, k), axis=1)
                for k, m in enumerate(result.meshes) if m is not None and k != r]
        print(f"\nbatch of {len(batch)} meshes, 2 workers, {label}: {wall:.1f} s wall "
              f"({result.timings['n_registrations']} registrations, "
              f"{result.timings['per_shape_mean']:.2f} s each), reference {result.reference_name}, "
              f"error vs truth mean {np.mean([e.mean() for e in errs]):.3f} mm, "
              f"max {np.max([e.max() for e in errs]):.3f} mm, failures {len(result.failures)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
