"""Multi-image registration into an unbiased common space by transformation synchronisation.

Bernard, Thunberg, Gemmar, Hertel, Husch, Goncalves: "Transitively consistent and unbiased
multi-image registration using numerically stable transformation synchronisation", MICCAI
workshop on spectral analysis in medical imaging, 2015 (thesis chapter 7). Pairwise linear
registrations of N images (``core.registration.volumes``: mutual information, multi-resolution) give
noisy transforms T_ij (image j -> image i) that are not transitively consistent
(T_ij T_jk != T_ik). The numerically stable synchronisation of ``core.alignment.transforms``
(:func:`core.alignment.transforms.synchronize_transforms`: the linear parts spectrally, the translations
by least squares) turns them into N absolute transforms into one common space, consistent by
construction, with no image as reference; every pair's noise is averaged out. The baseline,
``method="reference"``, registers every image to one reference image only (biased towards it).

Steps of :func:`register_images`:

1. inspect every image (read by path in the workers): an unreadable image is reported and left
   out; foreground samples (world points above the intensity's Otsu threshold) give a pose
   descriptor and the points on which residuals are measured;
2. pairwise registrations over the pair graph: ``all`` pairs i < j (the transform j -> i; the
   reverse is its inverse), or ``knn:K`` (each image with its K nearest by pose descriptor --
   centre of mass and principal extents -- plus links that keep the graph connected); every
   pair is one job of :func:`core.runtime.parallel.run_jobs` (process pool or Dask);
3. robust synchronisation: a pair whose registration failed is left out; after synchronising,
   each pair's residual (mean distance, mm, over the moving image's foreground samples, between
   the pair's own transform and the synchronised one) is compared with the others', and pairs
   beyond ``max(outlier_mm, median + 5 MAD)`` are dropped (worst first, never disconnecting the
   graph) and the rest re-synchronised, until none is left (all reported);
4. every image resampled into the common space (a grid covering the mapped foregrounds, at the
   finest input spacing unless given), and their mean -- intensities normalised by each image's
   99th foreground percentile -- the unbiased template.

Conventions: RAS mm, 4x4 matrices on column vectors. ``transforms[k]`` maps image k's world to
the common space; ``pairwise[i][j]`` maps image j's world onto image i's (as in
``core.alignment.transforms``).
"""

from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from core.alignment.transforms import synchronize_transforms
from core.runtime.failures import EXPECTED_ERRORS, describe_failure
from core.runtime.parallel import resolve_jobs, run_jobs, runs_inline
from core.runtime.progress import ProgressCallback, report, sub_progress

METHODS = ("sync", "reference")
N_SAMPLES = 2000


@dataclass
class MultiRegistrationResult:
    """Outcome of :func:`register_images` (JSON form: :meth:`to_dict`)."""

    paths: list
    method: str
    transform: str
    transforms: np.ndarray  # (N, 4, 4), NaN for images left out
    ok: list
    image_errors: dict
    pairs: list  # dicts: i, j, transform, metric, seconds, residual_mm, used, note
    reference: int | None = None
    grid_affine: np.ndarray | None = None
    grid_shape: tuple | None = None
    outputs: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)

    def pairwise_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, N, 4, 4) pairwise transforms (j -> i) and their (N, N) mask of used pairs."""
        n = len(self.paths)
        p = np.tile(np.eye(4), (n, n, 1, 1))
        mask = np.zeros((n, n), bool)
        for pair in self.pairs:
            if pair["transform"] is None or not pair["used"]:
                continue
            i, j, t = pair["i"], pair["j"], np.asarray(pair["transform"])
            p[i, j], p[j, i] = t, np.linalg.inv(t)
            mask[i, j] = mask[j, i] = True
        return p, mask

    def to_dict(self) -> dict[str, Any]:
        def mat(t):
            return None if t is None or not np.all(np.isfinite(t)) else np.asarray(t).tolist()

        return {
            "convention": "4x4 RAS mm matrices acting on column vectors; images[k].transform "
                          "maps image k world -> common space; pairs[].transform maps image j "
                          "world -> image i world",
            "method": self.method, "transform_class": self.transform,
            "reference": None if self.reference is None else str(self.paths[self.reference]),
            "images": [{"path": str(p), "ok": bool(self.ok[k]), "transform": mat(self.transforms[k]),
                        "error": self.image_errors.get(k),
                        "resampled": self.outputs.get("resampled", {}).get(k)}
                       for k, p in enumerate(self.paths)],
            "pairs": [{**{k: v for k, v in pair.items() if k != "transform"},
                       "fixed": str(self.paths[pair["i"]]), "moving": str(self.paths[pair["j"]]),
                       "transform": mat(pair["transform"])} for pair in self.pairs],
            "common_grid": None if self.grid_affine is None else
            {"affine": self.grid_affine.tolist(), "shape": list(self.grid_shape or ())},
            "template": self.outputs.get("template"),
            "timings": self.timings,
        }


# ----------------------------------------------------------------------------- worker jobs

@functools.lru_cache(maxsize=4)
def _load(path: str):
    """Image by path (a worker keeps the last few: pair jobs reuse them)."""
    from core.io import load_volume

    return load_volume(path)


def _foreground_samples(data: np.ndarray, affine: np.ndarray, n: int, seed: int) -> np.ndarray:
    """World points of voxels above the Otsu threshold (n of them, seeded)."""
    values = data[data > 0] if np.any(data > 0) else data.ravel()
    hist, edges = np.histogram(values, bins=128)
    centres = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    threshold = centres[np.argmax(w0 * w1 * (mu0 - mu1) ** 2)]  # Otsu 1979
    idx = np.flatnonzero(data.ravel() > threshold)
    if len(idx) == 0:
        raise ValueError("the image has no foreground (constant intensities)")
    rng = np.random.default_rng(seed)
    pick = rng.choice(idx, size=min(n, len(idx)), replace=False)
    ijk = np.column_stack(np.unravel_index(pick, data.shape)).astype(np.float64)
    return ijk @ affine[:3, :3].T + affine[:3, 3]


def _inspect_job(arg, common) -> dict:
    index, path = arg
    try:
        vol = _load(path)
        pts = _foreground_samples(np.asarray(vol.data, dtype=np.float32), vol.affine, N_SAMPLES, index)
        fg = np.asarray(vol.data)[np.asarray(vol.data) > 0]
        scale = float(np.percentile(fg, 99)) if fg.size else 1.0
        return {"ok": True, "samples": pts, "spacing": float(vol.spacing.min()), "scale": scale,
                "shape": vol.shape}
    except Exception as exc:  # reported per image, the rest go on; a bug with its traceback
        return {"ok": False,
                "error": str(exc) if isinstance(exc, EXPECTED_ERRORS) else describe_failure(exc)}


def _pair_job(arg, common) -> dict:
    from core.registration.volumes import register_volumes

    i, j = arg
    t0 = time.perf_counter()
    try:
        kwargs = dict(common["kwargs"])
        # Own samples per pair: shared sample positions would make the errors of all
        # registrations onto one image alike (a bias that synchronisation cannot average).
        kwargs["random_state"] = int(kwargs.get("random_state", 0)) + 7919 * i + 104729 * j
        res = register_volumes(_load(common["paths"][j]), _load(common["paths"][i]),
                               common["transform"], threads=common["threads"], **kwargs)
        return {"i": i, "j": j, "transform": res.transform, "metric": res.metric,
                "initial_metric": res.initial_metric, "seconds": time.perf_counter() - t0,
                "error": None}
    except Exception as exc:  # a failed pair is reported and left out; a bug with its traceback
        return {"i": i, "j": j, "transform": None, "metric": None, "initial_metric": None,
                "seconds": time.perf_counter() - t0, "error": describe_failure(exc)}


def _resample_job(arg, common) -> dict:
    from core.io import save_volume
    from core.registration.volumes import resample

    k, transform, out_path = arg
    vol = _load(common["paths"][k])
    data = resample(np.asarray(vol.data, dtype=np.float32), vol.affine, transform,
                    common["shape"], common["affine"])
    save_volume(out_path, data, common["affine"])
    return {"k": k, "path": str(out_path)}


# ----------------------------------------------------------------------------- pair graph

def _components(n: int, edges: set) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not edges:
        return np.arange(n)
    e = np.array(sorted(edges))
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def knn_pairs(descriptors: np.ndarray, k: int) -> list[tuple[int, int]]:
    """Pairs (i < j): each item with its ``k`` nearest (Euclidean on standardised descriptors),
    plus the shortest links that join the graph's components into one."""
    from scipy.spatial import cKDTree

    d = np.asarray(descriptors, dtype=np.float64)
    n = len(d)
    if n < 2:
        return []
    d = (d - d.mean(axis=0)) / np.maximum(d.std(axis=0), 1e-12)
    k = max(1, min(int(k), n - 1))
    _, nn = cKDTree(d).query(d, k=k + 1)
    edges = {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in nn[i, 1:] if int(j) != i}
    labels = _components(n, edges)
    while labels.max() > 0:  # join component 0 to its nearest other component
        inside = np.flatnonzero(labels == 0)
        outside = np.flatnonzero(labels != 0)
        dist, idx = cKDTree(d[outside]).query(d[inside])
        a = int(inside[np.argmin(dist)])
        b = int(outside[idx[np.argmin(dist)]])
        edges.add((min(a, b), max(a, b)))
        labels = _components(n, edges)
    return sorted(edges)


def parse_pairs(value: str) -> tuple[str, int]:
    """``all`` or ``knn:K`` -> ("all", 0) / ("knn", K)."""
    if value == "all":
        return "all", 0
    if value.startswith("knn:") and value[4:].isdigit() and int(value[4:]) >= 1:
        return "knn", int(value[4:])
    raise ValueError(f"--pairs must be 'all' or 'knn:K' with K >= 1, got {value!r}")


def pose_descriptor(samples: np.ndarray) -> np.ndarray:
    """Centre of mass and principal extents (sqrt eigenvalues) of foreground samples, (6,)."""
    centre = samples.mean(axis=0)
    ext = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov((samples - centre).T)), 0.0))
    return np.concatenate([centre, ext])


# ----------------------------------------------------------------------------- synchronisation

def pair_residuals(transforms: np.ndarray, pairs: Sequence[tuple[int, int, np.ndarray]],
                   samples: Sequence[np.ndarray]) -> np.ndarray:
    """Per pair (i, j, T_ij): mean distance (mm) over image j's samples between T_ij and the
    synchronised map T_i^-1 T_j."""
    out = np.empty(len(pairs))
    for n, (i, j, t) in enumerate(pairs):
        implied = np.linalg.inv(transforms[i]) @ transforms[j]
        diff = (t - implied)[:3]
        x = samples[j]
        out[n] = float(np.linalg.norm(x @ diff[:, :3].T + diff[:, 3], axis=1).mean())
    return out


def robust_synchronize(n: int, pairs: Sequence[tuple[int, int, np.ndarray]],
                       samples: Sequence[np.ndarray], transform: str, *,
                       outlier_mm: float = 3.0, max_rounds: int = 10
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synchronise pairwise transforms (i, j, T_ij: j -> i) of ``n`` items, dropping outliers.

    Returns (transforms (n, 4, 4), used (P,) bool, residual_mm (P,)). Residuals are those of
    the final synchronisation, also for the dropped pairs.
    """
    used = np.ones(len(pairs), bool)
    # Centre each item on its samples' centroid first (C_k = translation by -c_k): with
    # scanner coordinates far from the origin, the linear parts' noise would otherwise be
    # amplified by the distance to the origin when the translations are solved for.
    centring = np.tile(np.eye(4), (n, 1, 1))
    centring[:, :3, 3] = -np.stack([s.mean(axis=0) for s in samples])
    uncentre = np.linalg.inv(centring)
    centred = [centring[i] @ np.asarray(t) @ uncentre[j] for i, j, t in pairs]
    for _ in range(max_rounds + 1):
        p = np.tile(np.eye(4), (n, n, 1, 1))
        mask = np.zeros((n, n), bool)
        measured = np.zeros((n, n), bool)
        for (i, j, _t), t, u in zip(pairs, centred, used):
            if u:
                p[i, j] = t  # a measured block always wins over the inverse of the other one
                measured[i, j] = mask[i, j] = mask[j, i] = True
                if not measured[j, i]:
                    p[j, i] = np.linalg.inv(t)
        transforms = synchronize_transforms(p, transform, mask=mask, stable=True) @ centring
        resid = pair_residuals(transforms, pairs, samples)
        med = float(np.median(resid[used]))
        mad = float(np.median(np.abs(resid[used] - med))) * 1.4826
        limit = max(float(outlier_mm), med + 5.0 * mad)
        candidates = [q for q in np.argsort(-resid) if used[q] and resid[q] > limit]
        dropped = False
        for q in candidates:  # worst first; keep the graph connected
            trial = used.copy()
            trial[q] = False
            edges = {(pairs[int(m)][0], pairs[int(m)][1]) for m in np.flatnonzero(trial)}
            if _components(n, edges).max() == 0:
                used = trial
                dropped = True
                break
        if not dropped:
            return transforms, used, resid
    return transforms, used, resid


# ----------------------------------------------------------------------------- front end

def _common_grid(samples: list[np.ndarray], transforms: np.ndarray, spacing: float,
                 margin: float = 10.0) -> tuple[np.ndarray, tuple[int, int, int]]:
    pts = np.concatenate([s @ t[:3, :3].T + t[:3, 3] for s, t in zip(samples, transforms)])
    lo = np.percentile(pts, 0.5, axis=0) - margin
    hi = np.percentile(pts, 99.5, axis=0) + margin
    shape = tuple(int(v) for v in np.ceil((hi - lo) / spacing) + 1)
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = lo
    return affine, shape  # type: ignore[return-value]


def register_images(paths: Sequence[str | os.PathLike], transform: str = "affine", *,
                    method: str = "sync", reference: int | None = None, pairs: str = "all",
                    out_dir: str | os.PathLike | None = None, spacing: float | None = None,
                    outlier_mm: float = 3.0, both_directions: bool = True,
                    n_jobs: int | None = None,
                    registration: dict | None = None,
                    progress: ProgressCallback | None = None) -> MultiRegistrationResult:
    """Register images into one common space (see the module docstring).

    Parameters
    ----------
    paths : image files (any format ``core.io.load_volume`` reads); read by the workers.
    transform : {"rigid", "similarity", "affine"}
    method : ``sync`` (pairwise + synchronisation, reference-free) or ``reference``
        (every image registered to ``reference``).
    reference : index of the reference image (``reference`` method; default 0). With ``sync``
        it is ignored.
    pairs : ``all`` or ``knn:K`` (sync only).
    out_dir : where to write ``resampled/`` and ``template.nii.gz`` (None: nothing written).
    spacing : common grid spacing in mm (default: the finest input spacing).
    outlier_mm : pairs whose residual exceeds this (and the robust spread of the others) are
        dropped.
    n_jobs : pool processes (ignored on a Dask scheduler set by ``core.runtime.parallel.use_scheduler``).
    registration : keyword arguments of :func:`core.registration.volumes.register` (levels_mm, ...).
    progress : ``progress(fraction, message)``; may raise ``Cancelled``.
    """
    kind, k_nn = _check_options(transform, method, pairs)
    files = [str(p) for p in paths]
    n = len(files)
    if n < 2:
        raise ValueError(f"at least 2 images are needed, got {n}")
    t_start = time.perf_counter()
    timings: dict[str, float] = {}

    # 1. inspect
    report(progress, 0.0, "reading images")
    info, ok, image_errors = _inspect_images(files, n_jobs, sub_progress(progress, 0.0, 0.05))
    good = [k for k in range(n) if ok[k]]
    samples = {k: info[k]["samples"] for k in good}
    timings["inspect"] = time.perf_counter() - t_start

    # 2. pair graph and pairwise registrations
    ref, graph = _pair_graph(method, kind, k_nn, reference, files, good, ok, image_errors,
                             samples)
    if method == "sync" and both_directions:
        # Each pair registered both ways: registrations onto one fixed image share its noise
        # and sampling, an error common to all of them that the reverse direction balances.
        graph = graph + [(j, i) for i, j in graph]
    t0 = time.perf_counter()
    pair_list = _register_pairs(graph, files, transform, registration, n_jobs,
                                sub_progress(progress, 0.05, 0.85))
    timings["pairwise"] = time.perf_counter() - t0

    # 3. synchronise (or chain to the reference)
    if method == "reference":
        assert ref is not None  # _pair_graph returns the reference method's reference image
        transforms = _chain_to_reference(pair_list, ref, n, ok, image_errors)
    else:
        transforms = _synchronise_pairs(pair_list, good, samples, n, ok, image_errors,
                                        transform, outlier_mm)
    result = MultiRegistrationResult(paths=files, method=method, transform=transform,
                                     transforms=transforms, ok=ok, image_errors=image_errors,
                                     pairs=[{k: pr[k] for k in _PAIR_FIELDS} for pr in pair_list],
                                     reference=ref)
    placed = [k for k in range(n) if ok[k]]
    grid_spacing = float(spacing) if spacing else min(info[k]["spacing"] for k in placed)
    affine, shape = _common_grid([samples[k] for k in placed], transforms[placed], grid_spacing)
    result.grid_affine, result.grid_shape = affine, shape

    # 4. resample and average
    if out_dir is not None:
        t0 = time.perf_counter()
        result.outputs = _resample_and_average(Path(out_dir), files, placed, transforms,
                                               {k: info[k]["scale"] for k in placed},
                                               affine, shape, n_jobs,
                                               sub_progress(progress, 0.85, 1.0))
        timings["resample"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    timings["n_jobs"] = resolve_jobs(n_jobs)
    result.timings = timings
    report(progress, 1.0, "done")
    return result


_PAIR_FIELDS = ("i", "j", "transform", "metric", "initial_metric", "seconds", "residual_mm",
                "used", "note")


def _check_options(transform: str, method: str, pairs: str) -> tuple[str, int]:
    """The pair-graph kind and K of ``pairs``, after checking the transform and method."""
    from core.registration.volumes import TRANSFORMS

    if transform not in TRANSFORMS:
        raise ValueError(f"transform must be one of {', '.join(TRANSFORMS)}; got {transform!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
    return parse_pairs(pairs)


def _inspect_images(paths: list[str], n_jobs: int | None, progress: ProgressCallback | None
                    ) -> tuple[dict, list[bool], dict[int, str]]:
    """Step 1: every image read in a worker; (per-image info, ok flags, errors by index)."""
    n = len(paths)
    info = run_jobs(_inspect_job, [(k, (k, p)) for k, p in enumerate(paths)], n_jobs=n_jobs,
                    progress=progress, label="images read")
    ok = [bool(info[k]["ok"]) for k in range(n)]
    image_errors = {k: info[k]["error"] for k in range(n) if not ok[k]}
    if sum(ok) < 2:
        raise ValueError("fewer than 2 readable images: "
                         + "; ".join(f"{paths[k]}: {e}" for k, e in image_errors.items()))
    return info, ok, image_errors


def _pair_graph(method: str, kind: str, k_nn: int, reference: int | None, paths: list[str],
                good: list[int], ok: list[bool], image_errors: dict, samples: dict
                ) -> tuple[int | None, list[tuple[int, int]]]:
    """Step 2: (the reference index or None, the pairs (fixed i, moving j) to register)."""
    if method == "reference":
        ref = 0 if reference is None else int(reference)
        if not 0 <= ref < len(paths):
            raise ValueError(f"reference index {ref} out of range for {len(paths)} images")
        if not ok[ref]:
            raise ValueError(f"the reference image {paths[ref]} cannot be used: {image_errors[ref]}")
        return ref, [(ref, k) for k in good if k != ref]
    if kind == "all":
        return None, [(a, b) for ai, a in enumerate(good) for b in good[ai + 1:]]
    desc = np.stack([pose_descriptor(samples[k]) for k in good])
    return None, [(good[a], good[b]) for a, b in knn_pairs(desc, k_nn)]


def _register_pairs(graph: list[tuple[int, int]], paths: list[str], transform: str,
                    registration: dict | None, n_jobs: int | None,
                    progress: ProgressCallback | None) -> list[dict]:
    """Every pair of ``graph`` registered as one job (images read by path in the workers);
    the pair records, with ``used``/``note`` set for failed registrations."""
    inline = runs_inline(n_jobs, len(graph))
    common = {"paths": paths, "transform": transform, "kwargs": dict(registration or {}),
              "threads": None if inline else 1}
    out = run_jobs(_pair_job, [((i, j), (i, j)) for i, j in graph], common=common, n_jobs=n_jobs,
                   progress=progress, label="pairs registered")
    pair_list = [out[(i, j)] for i, j in graph]
    for pr in pair_list:
        pr["used"] = pr["transform"] is not None
        pr["residual_mm"] = None
        pr["note"] = None if pr["used"] else f"registration failed: {pr['error']}"
    return pair_list


def _chain_to_reference(pair_list: list[dict], ref: int, n: int, ok: list[bool],
                        image_errors: dict) -> np.ndarray:
    """Step 3, reference method: each image's transform is its registration to the reference."""
    transforms = np.full((n, 4, 4), np.nan)
    transforms[ref] = np.eye(4)
    for pr in pair_list:
        if pr["used"]:
            transforms[pr["j"]] = pr["transform"]
            pr["residual_mm"] = 0.0  # the chain uses every pair as is
        else:
            ok[pr["j"]] = False
            image_errors[pr["j"]] = f"registration to the reference failed: {pr['error']}"
    return transforms


def _linked_images(usable: list[dict], good: list[int], n: int, ok: list[bool],
                   image_errors: dict) -> list[int]:
    """The largest group of images linked by successful registrations; the others cannot be
    placed (marked not ok, with the reason)."""
    members = sorted({pr["i"] for pr in usable} | {pr["j"] for pr in usable})
    labels = _components(n, {(pr["i"], pr["j"]) for pr in usable})
    if members:
        sizes = np.bincount(labels[members], minlength=labels.max() + 1)
        main = int(np.argmax(sizes))
        members = [k for k in members if labels[k] == main]
    for k in good:
        if k not in members:
            ok[k] = False
            image_errors[k] = "no successful registration links this image to the others"
    if len(members) < 2:
        raise ValueError("no two images could be registered to each other")
    return members


def _synchronise_pairs(pair_list: list[dict], good: list[int], samples: dict, n: int,
                       ok: list[bool], image_errors: dict, transform: str, outlier_mm: float
                       ) -> np.ndarray:
    """Step 3, sync method: robust synchronisation of the linked images' pairs; each pair
    record gets its residual, and a note when it was dropped as an outlier."""
    usable = [pr for pr in pair_list if pr["used"]]
    members = _linked_images(usable, good, n, ok, image_errors)
    index = {k: m for m, k in enumerate(members)}
    inside = [pr for pr in usable if pr["i"] in index and pr["j"] in index]
    sub = [(index[pr["i"]], index[pr["j"]], np.asarray(pr["transform"])) for pr in inside]
    t_sync, used, resid = robust_synchronize(len(members), sub, [samples[k] for k in members],
                                             transform, outlier_mm=outlier_mm)
    transforms = np.full((n, 4, 4), np.nan)
    transforms[members] = t_sync
    med = float(np.median(resid[used]))
    for q, pr in enumerate(inside):
        pr["residual_mm"] = float(resid[q])
        if not used[q]:
            pr["used"] = False
            pr["note"] = (f"dropped: residual {resid[q]:.2f} mm against a median of "
                          f"{med:.2f} mm (disagrees with the other pairs)")
    return transforms


def _resample_and_average(out_dir: Path, paths: list[str], placed: list[int],
                          transforms: np.ndarray, scales: dict[int, float], affine: np.ndarray,
                          shape: tuple, n_jobs: int | None, progress: ProgressCallback | None
                          ) -> dict:
    """Step 4: every placed image resampled into the common grid (in the workers, written as
    it arrives) and the mean of their normalised intensities, the template."""
    from core.io import load_volume, save_volume

    (out_dir / "resampled").mkdir(parents=True, exist_ok=True)
    names = _output_names(paths)
    total = np.zeros(shape, np.float64)
    written: dict[int, str] = {}

    def accumulate(key, value):
        vol = load_volume(value["path"])  # one volume at a time in memory
        total[...] += np.asarray(vol.data, np.float64) / max(scales[key], 1e-12)
        written[key] = value["path"]
        return value["path"]

    run_jobs(_resample_job, [(k, (k, transforms[k], str(out_dir / "resampled" / names[k])))
                             for k in placed],
             common={"paths": paths, "shape": shape, "affine": affine}, n_jobs=n_jobs,
             on_result=accumulate, progress=progress, label="images resampled")
    template_path = out_dir / "template.nii.gz"
    save_volume(template_path, (total / len(placed)).astype(np.float32), affine)
    return {"resampled": written, "template": str(template_path)}


def _output_names(paths: Sequence[str]) -> list[str]:
    names, used = [], set()
    for p in paths:
        base = Path(p).name
        for suffix in (".nii.gz", ".nii", ".nrrd", ".mha", ".mhd", ".gz"):
            if base.lower().endswith(suffix):
                base = base[: -len(suffix)]
                break
        name, n = base, 1
        while name in used:
            n += 1
            name = f"{base}_{n}"
        used.add(name)
        names.append(name + ".nii.gz")
    return names
