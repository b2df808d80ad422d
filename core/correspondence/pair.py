"""One target mesh expressed with the reference's vertices and faces (steps 1-5 of the package).

Bernard et al., SPIE MI 2016: rigid then nonrigid CPD (Myronenko & Song, TPAMI 2010), a
bijective labelling by linear assignment (:mod:`core.correspondence.assignment`), the
reference's faces, and fairing (:func:`core.geometry.mesh.fair_mesh`).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from core.correspondence.assignment import auction_assign, labelling_candidates
from core.correspondence.cpd import CPDResult, cpd_nonrigid, cpd_rigid
from core.correspondence.offsets import NormalOffsetFit, fit_normal_offsets
from core.geometry import mesh as meshops
from core.geometry.toolkit import SurfaceProjector, symmetric_surface_distance
from core.types import TriMesh

DEFAULT_CPD_PARAMS: dict[str, Any] = {
    "w": 0.0,                 # outlier weight of the CPD mixture, in [0, 1)
    "beta": 2.0,              # Gaussian kernel width of the nonrigid motion (unit-RMS units)
    "lam": 2.0,               # motion coherence regularisation (lambda)
    "tolerance": 1e-5,        # relative change of the CPD objective to stop at
    "max_iterations": 100,    # nonrigid CPD iterations
    "refine_iterations": 20,  # nonrigid CPD iterations in a groupwise refinement pass (warm
                              # start from the current correspondence; the late iterations
                              # mostly add CPD's density-driven sliding: on tuning seeds the
                              # spread fell 6-16 % on beans and tubes against 100)
    "refine_deformation": "normal_offsets",  # the refinement passes' deformation of the
                              # posed mean: "normal_offsets" (an affine map and smooth offsets
                              # along the mean's normals, core.correspondence.offsets) or "cpd"
                              # (nonrigid CPD for refine_iterations, as until 2026-12-02)
    "offset_width": 0.5,      # kernel width of the offsets' prior (unit-RMS units)
    "offset_sd": 0.1,         # standard deviation of the offsets' prior (unit-RMS units)
    "offset_noise": 0.02,     # point-to-plane residual's standard deviation (unit-RMS units)
    "offset_iterations": 15,  # Gauss-Newton iterations of the offsets' fit (30 gave the same
                              # spread on tuning seeds), after offset_pose_iterations
    "offset_pose_iterations": 0,  # of its pose alone first: on tuning seeds 15 gained
                              # 14-16 % on rings, held out it turned one population of rings
                              # with independent bumps far off (-169 %), so none by default
    "offset_pose": "affine",  # the map fitted with the offsets: "affine" or "similarity" (as
                              # until 2026-12-02; held out, the affine map gained 31 points on
                              # tubes with independent bumps, README Measured)
    "deformation": "cpd",     # this correspondence's deformation ("cpd" or "normal_offsets";
                              # a refinement pass sets it from refine_deformation)
    "rigid_iterations": 40,   # rigid CPD iterations (refinement of the best start)
    "rigid_points": 500,      # subsample size for the rigid pose's starts
    "rigid_fine_points": 1000,  # subsample size for the chosen start's final refinement
    "rigid_sampling": "random",  # how the starts' subsamples are drawn: "random" or "even"
                              # (farthest-point picks, whatever the vertex density). Even
                              # starts changed nothing on the tuning half and left 5 thin
                              # report tubes out as mirrored against 1 (the mirror check
                              # compares the starts' fits)
    "rigid_fine_sampling": "even",  # how the final refinement's subsamples are drawn: a
                              # random draw follows the vertex density (a staircase's rows,
                              # a decimation's uneven triangles) and weights the pose to the
                              # dense parts. "even" since 2026-12-07: tuning half global
                              # -3.1 %, the others within 1 %; report half 0.5 mm label maps
                              # -7 %, two-lobed -2 %, thin level, ovoid +2 % (RESULTS.md)
    "rigid_fine_from": "start",  # where that refinement starts: "start" (the chosen start's
                              # rotation itself) or "run" (the end of its 15-iteration,
                              # scale-free short run, until 2026-12-05). The short run ends in
                              # a basin the refinement does not leave: on the tuning half
                              # "start" gained 3.2 % on coarse meshes, tied on global modes
                              # and concave shapes, +0.8 % on 1 mm label maps (RESULTS.md)
    "cpd_points": 6000,       # subsample size for nonrigid CPD (None: all points); with a
                              # subsample the fitted displacement field moves every vertex
                              # (CPD's E-step costs M x N per iteration: on a 10,000-vertex
                              # pair it was 11x the cost of a 2,500-vertex pair). 3,000
                              # before issue 27: on 4,500-5,500-vertex tuning populations
                              # (global, concave) all points gave a 3-13 % lower spread
    "low_rank": 80,           # rank of the kernel approximation (None: exact)
    "pose_starts": "auto",    # "auto" (identity + principal axes), "identity", "pca"
    "mirror_check": True,     # rigid fit of the mirrored target too (a left/right mix-up)
    "pose_switch": 0.35,      # "auto": a principal-axes start replaces the identity only when
                              # its rigid sigma^2 is below this fraction of the identity's
    "labelling": True,        # bijective labelling + fairing (False: nearest surface points,
                              # as plain CPD-then-project; a first pass before refinement)
    "pair_residual": True,    # the symmetric surface distance of each output (the batch
                              # measures its final outputs itself)
    "fairing_iterations": 120,  # 30 until 2026-12-06: the explicit tangential flow (step 0.5)
                              # had not spread the labelling's snapping over more than a few
                              # rings; 120 won on all 4 tuning families (mean and p95) and
                              # then on all 4 report families (ovoid -9 %, two-lobed -7 %)
    "fairing_step": 0.5,
    "fairing_candidates": 4,  # nearest triangle centroids searched by each fairing projection
                              # (the last projection is exact; 8 gave the same spread on tuning
                              # seeds, 0.544 vs 0.544 and 0.549 vs 0.551 mm on beans, at 1.5x the cost)
}


def mesh_problem(mesh: TriMesh, *, need_closed: bool = False) -> str | None:
    """Why ``mesh`` cannot be used for correspondence, or None if it can."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    if v.ndim != 2 or v.shape[1] != 3:
        return f"vertices must be (N, 3), got {v.shape}"
    if len(v) < 4:
        return f"only {len(v)} vertex{'es' if len(v) != 1 else ''}; a surface needs at least 4"
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        return f"{int(bad.sum())} vertices have NaN or infinite coordinates"
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        return "mesh has no triangles"
    if f.min() < 0 or f.max() >= len(v):
        return "faces index vertices that do not exist"
    unused = len(v) - len(np.unique(f))
    if unused:
        return f"{unused} vertices are not used by any triangle"
    pieces = meshops.n_components(f, len(v))
    if pieces > 1:
        return f"mesh has {pieces} disconnected pieces; one connected surface is needed"
    if need_closed and not meshops.is_closed(f):
        n_open = len(meshops.boundary_edges(f))
        return (f"a reference must be a closed surface, this one has {n_open} boundary edges"
                if n_open else "a reference must be a closed surface (some edges have more than 2 triangles)")
    return None


def offsets_fit(template: np.ndarray, faces: np.ndarray, target_vertices: np.ndarray,
                target_faces: np.ndarray, params: dict) -> NormalOffsetFit:
    """:func:`~core.correspondence.offsets.fit_normal_offsets` with the ``offset_*`` settings
    of ``params`` (unit-RMS units: the target normalised as :func:`correspond_pair` does)."""
    return fit_normal_offsets(template, faces, target_vertices, target_faces,
                              width=params["offset_width"], sd=params["offset_sd"],
                              noise=params["offset_noise"], iterations=params["offset_iterations"],
                              pose_iterations=params["offset_pose_iterations"],
                              pose=params["offset_pose"])


def normalise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(points centred and scaled to unit RMS radius, centre, scale): the unit-RMS units of
    every registration here."""
    centre = points.mean(axis=0)
    scale = float(np.sqrt(((points - centre) ** 2).sum(axis=1).mean()))
    return (points - centre) / scale, centre, scale


EVEN_POOL = 20  # an even subsample of n is picked from at most this many x n random points


def _subsample(points: np.ndarray, n: int, seed: int = 0, even: bool = False) -> np.ndarray:
    """``n`` of the points: a random draw, or (``even``) farthest-point picks from a random
    first one, spread evenly over the surface whatever its vertex density."""
    if len(points) <= n:
        return points
    rng = np.random.default_rng(seed)
    if even:
        from core.geometry.toolkit import farthest_point_indices

        # farthest-point picks cost n passes over the points: on EVEN_POOL x n random points
        # of a very large mesh (still dense everywhere) they stay a fraction of a second
        if len(points) > EVEN_POOL * n:
            points = points[rng.choice(len(points), EVEN_POOL * n, replace=False)]
        return points[farthest_point_indices(points, n, start=int(rng.integers(len(points))))]
    return points[rng.choice(len(points), n, replace=False)]


def principal_axes(points: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose columns are the principal axes of ``points``, longest first."""
    _, vecs = np.linalg.eigh(np.cov(points.T))
    vecs = vecs[:, ::-1]
    if np.linalg.det(vecs) < 0:
        vecs[:, 2] *= -1
    return vecs


def rigid_pose(target_n: np.ndarray, reference_n: np.ndarray, params: dict,
               parallel: bool) -> np.ndarray:
    """Similarity (4, 4) posing the normalised reference on the normalised target
    (:func:`rigid_fit`)."""
    return rigid_fit(target_n, reference_n, params, parallel)[0]


def rigid_fit(target_n: np.ndarray, reference_n: np.ndarray, params: dict, parallel: bool,
              prefer_identity: bool = True, refine: bool = True
              ) -> tuple[np.ndarray, float, bool]:
    """Similarity (4, 4) posing the normalised reference on the normalised target, the
    smallest sigma^2 of the short runs over all starts (normalised units; the best rigid fit
    whatever the orientation, for :func:`mirror_fit_ratio`), and whether a principal-axes
    start won over the identity (a switch the batch checks against the other shapes).

    Rigid CPD with scale on subsamples (``rigid_points`` of each). Starts: the identity
    (``pose_starts="identity"``), the four proper rotations aligning the reference's principal
    axes with the target's (``"pca"``), or all five (``"auto"``). Every start gets a short run.
    With ``"pca"`` the smallest sigma^2 wins. With ``"auto"`` the identity is kept unless a
    principal-axes start fits far better (sigma^2 below ``pose_switch`` times the
    identity's): inputs in scanner coordinates share the patient's axes, and a nearly
    symmetric shape fits about as well or better flipped end to end. Measured on the bent
    tubes of :mod:`core.datasets.shapes` (all within 45 degrees of one pose, so every
    switch is a flip): the flipped pose had 0.41-1.0 times the right pose's sigma^2 over 25
    pairs (the ring has an exact 180-degree symmetry), so "smallest sigma^2 wins" flips them
    and ruins the homologies; a bean turned far (120-180 degrees) has 0.15-0.6 times the
    identity start's sigma^2 in its right pose. No threshold separates the two: the default
    keeps the input orientation unless the evidence is overwhelming (a far-rotated bean is
    then found only for some rotations); inputs in arbitrary orientations should use
    ``pose_starts="pca"``.
    ``prefer_identity=False``: the smallest sigma^2 wins in ``"auto"`` too; ``refine=False``:
    the chosen start's short run, without the final refinement.
    """
    for key in ("rigid_sampling", "rigid_fine_sampling"):
        if params[key] not in ("random", "even"):
            raise ValueError(f"{key} must be 'random' or 'even', got {params[key]!r}")
    even_starts = params["rigid_sampling"] == "even"
    tgt = _subsample(target_n, params["rigid_points"], 1, even_starts)
    ref = _subsample(reference_n, params["rigid_points"], 2, even_starts)
    mode = params["pose_starts"]
    if mode not in ("auto", "identity", "pca"):
        raise ValueError(f"pose_starts must be 'auto', 'identity' or 'pca', got {mode!r}")
    if params["rigid_fine_from"] not in ("run", "start"):
        raise ValueError(f"rigid_fine_from must be 'run' or 'start', got {params['rigid_fine_from']!r}")
    starts = [np.eye(3)] if mode in ("identity", "auto") else []
    if mode in ("pca", "auto"):
        axes_t = principal_axes(target_n)
        axes_r = principal_axes(reference_n)
        flips = [np.diag(d) for d in ([1, 1, 1], [-1, -1, 1], [-1, 1, -1], [1, -1, -1])]
        starts += [axes_t @ f @ axes_r.T for f in flips]
    fits = []
    for rot in starts:
        # Without scale: both sets have unit RMS radius, and a free scale lets a shrunken,
        # wrongly oriented reference fit inside the target almost as well as the right pose.
        r = cpd_rigid(tgt, ref @ rot.T, scaling=len(starts) == 1, w=params["w"],
                      tolerance=params["tolerance"],
                      max_iterations=15 if len(starts) > 1 else params["rigid_iterations"],
                      parallel=parallel)
        start = np.eye(4)
        start[:3, :3] = rot
        fits.append((r.sigma2, _matrix(r) @ start))
    best = min(range(len(fits)), key=lambda i: fits[i][0])
    switch = float(params["pose_switch"])
    lowest = min(f[0] for f in fits)  # of the short runs (mirror_fit_ratio compares these)
    if (refine and prefer_identity and mode == "auto" and best != 0
            and fits[best][0] < switch * fits[0][0]):
        # Before switching, the identity start gets the full iterations: after 15 it can be
        # far from converged where a principal-axes start is not (a 2,000-vertex bent tube:
        # the identity's short run had over 1/0.35 times the sigma^2 of the flipped start,
        # fully run it ends 3 degrees from the truth, the flip 180).
        r = cpd_rigid(tgt, ref, scaling=False, w=params["w"], tolerance=params["tolerance"],
                      max_iterations=params["rigid_iterations"], parallel=parallel)
        fits[0] = (min(fits[0][0], r.sigma2), _matrix(r) if r.sigma2 < fits[0][0] else fits[0][1])
    if (prefer_identity and mode == "auto"
            and fits[best][0] >= switch * fits[0][0]):
        best = 0  # the identity start, unless clearly beaten
    matrix = fits[best][1]
    switched = mode == "auto" and best != 0
    if not refine:
        return matrix, float(lowest), switched
    # The chosen start is refined on ``rigid_fine_points`` points: a pose from 500-point
    # subsamples left the nonrigid step a worse start (measured on beans: 1.01 vs 0.86 mm
    # mean error against the truth for one reference).
    n_fine = max(int(params["rigid_points"]), int(params["rigid_fine_points"]))
    even_fine = params["rigid_fine_sampling"] == "even"
    tgt_f = _subsample(target_n, n_fine, 3, even_fine)
    ref_f = _subsample(reference_n, n_fine, 4, even_fine)
    if params["rigid_fine_from"] == "start":
        matrix = np.eye(4)
        matrix[:3, :3] = starts[best]
    r = cpd_rigid(tgt_f, ref_f @ matrix[:3, :3].T + matrix[:3, 3], scaling=True, w=params["w"],
                  tolerance=params["tolerance"], max_iterations=params["rigid_iterations"],
                  parallel=parallel)
    matrix = _matrix(r) @ matrix
    return matrix, float(lowest), switched


def _matrix(result: CPDResult) -> np.ndarray:
    """The (4, 4) matrix of a rigid CPD result (always set by :func:`cpd_rigid`)."""
    if result.matrix is None:
        raise ValueError("a rigid CPD result has no matrix")
    return result.matrix


def mirror_fit_ratio(reference: np.ndarray, target: np.ndarray, params: dict | None = None,
                     parallel: bool = True, proper: float | None = None) -> float:
    """How well the target's mirror image fits the reference, relative to the target itself:
    best rigid CPD sigma^2 (short runs from every start, :func:`rigid_fit`) of the
    normalised reference onto the mirrored target over the same onto the target (``proper``,
    when already known).

    Below 1 the target fits better mirrored: for a chiral structure, a left/right mix-up
    (measured on the twisted beans of :mod:`core.datasets.shapes`: 1.2-1.6 for
    correctly sided shapes, 0.6-0.8 for mirrored ones). A nearly achiral shape stays near 1
    either way, and cannot be told (nor does its side matter much to the model).
    """
    p = dict(DEFAULT_CPD_PARAMS)
    p.update(params or {})
    p["pose_starts"] = "auto"
    yn, _, _ = normalise(np.asarray(reference, dtype=np.float64))
    xn, _, _ = normalise(np.asarray(target, dtype=np.float64))
    if proper is None:
        proper = rigid_fit(xn, yn, p, parallel, refine=False)[1]
    mirrored = rigid_fit(xn * np.array([-1.0, 1.0, 1.0]), yn, p, parallel, refine=False)[1]
    return mirrored / max(proper, 1e-300)


def correspond_pair(reference: TriMesh, target: TriMesh, params: dict | None = None,
                    parallel: bool = True, posed: np.ndarray | None = None) -> dict:
    """Correspond one target mesh to the reference (steps 1-5 of the package docstring).

    ``posed`` (M, 3), optional: the reference's vertices already posed on the target (world
    mm), e.g. by a similarity from an earlier correspondence; the rigid CPD step is skipped.

    Returns
    -------
    dict
        ``vertices`` (M, 3) on the target, with the reference's vertex order; ``residual_mm``
        (None with ``pair_residual=False``);
        ``sigma2`` (mm^2: CPD's, or the offsets' fit's mean squared point-to-plane
        residual); ``n_iter``; ``mirror_ratio`` (:func:`mirror_fit_ratio`, None
        when not checked); ``pose_switched`` (a principal-axes start replaced the input's
        orientation); ``timings`` (seconds per step).
    """
    p = dict(DEFAULT_CPD_PARAMS)
    p.update(params or {})
    times = {}
    t0 = time.perf_counter()
    ref_v = np.asarray(reference.vertices, dtype=np.float64)
    ref_f = np.asarray(reference.faces)
    tgt_v = np.asarray(target.vertices, dtype=np.float64)
    tgt_f = np.asarray(target.faces)
    xn, centre, scale = normalise(tgt_v)
    mirror = None
    switched = False
    if posed is None:
        yn, _, _ = normalise(ref_v)
        pose, lowest, switched = rigid_fit(xn, yn, p, parallel)
        y_posed = yn @ pose[:3, :3].T + pose[:3, 3]
        if p["mirror_check"] and p["pose_starts"] == "auto":
            mirror = mirror_fit_ratio(ref_v, tgt_v, p, parallel, proper=lowest)
    else:
        y_posed = (np.asarray(posed, dtype=np.float64) - centre) / scale
    t1 = time.perf_counter()
    times["rigid"] = t1 - t0
    if p["deformation"] == "normal_offsets":
        fit = offsets_fit(y_posed, ref_f, xn, tgt_f, p)
        moved, sigma2, n_iter = fit.points, fit.residual2, fit.n_iter
    else:
        moved, nonrigid = _deform(xn, y_posed, p, parallel)
        sigma2, n_iter = nonrigid.sigma2, nonrigid.n_iter
    t2 = time.perf_counter()
    times["nonrigid"] = t2 - t1
    if p["labelling"]:
        labelled = label_points(moved, xn, tgt_f, sigma2, p["w"])
    t3 = time.perf_counter()
    times["assignment"] = t3 - t2
    if p["labelling"]:
        projector = SurfaceProjector(xn, tgt_f, k=int(p["fairing_candidates"]), exact=False,
                                     candidates="centroids")
        faired = meshops.fair_mesh(labelled, ref_f, projector, rest_vertices=y_posed,
                                   iterations=p["fairing_iterations"], step=p["fairing_step"])
        faired, _ = SurfaceProjector(xn, tgt_f)(faired)  # final exact projection
    else:
        faired, _ = SurfaceProjector(xn, tgt_f)(moved)
    t4 = time.perf_counter()
    times["fairing"] = t4 - t3
    vertices = faired * scale + centre
    residual = (symmetric_surface_distance(vertices, ref_f, tgt_v, tgt_f)
                if p["pair_residual"] else None)
    times["residual"] = time.perf_counter() - t4
    times["total"] = time.perf_counter() - t0
    return {"vertices": vertices, "residual_mm": residual, "sigma2": sigma2 * scale ** 2,
            "n_iter": n_iter, "mirror_ratio": mirror, "pose_switched": switched,
            "timings": times}


def _deform(xn: np.ndarray, y_posed: np.ndarray, p: dict, parallel: bool):
    """Nonrigid CPD of the posed reference onto the target (normalised units): moved points."""
    n_cpd = p["cpd_points"]
    x_cpd = xn if n_cpd is None else _subsample(xn, int(n_cpd), 3)
    y_cpd = y_posed if n_cpd is None else _subsample(y_posed, int(n_cpd), 4)
    # Pivoted Cholesky for the low-rank kernel also with a subsample: its Nystrom extension
    # reproduced the moved points to 1e-3 of the point spacing on a 3,000-point subsample
    # of a 10,000-vertex pair, and "eigen" (a dense eigendecomposition) took 8x longer.
    nonrigid = cpd_nonrigid(x_cpd, y_cpd, w=p["w"], beta=p["beta"], lam=p["lam"],
                            tolerance=p["tolerance"], max_iterations=p["max_iterations"],
                            low_rank=p["low_rank"], parallel=parallel,
                            low_rank_method="pivoted_cholesky")
    if len(y_cpd) == len(y_posed):
        return nonrigid.points, nonrigid
    return nonrigid.warp(y_posed), nonrigid


def label_points(moved: np.ndarray, vertices: np.ndarray, faces: np.ndarray, sigma2: float,
                 w: float = 0.0) -> np.ndarray:
    """The bijective labelling (M, 3): for each moved point, its distinct target point.

    Temperature: CPD's final sigma^2 can be tiny; it is floored at a fraction of the point
    spacing so that the log posterior stays informative (it only rescales the distance term).
    """
    candidates = labelling_candidates(moved, vertices, faces, spare=True)
    spacing2 = meshops.mean_edge_length(vertices, faces) ** 2
    rows, cols = auction_assign(moved, candidates, max(sigma2, 0.05 * spacing2), w)
    labelled = np.empty_like(moved)
    labelled[rows] = candidates[cols]
    return labelled

