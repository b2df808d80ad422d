"""Other criteria for the correspondence safeguard, scored offline on stored runs (issue 27
item 3; RESULTS "The safeguard: specificity and descriptor consistency").

Reads the runs ``bench_safeguard.py --save DIR --json FILE`` stored (each population's
reference-based runs with and without the remesh and its two refinement passes, and the raw
inputs) and scores, with the product's decision rule at several margins, how often each
criterion picks the option with the lowest true spread (the truth of ``FILE``'s checks):

- ``product``: the safeguard's own, leave-one-out generalisation against the raw inputs
  (:func:`core.correspondence.safeguard.loo_generalisation`);
- ``specificity`` (Davies et al., IEEE TMI 2002): the mean distance (mm) from shapes drawn
  from the run's PCA model (all modes, fixed draws per population so the options share them)
  to the nearest raw input surface, in the model's frame; a run whose points slide makes
  blurred, implausible instances;
- ``descriptor``: how consistent a local shape descriptor is at corresponding points: per
  shape, each vertex's height above the area-weighted centroid of its neighbours within r
  (r = 0.1, 0.2, 0.4 x the shape's RMS radius), over r, along the vertex normal (a curvature
  at scale r); the criterion is the area-weighted mean over vertices of its SD over the shapes;
- ``consistency`` (with ``--other-references``): how much the correspondence depends on the
  reference. Each judged option is run again with two other inputs as the reference (the
  batch's own plus 2 and plus 4, cyclically); for each pair of runs, every vertex of one run
  on shape k is located on the other run's surface of shape k (triangle and barycentric
  coordinates), carried by those coordinates to every other shape l of the other run, and
  compared with the first run's vertex on l (mm, both ways, averaged). Correspondences that
  are right do not depend on the reference and give zero; errors a reference leaves in its
  own way show up, errors every reference shares do not;
- products of the safeguard's criterion with each.

    PYTHONPATH=. python benchmarks/diag_safeguard_criteria.py DIR FILE [--other-references]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_safeguard import TIE, _check, populations  # noqa: E402

from core.alignment.transforms import apply_transform, fit_transform, generalized_procrustes  # noqa: E402
from core.correspondence import establish_correspondence  # noqa: E402
from core.correspondence.safeguard import loo_generalisation, refinement_choice  # noqa: E402
from core.datasets import families  # noqa: E402
from core.geometry.toolkit import closest_points_on_surface, surface_coordinates, vertex_normals  # noqa: E402
from core.types import TriMesh  # noqa: E402

RUNS = ("r0_remesh", "r0_plain", "r1_offsets", "r1_cpd")
SCALES = (0.1, 0.2, 0.4)
MARGINS = (0.0, 0.03, 0.05, 0.08)
SAMPLES = 40


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A third of the area of each vertex's triangles."""
    e1, e2 = vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    return np.bincount(faces.ravel(), np.repeat(area / 3.0, 3), minlength=len(vertices))


def descriptor(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, len(SCALES)) height of each vertex above its neighbours' centroid within r, / r."""
    normals = vertex_normals(vertices, faces)
    size = np.sqrt(((vertices - vertices.mean(axis=0)) ** 2).sum(axis=1).mean())
    tree = cKDTree(vertices)
    area = vertex_areas(vertices, faces)
    out = []
    for scale in SCALES:
        r = scale * size
        pairs = tree.sparse_distance_matrix(tree, r, output_type="coo_matrix")
        weights = sp.csr_matrix((area[pairs.col], (pairs.row, pairs.col)),
                                shape=(len(vertices),) * 2) + sp.diags(area)
        centroid = (weights @ vertices) / np.asarray(weights.sum(axis=1))
        out.append(np.einsum("ij,ij->i", normals, vertices - centroid) / r)
    return np.stack(out, axis=1)


def descriptor_spread(shapes: list[np.ndarray], faces: np.ndarray) -> float:
    sd = np.stack([descriptor(s, faces) for s in shapes]).std(axis=0).mean(axis=1)
    area = vertex_areas(np.mean(shapes, axis=0), faces)
    return float((sd * area).sum() / area.sum())


def specificity(shapes: list[np.ndarray], raw: list[TriMesh], seed: int = 0) -> float:
    stack = np.stack(shapes)
    aligned = generalized_procrustes(stack, "similarity", max_iter=20, tol=1e-6).aligned
    surfaces = [(apply_transform(fit_transform(stack[k], aligned[k], "similarity"),
                                 np.asarray(raw[k].vertices, float)), np.asarray(raw[k].faces))
                for k in range(len(stack))]
    flat = aligned.reshape(len(stack), -1)
    mean = flat.mean(axis=0)
    _, sv, vt = np.linalg.svd(flat - mean, full_matrices=False)
    draws = np.random.default_rng(seed).standard_normal((SAMPLES, len(sv)))
    instances = mean + (draws * sv / np.sqrt(len(stack) - 1)) @ vt
    return float(np.mean([min(float(closest_points_on_surface(x.reshape(-1, 3), v, f)[1].mean())
                              for v, f in surfaces) for x in instances]))


def stored_run(z, run: str) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """(input index -> corresponded vertices, faces) of one stored run."""
    keys = sorted(int(k.rsplit("_", 1)[1]) for k in z.files
                  if k.startswith(run + "_") and k.rsplit("_", 1)[1].isdigit())
    return {k: np.asarray(z[f"{run}_{k}"], dtype=np.float64) for k in keys}, z[f"{run}_faces"]


def population_criteria(npz: Path, others: Path | None = None) -> dict:
    """Per stored run: each criterion's value (``others``: the other references' runs)."""
    z = np.load(npz)
    raw = []
    while f"raw_{len(raw)}_v" in z:
        raw.append(TriMesh(z[f"raw_{len(raw)}_v"], z[f"raw_{len(raw)}_f"]))
    zo = None if others is None else np.load(others)
    out = {}
    for run in RUNS:
        if f"{run}_faces" not in z:
            continue
        shaped, faces = stored_run(z, run)
        keys = sorted(shaped)
        shapes = [shaped[k] for k in keys]
        product = loo_generalisation(shapes, faces, [raw[k] for k in keys])["value"]
        spec, desc = specificity(shapes, [raw[k] for k in keys]), descriptor_spread(shapes, faces)
        out[run] = {"product": product, "specificity": spec, "descriptor": desc,
                    "product x specificity": product * spec, "product x descriptor": product * desc}
        if zo is not None:
            cons = float(np.mean([reference_consistency(shaped, faces, *stored_run(zo, f"{j}_{run}"))
                                  for j in ("b0", "b1")]))
            out[run].update({"consistency": cons, "product x consistency": product * cons})
    return out


def _transfer(a: dict[int, np.ndarray], b: dict[int, np.ndarray], b_faces: np.ndarray,
              keys: list[int]) -> float:
    """Run ``a``'s vertices on each shape located on run ``b``'s surface of it, carried to
    every other shape of ``b``, against ``a``'s vertices there: the mean distance (mm)."""
    out = []
    for k in keys:
        tri, bary, _ = surface_coordinates(a[k], b[k], b_faces)
        for m in keys:
            if m != k:
                carried = np.einsum("pj,pjk->pk", bary, b[m][b_faces[tri]])
                out.append(np.linalg.norm(carried - a[m], axis=1).mean())
    return float(np.mean(out))


def reference_consistency(a: dict[int, np.ndarray], a_faces: np.ndarray,
                          b: dict[int, np.ndarray], b_faces: np.ndarray) -> float:
    """How far two runs with different references disagree (module docstring), mm."""
    keys = sorted(set(a) & set(b))
    return 0.5 * (_transfer(a, b, b_faces, keys) + _transfer(b, a, a_faces, keys))


def other_reference_runs(result: dict, n_shapes: int, path: Path) -> Path:
    """Each judged option of one population run again with two other references, stored
    at ``path`` (kept: a second call reads it)."""
    if path.exists():
        return path
    fam, seed = result["family"], result["seed"]
    report = fam in families.REPORT
    _, _, pop = next(iter(populations(report, [seed], n_shapes, [fam])))
    remesh_kept = any(c["stage"] == "remesh" and c["kept"] == "remesh" for c in result["checks"])
    groom = {} if remesh_kept else {"remesh": False}
    own = establish_correspondence(pop.meshes, refine=0, groom={"remesh": False}, safeguard=False,
                                   n_jobs=2).reference_index
    options = {"r0_remesh": dict(refine=0), "r0_plain": dict(refine=0, groom={"remesh": False}),
               "r1_offsets": dict(groom=groom, labelling=True),
               "r1_cpd": dict(groom=groom, labelling=True, refine_deformation="cpd")}
    arrays = {}
    for j, ref in enumerate(((own + 2) % n_shapes, (own + 4) % n_shapes)):
        for run, kw in options.items():
            res = establish_correspondence(pop.meshes, reference=ref, safeguard=False, n_jobs=2, **kw)
            arrays[f"b{j}_{run}_faces"] = res.faces
            arrays.update({f"b{j}_{run}_{k}": m.vertices for k, m in enumerate(res.meshes)
                           if m is not None})
    np.savez_compressed(path, **arrays)
    return path


def _right(check: dict, pick: str) -> bool:
    """Is ``pick`` right by the truth ``bench_safeguard.py`` stored for this decision?"""
    truth = {o: {"mean": t, "dropped": check["dropped"][o], "common": check["common_shapes"]}
             for o, t in check["truth_mm"].items()}
    return _check(check["stage"], check["criterion_mm"], truth, pick)["right"]


def score(results: list[dict], criteria: dict, name: str, margin: float) -> tuple[int, int, int]:
    """(right, decisions, misses costing more than ``TIE`` of the best option's true spread)."""
    right = total = costly = 0
    for res in results:
        values = {run: c[name] for run, c in criteria[(res["family"], res["seed"])].items()}
        remesh_kept = any(c["stage"] == "remesh" and c["kept"] == "remesh" for c in res["checks"])
        for check in res["checks"]:
            if check["stage"] == "remesh":
                pick = ("remesh" if values["r0_remesh"] < (1 - margin) * values["r0_plain"]
                        else "no remesh")
            else:  # the stored passes start from the remesh choice the product kept
                options = {"normal_offsets": values["r1_offsets"], "cpd": values["r1_cpd"]}
                options = {o: v for o, v in options.items() if o in check["truth_mm"]}
                base = values["r0_remesh" if remesh_kept else "r0_plain"]
                pick = refinement_choice(base, options, "normal_offsets", margin) or "none"
            ok = _right(check, pick)
            right, total = right + ok, total + 1
            costly += (not ok) and check["truth_mm"][pick] > (1 + TIE) * min(check["truth_mm"].values())
    return right, total, costly


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="bench_safeguard.py --save folder")
    ap.add_argument("json", type=Path, help="bench_safeguard.py --json file of the same run")
    ap.add_argument("--other-references", action="store_true",
                    help="add the reference-consistency criterion (runs each option with two other "
                         "references; stored in the folder as *_others.npz)")
    args = ap.parse_args()
    results = json.loads(args.json.read_text())
    criteria = {}
    for r in results:
        stored = args.folder / f"{r['family']}_{r['seed']}.npz"
        others = None
        if args.other_references:
            n_shapes = sum(1 for k in np.load(stored).files if k.startswith("raw_") and k.endswith("_v"))
            others = other_reference_runs(r, n_shapes, args.folder / f"{r['family']}_{r['seed']}_others.npz")
        criteria[(r["family"], r["seed"])] = population_criteria(stored, others)
    names = next(iter(next(iter(criteria.values())).values()))
    print(f"decisions right (misses costing > {TIE:.0%}) at margins {', '.join(f'{m:.0%}' for m in MARGINS)}")
    for name in names:
        cells = [score(results, criteria, name, m) for m in MARGINS]
        print(f"{name:24s}" + "".join(f"  {r}/{n} ({c})" for r, n, c in cells))


if __name__ == "__main__":
    main()
