"""Correspondence of a whole training set: grooming, reference choice, pairwise runs, refinement.

The batch layer of Bernard et al., SPIE MI 2016 (the package docstring has the method): it
grooms every input (:mod:`core.correspondence.grooming`), picks a representative reference, corresponds
every shape to it in a process pool, flags shapes that lie far from all others, and
refines groupwise: every shape is corresponded again to the evolving mean shape (as
population-based methods do; Heimann & Meinzer, Medical Image Analysis 2009), which removes
most of the reference's bias.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass, field

import numpy as np

from core.geometry import mesh as meshops
from core.alignment.transforms import apply_transform, fit_transform
from core.correspondence.pair import (DEFAULT_CPD_PARAMS, _normalise, _principal_axes, _task,
                                     mesh_problem, mirror_fit_ratio)
from core.correspondence.grooming import GroomingError, describe, groom_mesh
from core.correspondence.store import (InputFile, Scratch, VertexRows, open_mesh,
                                      open_rows, read_input, write_scratch_mesh)
from core.runtime.parallel import JobError, preload_in_workers, run_jobs, runs_inline
from core.runtime.progress import ProgressCallback, report, sub_progress
from core.types import TriMesh

preload_in_workers(__name__)  # per-shape jobs: workers start with this module imported


@dataclass
class CorrespondenceResult:
    """Corresponded training meshes.

    Attributes
    ----------
    meshes : list of TriMesh or None
        One per input, None where it failed. All others share ``faces`` and vertex i is
        homologous across them.
    reference_index : int or None
        Index of the chosen reference among the inputs (None for an external reference).
    reference_name : str
    faces : (F, 3) int
        The reference's faces (after grooming).
    residuals_mm : list of float or None
        Symmetric mean surface distance (mm) between each output and its (groomed) input.
    failures : dict
        Mesh name -> reason, for every input that failed.
    timings : dict
        Seconds: ``total``, ``per_shape_mean``, ``per_shape_max``, ``cpu_total`` (sum over all
        registrations), ``assignment_total``, ``grooming`` and ``n_registrations``.
    candidate_scores : dict
        Reference candidate name -> selection score (lower is better), for ``reference="auto"``.
    shape_timings : list of float or None
        Seconds spent on each input with the chosen reference (all passes).
    params : dict
        The CPD/fairing parameters used.
    grooming : dict
        Mesh name -> what grooming did (:class:`core.correspondence.grooming.GroomReport` as a dict).
    reference_reason : str
        Why this reference was chosen (and which candidates were excluded).
    refinement : list of float
        Mean change of the corresponded vertices (mm) at each groupwise refinement pass.
    unreadable : dict
        Input path -> why it could not be read (also in ``failures``), for inputs given as paths.
    poses : dict
        Mesh name -> how its rigid pose was settled, for the shapes whose best fit to the
        reference turned them from their input orientation (:func:`_recheck_switched`).
    safeguard : dict
        What the safeguard (:mod:`core.correspondence.safeguard`) tried, its criterion's
        values and what it kept: ``{"enabled", "stages": [...]}``.
    """

    meshes: list
    reference_index: int | None
    reference_name: str
    faces: np.ndarray
    residuals_mm: list
    failures: dict
    timings: dict
    candidate_scores: dict = field(default_factory=dict)
    shape_timings: list = field(default_factory=list)
    params: dict = field(default_factory=dict)
    grooming: dict = field(default_factory=dict)
    reference_reason: str = ""
    refinement: list = field(default_factory=list)
    unreadable: dict = field(default_factory=dict)
    poses: dict = field(default_factory=dict)
    safeguard: dict = field(default_factory=dict)

    def to_report(self, names: list[str] | None = None) -> dict:
        """JSON-ready summary (per shape: residual, grooming, error; reference and why)."""
        names = names or [m.name if m is not None else f"shape_{i}" for i, m in enumerate(self.meshes)]
        ok = [r for r in self.residuals_mm if r is not None]
        return {
            "reference": self.reference_name,
            "reference_index": self.reference_index,
            "reference_reason": self.reference_reason,
            "n_vertices": int(self.faces.max()) + 1 if len(self.faces) else 0,
            "n_faces": int(len(self.faces)),
            "shapes": [{"name": n, "ok": self.residuals_mm[i] is not None,
                        "residual_mm": self.residuals_mm[i],
                        "seconds": self.shape_timings[i] if i < len(self.shape_timings) else None,
                        "grooming": self.grooming.get(n),
                        "pose": self.poses.get(n),
                        "error": self.failures.get(n)}
                       for i, n in enumerate(names)],
            "mean_residual_mm": float(np.mean(ok)) if ok else None,
            "candidate_scores": self.candidate_scores,
            "refinement_change_mm": self.refinement,
            "failures": self.failures,
            "timings": self.timings,
            "params": self.params,
            "safeguard": self.safeguard,
        }


def _mesh_name(mesh: TriMesh | InputFile | str | os.PathLike, index: int) -> str:
    if isinstance(mesh, TriMesh):
        return mesh.name or f"mesh {index}"
    if isinstance(mesh, InputFile):
        return mesh.name or mesh.path
    return str(mesh)  # a path: named by it


def _check_params(cpd_params: dict, selection: str) -> dict:
    unknown = set(cpd_params) - set(DEFAULT_CPD_PARAMS)
    if unknown:
        raise ValueError(f"unknown correspondence parameter(s): {', '.join(sorted(unknown))}; "
                         f"known: {', '.join(DEFAULT_CPD_PARAMS)}")
    if selection not in ("compactness", "residual"):
        raise ValueError(f"selection must be 'compactness' or 'residual', got {selection!r}")
    params = dict(DEFAULT_CPD_PARAMS)
    params.update(cpd_params)
    if not 0.0 <= params["w"] < 1.0:
        raise ValueError(f"outlier weight w must be in [0, 1), got {params['w']}")
    for name in ("refine_deformation", "deformation"):
        if params[name] not in ("normal_offsets", "cpd"):
            raise ValueError(f"{name} must be 'normal_offsets' or 'cpd', got {params[name]!r}")
    if params["offset_pose"] not in ("affine", "similarity"):
        raise ValueError(f"offset_pose must be 'affine' or 'similarity', got {params['offset_pose']!r}")
    for name in ("beta", "lam", "tolerance", "offset_width", "offset_sd", "offset_noise"):
        if not params[name] > 0:
            raise ValueError(f"{name} must be positive, got {params[name]}")
    return params


def default_vertex_count(meshes: list[TriMesh]) -> int:
    """The common density when ``vertices`` is not given: the median input vertex count, so
    that it does not depend on which subject is the reference (inputs already within 10% of
    it with an even spacing are left as they are)."""
    return _default_count([len(m.vertices) for m in meshes])


def _default_count(counts: list[int]) -> int:
    return max(int(np.median(counts)), 20) if counts else 2000


def _shape_info(mesh: TriMesh) -> dict:
    """What reference selection needs of a usable (groomed) input: its pose- and
    scale-invariant descriptor and whether it is closed (computed where the mesh is)."""
    return {"descriptor": _descriptor(mesh.vertices, mesh.faces),
            "closed": bool(meshops.is_closed(np.asarray(mesh.faces)))}


def _read_job(item: tuple, raw_dir: str | None) -> tuple:
    """core.runtime.parallel job: read one input file -> (vertex count or None, problem or None, the
    reader's warnings for the client to show, the mesh to groom: in ``raw_dir`` if given
    (the grooming job then needs no second read of the file in a child), else itself)."""
    index, handle = item
    mesh, problem, notes = read_input(handle.path)
    if mesh is None:
        return None, problem, notes, None
    kept = mesh if raw_dir is None else write_scratch_mesh(mesh, raw_dir, index)
    return len(mesh.vertices), None, notes, kept


def _groom_job(item: tuple, common: tuple) -> tuple:
    """core.runtime.parallel job: groom (or, with no options, only check) one input ->
    (groomed mesh or its scratch handle, report dict or None, None, info) or
    (None, None, problem, None). With a scratch directory the groomed mesh is written there
    and only its handle travels back."""
    index, handle = item
    options, scratch, name = common[0], common[1], common[2][index]
    mesh = open_mesh(handle)
    if options is None:
        problem = mesh_problem(mesh)
        if problem:
            return None, None, problem, None
        groomed, rep = TriMesh(mesh.vertices, mesh.faces, name), None
    else:
        try:
            groomed, rep = groom_mesh(mesh, options)
        except GroomingError as exc:
            return None, None, f"grooming: {exc}", None
        groomed.name = name
        rep = rep.to_dict()
    info = _shape_info(groomed)
    kept = groomed if scratch is None else write_scratch_mesh(groomed, scratch, index)
    return kept, rep, None, info


def _read_inputs(meshes: list, names: list[str], progress: ProgressCallback | None,
                 n_jobs: int | None, scratch: Scratch | None
                 ) -> tuple[dict[int, int], dict[str, str], list]:
    """Vertex count of every input, the inputs that cannot be read (name -> problem), and
    what to groom each from. Input files are read by the workers, each in a child process (a
    reader crash costs that file only); with a scratch folder the client never holds them."""
    from core.errors import DataFileWarning

    counts = {i: len(m.vertices) for i, m in enumerate(meshes) if isinstance(m, TriMesh)}
    sources = list(meshes)
    unread: dict[str, str] = {}
    files = [(i, (i, m)) for i, m in enumerate(meshes) if isinstance(m, InputFile)]
    if files:
        done = run_jobs(_read_job, files, common=None if scratch is None else str(scratch.raw),
                        n_jobs=n_jobs, label="reading", progress=sub_progress(progress, 0.0, 0.02))
        for i, _ in files:
            n, problem, notes, kept = done[i]
            for note in notes:
                warnings.warn(DataFileWarning(note), stacklevel=2)
            if problem is not None:
                unread[names[i]] = problem
            else:
                counts[i], sources[i] = n, kept
    return counts, unread, sources


def _prepare(meshes: list, names: list[str], groom: bool | dict, vertices: int | None,
             progress: ProgressCallback | None = None, n_jobs: int | None = 1,
             scratch: Scratch | None = None) -> tuple[list, dict, dict]:
    """Groomed (or checked) inputs, per-shape failures and grooming reports. Grooming is a
    per-shape job too (:func:`core.runtime.parallel.run_jobs`: pool or Dask).

    ``meshes`` holds TriMesh objects or :class:`~core.correspondence.store.InputFile`
    handles (read by the workers). The groomed inputs come back as meshes, or with a
    ``scratch`` directory as handles of the files the workers wrote there
    (:func:`_prepare_all` also returns what reference selection needs).
    """
    prepared, failures, reports, _, _ = _prepare_all(meshes, names, groom, vertices, progress,
                                                     n_jobs, scratch)
    return prepared, failures, reports


def _prepare_all(meshes: list, names: list[str], groom: bool | dict, vertices: int | None,
                 progress: ProgressCallback | None, n_jobs: int | None,
                 scratch: Scratch | None) -> tuple[list, dict, dict, dict, dict]:
    """:func:`_prepare` and, per usable input, what reference selection needs
    (:func:`_shape_info`, plus ``n_input``: its vertex count before grooming), and the
    inputs that could not be read."""
    counts, unread, meshes = _read_inputs(meshes, names, progress, n_jobs, scratch)
    prepared: list = [None] * len(meshes)
    failures: dict[str, str] = dict(unread)
    reports: dict[str, dict] = {}
    info: dict[int, dict] = {}
    readable = [i for i in range(len(meshes)) if i in counts]
    if groom is False and scratch is None and all(isinstance(m, TriMesh) for m in meshes):
        for i, m in enumerate(meshes):  # in memory, nothing to groom: checked here
            problem = mesh_problem(m)
            if problem:
                failures[names[i]] = problem
            else:
                prepared[i] = m
                info[i] = dict(_shape_info(m), n_input=counts[i])
        return prepared, failures, reports, info, unread
    options = None
    if groom is not False:
        options = dict(groom) if isinstance(groom, dict) else {}
        options.setdefault("vertices", int(vertices) if vertices else
                           _default_count([counts[i] for i in readable]))
        options.setdefault("keep_tessellation_above", TARGET_KEEP_SHARE)
    common = (options, None if scratch is None else str(scratch.groomed), names)
    try:
        done = run_jobs(_groom_job, [(i, (i, meshes[i])) for i in readable], common=common,
                        n_jobs=n_jobs, progress=sub_progress(progress, 0.02, 0.1),
                        label="grooming" if options is not None else "checking")
    except JobError as exc:  # an unexpected error of one input: raised as it is, as inline
        raise (exc.__cause__ or exc) from None
    if scratch is not None:
        scratch.drop_raw()  # the inputs as read: groomed now
    for i in readable:
        kept, rep, problem, shape = done[i]
        if problem is not None:
            failures[names[i]] = problem
            continue
        prepared[i] = kept
        info[i] = dict(shape, n_input=counts[i])
        if rep is not None:
            reports[names[i]] = rep
    failures = {n: failures[n] for n in names if n in failures}  # input order
    return prepared, failures, reports, info, unread


TARGET_KEEP_SHARE = 0.5  # inputs with at least this share of the common count keep their tessellation


def remesh_reference(prepared: list, candidates: list, groom: bool | dict, vertices: int | None,
                     info: dict, names: list[str], grooming: dict, store: Scratch | None) -> None:
    """Only the reference (candidates) is remeshed to the common count; the targets keep
    their own tessellation unless coarse (grooming's ``keep_tessellation_above``).

    Why (issue 27; uneven beans, ``core.datasets.shapes.unevenly_decimated``, 8 shapes, seed
    1, true spread mean / p95 mm, reference-based): both remeshed 2.33 / 3.30, the targets
    alone remeshed 2.34 / 3.43, the reference alone 1.93 / 3.03, neither 1.98 / 3.36; with
    one refinement pass 0.77 / 1.17 both, 0.64 / 1.05 neither, 0.47 / 0.68 the reference
    alone. The remesh is accurate (0.007-0.014 mm from the input surface), so what the
    targets lose is their own vertex density: a quadric decimation's follows the curvature,
    the same on homologous parts of every shape, and CPD matches densities; an even remesh
    replaces it by one even in area, which the shapes' bumps and scalings skew. The
    reference is remeshed: its vertices are the model's, evenly spread, and its resolution
    then does not depend on which subject it is.
    """
    options = dict(groom) if isinstance(groom, dict) else {}
    if groom is False or not options.get("remesh", True) or not info:
        return
    if options.get("keep_tessellation_above", TARGET_KEEP_SHARE) is None:
        return  # every input was remeshed already
    from core.correspondence.grooming import needs_remesh, remesh

    count = int(vertices) if vertices else _default_count([d["n_input"] for d in info.values()])
    for c in candidates:
        if c is None:
            continue
        mesh = open_mesh(prepared[c])
        if not needs_remesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), count):
            continue
        v, f = remesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces), count)
        out = TriMesh(v, f, mesh.name)
        prepared[c] = out if store is None else write_scratch_mesh(out, store.groomed, c)
        rep = grooming.setdefault(names[c], {})
        rep.update(remeshed=True, output_vertices=int(len(v)))


def _descriptor(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Pose- and scale-invariant shape summary: principal extents and the isoperimetric ratio."""
    xn, _, scale = _normalise(np.asarray(vertices, dtype=np.float64))
    extents = np.sqrt(np.sort(np.linalg.eigvalsh(np.cov(xn.T))))
    area = 0.5 * np.linalg.norm(np.cross(xn[faces[:, 1]] - xn[faces[:, 0]],
                                         xn[faces[:, 2]] - xn[faces[:, 0]]), axis=1).sum()
    vol = abs(meshops.volume(xn, faces))
    return np.append(extents, area / max(vol, 1e-12) ** (2.0 / 3.0) / 10.0)


def pick_reference_candidates(raw: list[TriMesh], prepared: list, usable: list[int], n: int,
                              grooming: dict, names: list[str]) -> tuple[list[int], str]:
    """The n most typical usable shapes (closest to the median descriptor), and why.

    Excluded first: coarse inputs (fewer than half the median input vertex count, which
    would set a coarse model resolution without remeshing), inputs that needed repair
    (dropped pieces or filled holes) and unrepresentative ones (descriptor more than 3
    robust standard deviations from the median).
    """
    info = {i: {"n_input": len(raw[i].vertices),
                "descriptor": _descriptor(prepared[i].vertices, prepared[i].faces)} for i in usable}
    return _pick_candidates(info, usable, n, grooming, names)


def _pick_candidates(info: dict[int, dict], usable: list[int], n: int, grooming: dict,
                     names: list[str]) -> tuple[list[int], str]:
    """:func:`pick_reference_candidates` from per-shape ``info`` (``n_input``,
    ``descriptor``) computed where the meshes are."""
    counts = np.array([info[i]["n_input"] for i in usable], dtype=float)
    desc = np.array([info[i]["descriptor"] for i in usable])
    dist = np.linalg.norm(desc - np.median(desc, axis=0), axis=1)
    mad = 1.4826 * np.median(np.abs(dist - np.median(dist))) + 1e-12
    excluded = {}
    for j, i in enumerate(usable):
        rep = grooming.get(names[i], {})
        if counts[j] < 0.5 * np.median(counts):
            excluded[i] = f"coarse ({int(counts[j])} vertices)"
        elif any(rep.get(k) for k in ("dropped_pieces", "filled_holes", "split_vertices",
                                      "removed_handles", "removed_non_manifold_faces")):
            excluded[i] = "needed repair"
        elif (dist[j] - np.median(dist)) / mad > 3.0:
            excluded[i] = "unrepresentative shape"
    pool = [j for j, i in enumerate(usable) if i not in excluded] or list(range(len(usable)))
    order = sorted(pool, key=lambda j: (dist[j], j))[:max(1, n)]
    chosen = [usable[j] for j in order]
    why = (f"closest to the median shape (principal extents, area/volume) among "
           f"{len(pool)} of {len(usable)} usable inputs")
    if excluded:
        why += "; excluded: " + ", ".join(f"{names[i]} ({r})" for i, r in excluded.items())
    return chosen, why


def _compactness(shapes: np.ndarray) -> float:
    """Mean per-vertex variance after similarity GPA, over the squared mean size (lower = compact)."""
    from core.alignment.transforms import generalized_procrustes

    if len(shapes) < 2:
        return 0.0
    res = generalized_procrustes(shapes, "similarity", max_iter=20, tol=1e-5)
    size2 = float(((res.mean - res.mean.mean(axis=0)) ** 2).sum(axis=1).mean())
    return float(((res.aligned - res.mean) ** 2).sum(axis=2).mean() / max(size2, 1e-300))


def _task_job(task: tuple, references: dict) -> tuple:
    """core.runtime.parallel job: one correspondence task whose reference arrays come from
    ``references`` (sent once per worker) -> (result or None, error or None).

    The target is a handle (:func:`core.correspondence.store.open_mesh`: the mesh itself, or
    a file the worker reads). A refinement task carries the shape's current correspondence
    (a handle too, :func:`~core.correspondence.store.open_rows`) instead of the posed mean:
    the worker poses the mean on it (core.alignment.transforms.fit_transform), as the client did before.
    """
    key, _, _, target, _, params, parallel, *rest = task
    ref_v, ref_f = references[key[0]]
    mesh = open_mesh(target)
    extra = ()
    if rest:
        current = open_rows(rest[0])
        # Affine for the offsets' fit (whose own pose refines it), similarity for CPD.
        how = "affine" if params["deformation"] == "normal_offsets" else "similarity"
        extra = (apply_transform(fit_transform(ref_v, current, how), ref_v),)
    _, out, err = _task((key, ref_v, ref_f, mesh.vertices, mesh.faces, params, parallel, *extra))
    return out, err


def _run_tasks(tasks: list[tuple], n_jobs: int, progress: ProgressCallback | None,
               start: float, stop: float, on_result: Callable | None = None) -> dict:
    """Run correspondence tasks in this process or through :func:`core.runtime.parallel.run_jobs`
    (process pool, or Dask inside :func:`core.runtime.parallel.use_scheduler`); cancellable via
    progress. ``on_result(key, (out, err))`` sees each result as it arrives (streaming);
    what it returns, if not None, is kept instead of the result (a summary: the client then
    holds no vertices).

    A task is :func:`_task_job`'s argument; its ``parallel`` flag (index 6) is set here:
    rustcpd's own threads only when running in this process. The reference of every task is
    sent once per worker, not once per task.
    """
    results = {}
    total = len(tasks)
    if total == 0:
        return results
    references = {t[0][0]: (t[1], t[2]) for t in tasks}
    keep = (lambda key, value: value) if on_result is None else (
        lambda key, value: _or(on_result(key, value), value))
    if runs_inline(n_jobs, total):
        for done, t in enumerate(tasks):
            report(progress, start + (stop - start) * done / total, f"corresponding {done + 1}/{total}")
            results[t[0]] = keep(t[0], _task_job(t[:6] + (True,) + t[7:], references))
        report(progress, stop, "correspondence done")
        return results
    items = [(t[0], (t[0], None, None) + t[3:6] + (False,) + t[7:]) for t in tasks]
    results = run_jobs(_task_job, items, common=references, n_jobs=n_jobs, on_result=keep,
                       progress=sub_progress(progress, start, stop), label="corresponding")
    report(progress, stop, "correspondence done")
    return results


def _or(value, default):
    return default if value is None else value


def _tasks(reference: TriMesh, ref_key, targets: dict, params: dict,
           current: dict | None = None) -> list[tuple]:
    """Tasks corresponding ``reference`` to each target (a mesh handle); with ``current``
    (shape -> handle of its current correspondence) the reference is posed on each shape."""
    ref_v, ref_f = np.asarray(reference.vertices, float), np.asarray(reference.faces)
    return [((ref_key, i), ref_v, ref_f, handle, None, params, False)
            + ((current[i],) if current is not None else ())
            for i, handle in targets.items()]


def _resolve_reference(reference, prepared: list, names: list[str], failures: dict, usable,
                       info: dict, n_references: int, grooming: dict
                       ) -> tuple[list, TriMesh | None, str]:
    """(candidate indices or [None], external reference mesh or None, reason)."""
    if isinstance(reference, (str, os.PathLike)) and str(reference) != "auto":
        ref_path = str(reference)
        if ref_path in names:  # one of the inputs, by its name
            reference = names.index(ref_path)
        else:
            from core.io import load_mesh

            reference = load_mesh(ref_path)  # DataFileError names the file
            reference.name = ref_path
    if isinstance(reference, TriMesh):
        problem = mesh_problem(reference, need_closed=True)
        ref_name = reference.name or "reference"
        if problem:
            raise ValueError(f"{ref_name}: {problem}")
        return [None], reference, "given (external reference mesh)"
    if isinstance(reference, (int, np.integer)) and not isinstance(reference, bool):
        idx = int(reference)
        if not 0 <= idx < len(prepared):
            raise ValueError(f"reference index {idx} out of range for {len(prepared)} meshes")
        if prepared[idx] is None:
            raise ValueError(f"{names[idx]}: {failures.get(names[idx])}")
        problem = mesh_problem(open_mesh(prepared[idx]), need_closed=True)
        if problem:
            raise ValueError(f"{names[idx]}: {problem}")
        return [idx], None, "given (by index or name)"
    if reference != "auto":
        raise ValueError(f"reference must be 'auto', an index or a TriMesh, got {reference!r}")
    closed = [i for i in usable if info[i]["closed"]]
    if not closed and usable:
        # None is closed as given (grooming off): the most typical one that grooming repairs
        # serves, as a repaired copy (every input is still corresponded as it is)
        order, _ = _pick_candidates(info, usable, len(usable), grooming, names)
        problems = {}
        for i in order:
            try:
                repaired, rep = groom_mesh(open_mesh(prepared[i]), {"remesh": False})
            except GroomingError as exc:
                problems[names[i]] = f"not repairable: {exc}"
                continue
            repaired.name = f"{names[i]} (repaired)"
            done = describe(rep.to_dict()) or "checked"
            return [None], repaired, (f"a repaired copy of {names[i]} ({done}): no input is a "
                                      f"closed surface as given")
        failures = {**failures, **problems}
    if not closed:
        raise ValueError("no input mesh can serve as reference (none is a valid closed surface "
                         "or can be repaired into one: "
                         + "; ".join(f"{k}: {v}" for k, v in failures.items()) + ")"
                         if failures else "no input mesh is a closed surface")
    candidates, why = _pick_candidates(info, closed, n_references, grooming, names)
    return candidates, None, why


def _select(candidates: list, external, prepared: list, names: list[str], usable: list[int],
            params: dict, n_jobs: int, progress, selection: str, selection_shapes: int
            ) -> tuple[object, dict, dict, list[int], float]:
    """Correspond the selection subset to every candidate; keep the best (compactness or
    residual). Returns (chosen, scores, results so far, shapes still to do, progress).

    A single candidate is the reference without trials: every shape is left to the main
    pass (whose results stream; its score, the mean pair residual, is 0.0 as those are
    not computed for one candidate)."""
    if len(candidates) == 1:
        c = candidates[0]
        name = (external.name or "reference") if c is None else names[c]
        return c, {name: 0.0, "_n_registrations": 0}, {}, [i for i in usable if i != c], 0.1
    if len(candidates) > 1 and len(usable) > max(int(selection_shapes), len(candidates)):
        others = [i for i in usable if i not in candidates]
        n_more = max(int(selection_shapes) - len(candidates), 1)
        spread = np.linspace(0, len(others) - 1, min(n_more, len(others))).round().astype(int)
        subset = sorted(set(candidates) | {others[j] for j in spread})
    else:
        subset = list(usable)
    tasks = []
    for c in candidates:
        ref = external if c is None else open_mesh(prepared[c])
        tasks += _tasks(ref, c, {i: prepared[i] for i in subset if i != c}, params)
    rest = [i for i in usable if i not in subset]
    split = 0.1 + 0.5 * len(tasks) / max(len(tasks) + len(rest), 1)
    results = _run_tasks(tasks, n_jobs, progress, 0.1, split)
    scores, best = {}, None
    for c in candidates:
        outs = [results[(c, i)][0] for i in subset if c is None or i != c]
        shapes = [o["vertices"] for o in outs if o is not None]
        if c is not None:
            shapes.append(np.asarray(open_mesh(prepared[c]).vertices, float))
        resid = [o["residual_mm"] for o in outs if o is not None and o["residual_mm"] is not None]
        if selection == "compactness" and len(candidates) > 1:
            score = _compactness(np.stack(shapes)) if len(shapes) >= 2 else np.inf
        else:
            score = float(np.mean(resid)) if resid else 0.0
        scores[(external.name or "reference") if c is None else names[c]] = score
        key = (-len(shapes), score)
        if best is None or key < best[0]:
            best = (key, c)
    chosen = best[1]
    done = {i: results[(chosen, i)] for i in subset if chosen is None or i != chosen}
    scores["_n_registrations"] = len(tasks)
    return chosen, scores, done, rest, split


MIRROR_SUSPECT = 0.95  # pair.mirror_fit_ratio against the reference below this: check again
MIRROR_RATIO = 0.8     # ... against the others' mean below this: mirrored


def _flag_mirrored(results: dict, usable: list[int], vertices: MutableMapping,
                   prepared: list, params: dict) -> dict[int, str]:
    """Inputs whose mirror image fits better than any rotation of them (a left/right mix-up).

    The pairwise step measured :func:`core.correspondence.pair.mirror_fit_ratio` against the
    reference; a reference's own bumps make that noisy on a nearly achiral shape (0.87 for a
    correctly sided bean), so suspects are checked again against the mean of the others
    (measured: 0.92 and up for correctly sided beans, 1.4 and up for the chiral twisted
    beans, 0.73 and below for mirrored twisted beans). When most inputs are suspects, the
    reference is the odd one and nothing is flagged.
    """
    ratios = {i: results[i][0].get("mirror_ratio") for i in usable
              if i in results and results[i][0] is not None}
    suspects = [i for i, r in ratios.items() if r is not None and r < MIRROR_SUSPECT]
    others = [k for k in sorted(vertices) if k not in suspects]
    if not suspects or 2 * len(suspects) >= len(ratios) or len(others) < 2:
        return {}
    mean, _ = _gpa(vertices, others, tol=1e-5)
    flagged = {}
    for i in suspects:
        r = mirror_fit_ratio(mean, open_mesh(prepared[i]).vertices, params)
        if r < MIRROR_RATIO:
            flagged[i] = (f"mirrored: its mirror image fits the other shapes better than any "
                          f"rotation of it (rigid fit sigma^2 ratio {r:.2f}); a left/right mix-up?")
    return flagged


NEIGHBOUR_TRIES = 3  # closest shapes a switched shape is corresponded to again, one by one
NEIGHBOUR_POOL = 64  # unswitched shapes the closest are chosen from


def _recheck_switched(results: dict, corresponded: MutableMapping, faces: np.ndarray,
                      prepared: list, params: dict, n_jobs: int, timings: dict) -> dict:
    """Shapes whose rigid pose switched to a principal-axes start, checked against a closer
    shape.

    The pairwise step keeps the input's orientation unless a principal-axes start fits the
    reference far better (:func:`core.correspondence.pair._rigid_fit`). Against a reference
    turned far from the shape (inputs up to 90 degrees apart), the identity start can stall
    and a nearly symmetric shape then fits far better flipped end to end: bent tubes came out
    reversed, 28-30 mm from their true homologues (1 of 12 in held-out population 107 of
    ``bench_correspondence``; against shape 0 of twenty 8-tube sets, 3 of 7 in one and 1 of 7
    in another; ``test_a_tube_flipped_against_the_reference_keeps_its_input_orientation_in_the_batch``).
    Each switched shape is corresponded again, the same way
    (every start, the same rule), to the shape that did not switch whose long axis is
    closest to its own, as that shape's correspondence: from an input orientation that
    close, the identity start converges. The new result is kept when it keeps the input
    orientation (otherwise the next closest is tried, up to :data:`NEIGHBOUR_TRIES`); a
    shape that switches every time is truly turned and keeps its first result.
    Only when the switched shapes are a minority (the inputs share their orientation).
    Returns shape index -> what was done.
    """
    switched = [k for k, (res, err) in results.items()
                if err is None and res is not None and res.get("pose_switched") and k in corresponded]
    others = [k for k in sorted(corresponded) if k not in switched]
    if not switched or len(others) <= len(switched):
        return {}
    # The closest shapes are looked for among at most NEIGHBOUR_POOL of the others (a
    # cohort's meshes may be files: each is read once for its long axis).
    pool = others[::max(1, len(others) // NEIGHBOUR_POOL)]
    axis = {k: _principal_axes(np.asarray(open_mesh(prepared[k]).vertices))[:, 0]
            for k in switched + pool}
    ranked = {k: sorted(pool, key=lambda o: -abs(float(axis[o] @ axis[k])))[:NEIGHBOUR_TRIES]
              for k in switched}
    notes = {k: ("turned from its input orientation: its principal axes fitted the reference "
                 f"and its {len(ranked[k])} closest shapes far better") for k in switched}
    pending = list(switched)
    for attempt in range(NEIGHBOUR_TRIES):
        tasks = []
        for k in pending:
            if attempt < len(ranked[k]):
                j = ranked[k][attempt]
                tasks += _tasks(TriMesh(np.asarray(corresponded[j], float), faces, "neighbour"),
                                j, {k: prepared[k]}, params)
        if not tasks:
            break
        for (j, k), (out, _) in _run_tasks(tasks, n_jobs, None, 0.6, 0.6).items():
            if out is None:
                continue
            _add_timings(timings, k, out)
            if not out["pose_switched"]:
                corresponded[k] = out["vertices"]
                pending.remove(k)
                notes[k] = ("input orientation kept: against one of its closest shapes the "
                            "input orientation fitted (against the reference a principal-axes "
                            "pose had)")
    return notes


OUTLIER_FACTOR = 3.0  # an outlier's Procrustes distance to the mean: over this many times the median


def _flag_outliers(vertices: MutableMapping, names: list[str], protect) -> dict[int, str]:
    """Shapes far from every other one after similarity alignment (a different structure
    by mistake; mirrored sides: :func:`_flag_mirrored`).

    Flagged: a robust z-score over 5 and a distance over :data:`OUTLIER_FACTOR` times the
    median. Measured on 6-shape sets of :mod:`core.datasets.shapes`: shapes of the
    right structure reach 2.65x the median (bent tubes whose correspondence is
    off by over a millimetre), a ring or a tube among beans 3.9-4.4x. With 2x such a tube
    was dropped from its training set as "a different structure".
    """
    keys = sorted(vertices)
    if len(keys) < 6:  # too few for a robust spread of the distances
        return {}
    mean, rmsd = _gpa(vertices, keys, tol=1e-5)
    size = float(np.sqrt(((mean - mean.mean(axis=0)) ** 2).sum(axis=1).mean()))
    dist = rmsd / size
    med = float(np.median(dist))
    mad = 1.4826 * float(np.median(np.abs(dist - med))) + 1e-3 * med + 1e-12
    flagged = {}
    for j, k in enumerate(keys):
        if k != protect and (dist[j] - med) / mad > 5.0 and dist[j] > OUTLIER_FACTOR * med:
            flagged[k] = (f"far from every other training shape ({dist[j]:.2f} of the mean size "
                          f"from the mean, typical {med:.2f}; a different structure?)")
    return flagged


def _retry_from_mean(vertices: MutableMapping, keys: list[int], faces: np.ndarray,
                     prepared: list, params: dict, n_jobs: int, timings: dict) -> None:
    """Correspond ``keys`` again, from scratch (rigid starts included), to the mean of the
    other shapes: a reference that is closer to them than the chosen one was."""
    others = [k for k in sorted(vertices) if k not in keys]
    if len(others) < 2:
        return
    mean, _ = _gpa(vertices, others, tol=1e-6)
    results = _run_tasks(_tasks(TriMesh(mean, faces, "mean"), "retry",
                                {k: prepared[k] for k in keys}, params), n_jobs, None, 0.6, 0.6)
    for k in keys:
        out, _ = results[("retry", k)]
        if out is not None:
            vertices[k] = out["vertices"]
            _add_timings(timings, k, out)


def _gpa(vertices: Mapping, keys: list[int], tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(mean, per-shape rmsd) of the similarity GPA of ``vertices[k]`` over ``keys`` (20
    iterations at most), one shape at a time (``vertices`` in memory or a vertex store)."""
    from core.alignment.transforms import procrustes_mean

    return procrustes_mean(vertices, keys, "similarity", max_iter=20, tol=tol)


def _handle(vertices: Mapping, key: int):
    """What a job needs to read ``vertices[key]`` (the array, or a row of a vertex store)."""
    return vertices.handle(key) if isinstance(vertices, VertexRows) else vertices[key]


def _refine(vertices: MutableMapping, faces: np.ndarray, prepared: list, params: dict,
            n_jobs: int, progress, passes: int, timings: dict,
            on_last_pass: Callable | None = None) -> list[float]:
    """Groupwise refinement: correspond every shape again to the current mean shape.

    The mean of the similarity-aligned corresponded shapes is posed on each shape by a fit
    over the current correspondences (no rigid CPD needed; in the worker, :func:`_task_job`:
    affine for the default ``refine_deformation="normal_offsets"``, similarity for ``"cpd"``),
    moved onto the shape (:mod:`core.correspondence.offsets`, or nonrigid CPD), then
    labelled and faired as in the pairwise step. Each result replaces the shape's
    correspondence as it arrives (its job was the only reader of it);
    ``on_last_pass(key, (out, err))`` sees the last pass's results as they arrive (final).
    """
    changes = []
    for it in range(int(passes)):
        keys = sorted(vertices)
        if len(keys) < 3:
            break
        mean_v, _ = _gpa(vertices, keys, tol=1e-6)
        current = {k: _handle(vertices, k) for k in keys}
        tasks = _tasks(TriMesh(mean_v, faces, "mean"), "mean", {k: prepared[k] for k in keys},
                       params, current)
        moved: dict[int, float] = {}
        last = it == int(passes) - 1

        def absorb(key: tuple, value: tuple, last: bool = last, moved: dict = moved) -> tuple:
            out, err = value
            k = key[1]
            if out is not None:  # else: keep the previous correspondence of this shape
                moved[k] = float(np.linalg.norm(out["vertices"] - vertices[k], axis=1).mean())
                vertices[k] = out["vertices"]
                _add_timings(timings, k, out)
            if last and on_last_pass is not None:
                on_last_pass(key, value)
            return None, err

        start = 0.6 + 0.35 * it / passes
        _run_tasks(tasks, n_jobs, progress, start, start + 0.35 / passes, on_result=absorb)
        ok = [moved[k] for k in keys if k in moved]
        changes.append(float(np.mean(ok)) if ok else 0.0)
    return changes


def _pass_params(params: dict) -> dict:
    """The correspondence parameters of a refinement pass (its deformation, no residual)."""
    return dict(params, pair_residual=False, max_iterations=int(params["refine_iterations"]),
                deformation=params["refine_deformation"])


def _add_timings(timings: dict, key: int, out: dict) -> None:
    per = timings.setdefault("_per_shape", {})
    per[key] = per.get(key, 0.0) + float(out["timings"]["total"])
    timings["assignment_total"] = timings.get("assignment_total", 0.0) + out["timings"]["assignment"]
    timings["cpu_total"] = timings.get("cpu_total", 0.0) + out["timings"]["total"]
    timings["n_registrations"] = timings.get("n_registrations", 0) + 1


def establish_correspondence(meshes: list[TriMesh | InputFile | str | os.PathLike],
                             reference: str | int | TriMesh = "auto", *,
                             n_references: int = 1, n_jobs: int | None = None,
                             progress: ProgressCallback | None = None, selection: str = "compactness",
                             selection_shapes: int = 8, groom: bool | dict = True,
                             vertices: int | None = None, refine: int = 1,
                             on_shape: Callable[[int, TriMesh], None] | None = None,
                             on_provisional: Callable[[int, TriMesh], None] | None = None,
                             on_unreadable: Callable[[int, str], None] | None = None,
                             scratch: str | os.PathLike | None = None, keep_meshes: bool = True,
                             safeguard: bool = True, **cpd_params) -> CorrespondenceResult:
    """Express every training mesh with the vertices and faces of one reference mesh.

    Parameters
    ----------
    meshes : list of TriMesh or paths (or :class:`~core.correspondence.store.InputFile`)
        Training meshes (any vertex count, order and pose). ``mesh.name`` names them in errors.
        A path is read by the worker that needs it (each file in a child process: a reader
        crash costs that file only); it is named by its path, and an unreadable one is a
        failure like any other (listed in ``unreadable`` too).
    reference : "auto", int, path or TriMesh
        ``"auto"``: the most typical usable input (:func:`pick_reference_candidates`), or with
        ``n_references`` > 1 the best of that many by ``selection``; int: that input; a path:
        the input of that name, else the mesh file; TriMesh: an external reference mesh
        (kept as it is, not groomed). A reference must be one closed connected surface.
    n_references : int
        Candidates tried with ``"auto"`` (1: no trial registrations; the groupwise
        refinement removes most of the reference's influence).
    n_jobs : int, optional
        Worker processes (default: CPU count). 1 runs in this process.
    progress : callable, optional
        ``progress(fraction, message)``; may raise :class:`core.runtime.progress.Cancelled`, which
        terminates the worker pool and propagates.
    selection : {"compactness", "residual"}
        How several ``"auto"`` candidates are ranked.
    selection_shapes : int
        Candidates are compared on this many shapes.
    groom : bool or dict
        Grooming before correspondence (:mod:`core.correspondence.grooming`; a dict overrides its options,
        e.g. ``{"remesh": False}``); False only checks the inputs.
    vertices : int, optional
        Common vertex count of the groomed inputs (default :func:`default_vertex_count`).
    refine : int
        Groupwise refinement passes (0: plain reference-based correspondence).
    on_shape : callable, optional
        ``on_shape(index, mesh)`` for every corresponded input as soon as its result is final
        (streaming: the command line writes each output as it arrives, so an interrupted run
        leaves the finished ones). Results become final during the last refinement pass, as
        its jobs complete (with the safeguard, a shape whose first-pass result was rolled
        back or refined further is given again, with its kept result); with ``refine=0``
        after the outlier check (all at once).
    on_provisional : callable, optional
        ``on_provisional(index, mesh)`` for every shape's reference-based result (before the
        refinement passes, after the outlier check; only when ``refine`` > 0): what an
        interrupted run can still hand over for the shapes not yet final.
    on_unreadable : callable, optional
        ``on_unreadable(index, problem)`` for every input path that cannot be read, as soon
        as that is known (an interrupted run can still report it).
    scratch : path, optional
        A directory (created; removed at the end, also when stopped) where the workers keep
        the groomed inputs and the client the corresponded vertices of every pass, instead
        of this process's memory (:mod:`core.correspondence.store`): with paths as inputs,
        the client's memory then stays flat in the number of shapes. On a cluster every
        worker must see it at this path. The results are bit-identical either way.
    keep_meshes : bool
        False: ``result.meshes`` holds None for every input (the shapes went to
        ``on_shape``); all the rest of the result is there.
    safeguard : bool
        Keep the remesh and each refinement pass only where the model's leave-one-out
        generalisation against the raw inputs says it helps
        (:mod:`core.correspondence.safeguard`; ``result.safeguard`` says what was kept).
        With it the last pass's outputs reach ``on_shape`` once the pass is judged.
    **cpd_params
        Overrides of :data:`DEFAULT_CPD_PARAMS`.
    """
    params = _check_params(cpd_params, selection)
    if len(meshes) == 0:
        raise ValueError("no meshes to correspond")
    record: dict = {"enabled": bool(safeguard), "stages": []}
    if cpd_params.get("labelling"):  # given: the first pass labels too (popped by _establish)
        record["labelling"] = True
    if safeguard:
        from core.correspondence.safeguard import choose_remesh

        groom, trial = choose_remesh(list(meshes), reference, groom, vertices, n_jobs, cpd_params)
        record["stages"] += [trial] if trial else []
    store = None if scratch is None else Scratch(scratch)
    try:
        return _establish(list(meshes), reference, params, store, record, n_references=n_references,
                          n_jobs=n_jobs, progress=progress, selection=selection,
                          selection_shapes=selection_shapes, groom=groom, vertices=vertices,
                          refine=refine, on_shape=on_shape, on_provisional=on_provisional,
                          on_unreadable=on_unreadable, keep_meshes=keep_meshes)
    finally:
        if store is not None:
            store.remove()


def _establish(meshes: list, reference, params: dict, store: Scratch | None, record: dict, *,
               n_references: int, n_jobs: int | None, progress, selection: str,
               selection_shapes: int, groom: bool | dict, vertices: int | None, refine: int,
               on_shape: Callable | None, on_provisional: Callable | None,
               on_unreadable: Callable | None, keep_meshes: bool) -> CorrespondenceResult:
    """:func:`establish_correspondence` with its per-shape data in ``store`` (or memory)."""
    t_start = time.perf_counter()
    labelled = record.pop("labelling", False)
    names = [_mesh_name(m, i) for i, m in enumerate(meshes)]
    handles = [m if isinstance(m, (TriMesh, InputFile)) else InputFile(str(m)) for m in meshes]
    report(progress, 0.0, "grooming")
    n_jobs = (os.cpu_count() or 1) if n_jobs is None else int(n_jobs)
    prepared, failures, grooming, info, unread = _prepare_all(handles, names, groom, vertices,
                                                              progress, n_jobs, store)
    for i, name in enumerate(names) if on_unreadable is not None else ():
        if name in unread:
            on_unreadable(i, unread[name])
    if len(unread) == len(meshes):
        raise ValueError("no input mesh could be read: "
                         + "; ".join(f"{k}: {v}" for k, v in unread.items()))
    t_groom = time.perf_counter() - t_start
    usable = [i for i, m in enumerate(prepared) if m is not None]
    candidates, external, why = _resolve_reference(reference, prepared, names, failures, usable,
                                                   info, n_references, grooming)
    remesh_reference(prepared, candidates, groom, vertices, info, names, grooming, store)
    # The batch measures its final outputs itself; before a refinement pass the first pass
    # only has to give the mean shape, so it skips labelling and fairing (plain
    # CPD-then-project; the refinement labels and fairs every shape).
    first = dict(params, pair_residual=selection == "residual" and len(candidates) > 1)
    if refine >= 1 and len(usable) >= 4 and not (record["enabled"] or labelled):
        first["labelling"] = False  # (a safeguard's rollback needs the labelled result)
    chosen, scores, results, rest, split = _select(candidates, external, prepared, names, usable,
                                                   first, n_jobs, progress, selection,
                                                   selection_shapes)
    n_trial = scores.pop("_n_registrations") - len(results)  # trial runs of the losers
    ref = external if chosen is None else open_mesh(prepared[chosen])
    ref_faces = np.asarray(ref.faces).copy()
    corresponded: MutableMapping = ({} if store is None else
                                    store.rows("corresponded", len(ref.vertices)))

    def absorb(key: tuple, value: tuple) -> tuple:  # streaming: the client keeps no vertices
        out, err = value
        if out is None:
            return value
        corresponded[key[1]] = out["vertices"]
        return {k: v for k, v in out.items() if k != "vertices"}, err

    results.update({k[1]: v for k, v in _run_tasks(
        _tasks(ref, chosen, {i: prepared[i] for i in rest}, first), n_jobs, progress,
        split, 0.6, on_result=absorb).items()})
    timings: dict = {"grooming": t_groom, "n_registrations": n_trial}
    _collect(results, chosen, ref, usable, names, failures, timings, corresponded)
    poses = {names[k]: note for k, note in _recheck_switched(
        results, corresponded, ref_faces, prepared, first, n_jobs, timings).items()}
    _drop_flagged(results, usable, corresponded, prepared, names, chosen, ref_faces, params,
                  first, n_jobs, timings, failures)
    del results  # per-shape summaries of the first pass: not needed any more
    streamed: set[int] = set()

    def stream(k: int, v: np.ndarray) -> None:
        if on_shape is not None and k not in streamed:
            streamed.add(k)
            on_shape(k, TriMesh(v, ref_faces, names[k]))

    def final(key: tuple, value: tuple) -> None:  # a last-pass failure keeps the previous result
        stream(key[1], value[0]["vertices"] if value[0] is not None else corresponded[key[1]])

    if on_provisional is not None and refine > 0:
        for k in sorted(corresponded):
            on_provisional(k, TriMesh(corresponded[k], ref_faces, names[k]))
    changes, again = _refine_guarded(record, handles, corresponded, ref_faces, prepared, params, n_jobs,
                                     progress, refine, timings, final if on_shape is not None else None)
    for k in sorted(corresponded) if on_shape is not None else ():
        if k not in streamed or again:  # untouched by a pass (refine=0, < 3 shapes), or replaced
            streamed.discard(k)
            stream(k, corresponded[k])
    result = _result(meshes, names, corresponded, prepared, chosen, ref, ref_faces, failures,
                     timings, scores, params, grooming, why, changes, t_start, n_jobs, progress,
                     keep_meshes)
    result.unreadable, result.poses, result.safeguard = unread, poses, record
    return result


def _refine_guarded(record: dict, handles: list, vertices: MutableMapping, faces: np.ndarray,
                    prepared: list, params: dict, n_jobs: int, progress, passes: int,
                    timings: dict, on_last_pass: Callable | None) -> tuple[list[float], bool]:
    """:func:`_refine`, each pass judged by the safeguard when it is on
    (:class:`core.correspondence.safeguard.RefinementGuard`, its record into ``record``).
    Returns the changes and whether the shapes must stream again: the first pass's results
    stream as they arrive (an interrupted run keeps them); with the safeguard, when that pass
    is rolled back or another follows, the kept results replace them (``on_shape`` is called
    again for those shapes)."""
    if not record["enabled"]:
        return _refine(vertices, faces, prepared, _pass_params(params), n_jobs, progress, passes,
                       timings, on_last_pass=on_last_pass), False
    from core.correspondence.safeguard import RefinementGuard, raw_mesh

    guard = RefinementGuard(lambda k: raw_mesh(handles[k]))

    calls = []

    def run_pass(p: dict) -> list[float]:
        calls.append(p["refine_deformation"])
        return _refine(vertices, faces, prepared, _pass_params(p), n_jobs, progress, 1, timings,
                       on_last_pass=on_last_pass if len(calls) == 1 else None)
    changes = guard.refine(vertices, faces, params, passes, run_pass)
    record["stages"] += [guard.record] if passes > 0 else []
    done = guard.record["passes"]
    kept_first = len(calls) == 1 and bool(done) and done[0]["kept"] == calls[0]
    return changes, bool(calls) and not kept_first


def _drop_flagged(results: dict, usable: list[int], corresponded: MutableMapping, prepared: list,
                  names: list[str], chosen, ref_faces: np.ndarray, params: dict, first: dict,
                  n_jobs: int, timings: dict, failures: dict) -> None:
    """The mirror and outlier checks: flagged shapes leave ``corresponded``, their reason
    goes to ``failures``."""
    for k, reason in _flag_mirrored(results, usable, corresponded, prepared, params).items():
        failures[names[k]] = reason
        corresponded.pop(k, None)
    flagged = _flag_outliers(corresponded, names, chosen)
    if flagged:  # a wrong pose looks like a wrong shape: once more from the others' mean
        _retry_from_mean(corresponded, list(flagged), ref_faces, prepared, first, n_jobs, timings)
        flagged = {k: r for k, r in _flag_outliers(corresponded, names, chosen).items()
                   if k in flagged}
    for k, reason in flagged.items():
        failures[names[k]] = reason
        del corresponded[k]


def _collect(results: dict, chosen, ref: TriMesh, usable: list[int], names: list[str],
             failures: dict, timings: dict, out: MutableMapping) -> MutableMapping:
    """Corresponded vertices per input index (the reference itself included) into ``out``
    (results whose vertices already went there as they arrived keep only a summary)."""
    for i in usable:
        if chosen is not None and i == chosen:
            out[i] = np.asarray(ref.vertices, float).copy()
            continue
        res, err = results[i]
        if err is not None:
            failures[names[i]] = f"correspondence failed: {err}"
            continue
        if "vertices" in res:
            out[i] = res["vertices"]
        _add_timings(timings, i, res)
    return out


def _residual_job(item: tuple, faces: np.ndarray) -> float:
    """core.runtime.parallel job: symmetric mean surface distance (mm) between a corresponded shape
    (vertices or their handle) and its groomed input (a mesh handle)."""
    from core.geometry.toolkit import symmetric_surface_distance

    vertices, target = item
    mesh = open_mesh(target)
    return symmetric_surface_distance(open_rows(vertices), faces, mesh.vertices, mesh.faces)


def _result(meshes, names, corresponded, prepared, chosen, ref, ref_faces, failures, timings,
            scores, params, grooming, why, changes, t_start, n_jobs, progress, keep_meshes=True
            ) -> CorrespondenceResult:
    out_meshes: list[TriMesh | None] = [None] * len(meshes)
    residuals: list[float | None] = [None] * len(meshes)
    per = timings.pop("_per_shape", {})
    shape_times = [per.get(i) for i in range(len(meshes))]
    measured = [i for i in sorted(corresponded) if not (i == chosen and not changes)]
    for i in corresponded:
        residuals[i] = 0.0  # the reference before any refinement: itself
    residuals_of = run_jobs(_residual_job, [(i, (_handle(corresponded, i), prepared[i]))
                                            for i in measured],
                            common=ref_faces, n_jobs=n_jobs, label="measuring",
                            progress=sub_progress(progress, 0.95, 1.0))
    for i in measured:
        residuals[i] = residuals_of[i]
    if keep_meshes:
        for i in corresponded:
            out_meshes[i] = TriMesh(corresponded[i], ref_faces, names[i])
    times = [t for t in per.values()]
    timings.update(total=time.perf_counter() - t_start,
                   per_shape_mean=float(np.mean(times)) if times else 0.0,
                   per_shape_max=float(np.max(times)) if times else 0.0, n_jobs=int(n_jobs))
    timings.setdefault("cpu_total", 0.0)
    timings.setdefault("assignment_total", 0.0)
    timings.setdefault("n_registrations", 0)
    report(progress, 1.0, "done")
    return CorrespondenceResult(
        meshes=out_meshes, reference_index=chosen,
        reference_name=ref.name or ("reference" if chosen is None else names[chosen]),
        faces=ref_faces, residuals_mm=residuals, failures=failures, timings=timings,
        candidate_scores=scores, shape_timings=shape_times, params=params, grooming=grooming,
        reference_reason=why, refinement=changes)
