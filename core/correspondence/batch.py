"""Correspondence of a whole training set: grooming, reference choice, pairwise runs, refinement.

The batch layer of Bernard et al., SPIE MI 2016 (the package docstring has the method): it
grooms every input (:mod:`core.correspondence.grooming`), picks a representative reference,
corresponds every shape to it in a process pool, flags shapes that lie far from all others,
and refines groupwise: every shape is corresponded again to the evolving mean shape (as
population-based methods do; Heimann & Meinzer, Medical Image Analysis 2009), which removes
most of the reference's bias.

One run is a :class:`CorrespondenceRun` (the state the stages share; its methods are the
stages). The stages' work is in :mod:`~core.correspondence.inputs` (reading, grooming, the
reference's remesh), :mod:`~core.correspondence.reference` (candidates, selection),
:mod:`~core.correspondence.checks` (mirrored sides, switched poses, outliers) and
:mod:`~core.correspondence.refinement` (the groupwise passes, the safeguard's judging); the
per-shape jobs in :mod:`~core.correspondence.tasks`.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, MutableMapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.correspondence.checks import drop_flagged, recheck_switched
from core.correspondence.inputs import default_count, mesh_name, prepare_inputs, remesh_reference
from core.correspondence.pair import DEFAULT_CPD_PARAMS
from core.correspondence.reference import resolve_reference, select_reference
from core.correspondence.refinement import refine_guarded
from core.correspondence.store import InputFile, Scratch, open_mesh, open_rows
from core.correspondence.tasks import add_timings, make_tasks, run_tasks, vertex_handle
from core.runtime.parallel import preload_in_workers, run_jobs
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
        reference turned them from their input orientation
        (:func:`core.correspondence.checks.recheck_switched`).
    safeguard : dict
        What the safeguard (:mod:`core.correspondence.safeguard`) tried, its criterion's
        values and what it kept: ``{"enabled", "stages": [...]}``.
    mirror_report : dict
        When the mirror check compared suspects with the others' mean
        (:func:`core.correspondence.checks.flag_mirrored`):
        ``{"suspects": name -> mirror ratio against the others' mean, "handedness": the
        others' (None when not measured), "flagged": names left out, "note": why the others
        were kept}``; empty otherwise.
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
    mirror_report: dict = field(default_factory=dict)

    def provenance(self) -> dict:
        """What a model built from this result keeps of it (``ShapeModel.info["correspondence"]``):
        the reference, the mean residual, the failures, what the safeguard kept and the mirror
        check's findings."""
        ok = [r for r in self.residuals_mm if r is not None]
        return {"reference": self.reference_name,
                "mean_residual_mm": float(np.mean(ok)) if ok else None,
                "failures": dict(self.failures), "safeguard": self.safeguard,
                "mirror_report": self.mirror_report}

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
            "mirror_report": self.mirror_report,
        }


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
    return default_count([len(m.vertices) for m in meshes])



def _residual_job(item: tuple, faces: np.ndarray) -> float:
    """core.runtime.parallel job: symmetric mean surface distance (mm) between a corresponded shape
    (vertices or their handle) and its groomed input (a mesh handle)."""
    from core.geometry.toolkit import symmetric_surface_distance

    vertices, target = item
    mesh = open_mesh(target)
    return symmetric_surface_distance(open_rows(vertices), faces, mesh.vertices, mesh.faces)


@dataclass
class CorrespondenceRun:
    """One run of :func:`establish_correspondence`: the state its stages share, the stages
    as methods (:meth:`run`), the stages' work in :mod:`~core.correspondence.inputs`,
    :mod:`~core.correspondence.reference`, :mod:`~core.correspondence.checks` and
    :mod:`~core.correspondence.refinement`.

    Per shape index: ``prepared`` (the groomed input, a mesh or its scratch handle; None
    where it failed), ``info`` (what reference selection needs), ``corresponded`` (the
    current correspondence, in memory or in the scratch store's rows); per name:
    ``failures``, ``grooming`` (what grooming did), ``unread``.
    """

    meshes: list
    params: dict
    store: Scratch | None
    record: dict
    n_jobs: int
    progress: ProgressCallback | None = None
    on_shape: Callable[[int, TriMesh], None] | None = None
    names: list[str] = field(default_factory=list)
    handles: list = field(default_factory=list)
    prepared: list = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)
    grooming: dict[str, dict] = field(default_factory=dict)
    info: dict[int, dict] = field(default_factory=dict)
    unread: dict[str, str] = field(default_factory=dict)
    usable: list[int] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    corresponded: MutableMapping = field(default_factory=dict)
    mirror_report: dict = field(default_factory=dict)
    chosen: int | None = None
    reference: TriMesh | None = None
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), int))
    streamed: set[int] = field(default_factory=set)
    t_start: float = field(default_factory=time.perf_counter)

    def __post_init__(self) -> None:
        self.names = [mesh_name(m, i) for i, m in enumerate(self.meshes)]
        self.handles = [m if isinstance(m, (TriMesh, InputFile)) else InputFile(str(m))
                        for m in self.meshes]

    def run(self, reference: Any, *, n_references: int, selection: str, selection_shapes: int,
            groom: bool | dict, vertices: int | None, refine: int,
            on_provisional: Callable | None, on_unreadable: Callable | None,
            keep_meshes: bool) -> CorrespondenceResult:
        """Every stage in turn: inputs, reference and the reference-based pass, the checks,
        the refinement passes (streaming the final results), the result."""
        labelled = self.record.pop("labelling", False)
        t_groom = self.prepare(groom, vertices, on_unreadable)
        candidates, external, why = resolve_reference(self, reference, n_references)
        remesh_reference(self, candidates, groom, vertices)
        # The batch measures its final outputs itself; before a refinement pass the first pass
        # only has to give the mean shape, so it skips labelling and fairing (plain
        # CPD-then-project; the refinement labels and fairs every shape).
        first = dict(self.params, pair_residual=selection == "residual" and len(candidates) > 1)
        if refine >= 1 and len(self.usable) >= 4 and not (self.record["enabled"] or labelled):
            first["labelling"] = False  # (a safeguard's rollback needs the labelled result)
        scores, results = self.first_pass(candidates, external, first, selection,
                                          selection_shapes, t_groom)
        poses = {self.names[k]: note for k, note in recheck_switched(self, results, first).items()}
        drop_flagged(self, results, first)
        del results  # per-shape summaries of the first pass: not needed any more
        if on_provisional is not None and refine > 0:
            for k in sorted(self.corresponded):
                on_provisional(k, TriMesh(self.corresponded[k], self.faces, self.names[k]))
        changes = self.refine(refine)
        result = self.result(scores, why, changes, keep_meshes)
        result.unreadable, result.poses, result.safeguard = self.unread, poses, self.record
        result.mirror_report = self.mirror_report
        return result

    def prepare(self, groom: bool | dict, vertices: int | None,
                on_unreadable: Callable | None) -> float:
        """Read and groom the inputs (:func:`~core.correspondence.inputs.prepare_inputs`);
        the unreadable ones go to ``on_unreadable``. Returns the seconds it took."""
        report(self.progress, 0.0, "grooming")
        prepare_inputs(self, groom, vertices)
        if on_unreadable is not None:
            for i, name in enumerate(self.names):
                if name in self.unread:
                    on_unreadable(i, self.unread[name])
        if len(self.unread) == len(self.meshes):
            raise ValueError("no input mesh could be read: "
                             + "; ".join(f"{k}: {v}" for k, v in self.unread.items()))
        t_groom = time.perf_counter() - self.t_start
        self.usable = [i for i, m in enumerate(self.prepared) if m is not None]
        return t_groom

    def first_pass(self, candidates: list, external: TriMesh | None, first: dict,
                   selection: str, selection_shapes: int, t_groom: float) -> tuple[dict, dict]:
        """Choose the reference among the candidates
        (:func:`~core.correspondence.reference.select_reference`) and correspond every
        usable shape to it; the shapes' vertices go to ``corresponded`` as they arrive.
        Returns (candidate scores, per-shape results: summaries without the vertices)."""
        chosen, scores, results, rest, split = select_reference(self, candidates, external, first,
                                                                selection, selection_shapes)
        n_trial = scores.pop("_n_registrations") - len(results)  # trial runs of the losers
        ref = external if chosen is None else open_mesh(self.prepared[chosen])
        assert ref is not None  # an external reference when no input is chosen
        self.chosen, self.reference = chosen, ref
        self.faces = np.asarray(ref.faces).copy()
        self.corresponded = {} if self.store is None else self.store.rows("corresponded",
                                                                           len(ref.vertices))

        def absorb(key: tuple, value: tuple) -> tuple:  # streaming: the client keeps no vertices
            out, err = value
            if out is None:
                return value
            self.corresponded[key[1]] = out["vertices"]
            return {k: v for k, v in out.items() if k != "vertices"}, err

        results.update({k[1]: v for k, v in run_tasks(
            make_tasks(ref, chosen, {i: self.prepared[i] for i in rest}, first), self.n_jobs,
            self.progress, split, 0.6, on_result=absorb).items()})
        self.timings = {"grooming": t_groom, "n_registrations": n_trial}
        self._collect(results)
        return scores, results

    def _collect(self, results: dict) -> None:
        """Corresponded vertices per input index (the reference itself included) into
        ``corresponded`` (results whose vertices already went there as they arrived keep
        only a summary); failed shapes into ``failures``."""
        assert self.reference is not None
        for i in self.usable:
            if self.chosen is not None and i == self.chosen:
                self.corresponded[i] = np.asarray(self.reference.vertices, float).copy()
                continue
            res, err = results[i]
            if err is not None:
                self.failures[self.names[i]] = f"correspondence failed: {err}"
                continue
            if "vertices" in res:
                self.corresponded[i] = res["vertices"]
            add_timings(self.timings, i, res)

    def stream(self, k: int, v: np.ndarray) -> None:
        """Hand shape ``k``'s result to ``on_shape`` (once)."""
        if self.on_shape is not None and k not in self.streamed:
            self.streamed.add(k)
            self.on_shape(k, TriMesh(v, self.faces, self.names[k]))

    def _final(self, key: tuple, value: tuple) -> None:
        """A last-pass result is final (a failure keeps the previous result)."""
        self.stream(key[1], value[0]["vertices"] if value[0] is not None else self.corresponded[key[1]])

    def refine(self, passes: int) -> list[float]:
        """The groupwise refinement passes
        (:func:`~core.correspondence.refinement.refine_guarded`), streaming the final
        results; the mean change of each pass."""
        on_last = self._final if self.on_shape is not None else None
        changes, again = refine_guarded(self, passes, on_last)
        for k in sorted(self.corresponded) if self.on_shape is not None else ():
            if k not in self.streamed or again:  # untouched by a pass (refine=0, < 3 shapes), or replaced
                self.streamed.discard(k)
                self.stream(k, self.corresponded[k])
        return changes

    def result(self, scores: dict, why: str, changes: list[float],
               keep_meshes: bool = True) -> CorrespondenceResult:
        """The outputs measured against their groomed inputs, and the result."""
        n = len(self.meshes)
        out_meshes: list[TriMesh | None] = [None] * n
        residuals: list[float | None] = [None] * n
        timings, corresponded, chosen = self.timings, self.corresponded, self.chosen
        per = timings.pop("_per_shape", {})
        shape_times = [per.get(i) for i in range(n)]
        measured = [i for i in sorted(corresponded) if not (i == chosen and not changes)]
        for i in corresponded:
            residuals[i] = 0.0  # the reference before any refinement: itself
        residuals_of = run_jobs(_residual_job, [(i, (vertex_handle(corresponded, i), self.prepared[i]))
                                                for i in measured],
                                common=self.faces, n_jobs=self.n_jobs, label="measuring",
                                progress=sub_progress(self.progress, 0.95, 1.0))
        for i in measured:
            residuals[i] = residuals_of[i]
        if keep_meshes:
            for i in corresponded:
                out_meshes[i] = TriMesh(corresponded[i], self.faces, self.names[i])
        times = list(per.values())
        timings.update(total=time.perf_counter() - self.t_start,
                       per_shape_mean=float(np.mean(times)) if times else 0.0,
                       per_shape_max=float(np.max(times)) if times else 0.0, n_jobs=int(self.n_jobs))
        timings.setdefault("cpu_total", 0.0)
        timings.setdefault("assignment_total", 0.0)
        timings.setdefault("n_registrations", 0)
        report(self.progress, 1.0, "done")
        assert self.reference is not None
        return CorrespondenceResult(
            meshes=out_meshes, reference_index=chosen,
            reference_name=self.reference.name or ("reference" if chosen is None else self.names[chosen]),
            faces=self.faces, residuals_mm=residuals, failures=self.failures, timings=timings,
            candidate_scores=scores, shape_timings=shape_times, params=self.params,
            grooming=self.grooming, reference_reason=why, refinement=changes)


def establish_correspondence(meshes: Sequence[TriMesh | InputFile | str | os.PathLike],
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
        ``"auto"``: the most typical usable input
        (:func:`~core.correspondence.reference.pick_reference_candidates`), or with
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
    if cpd_params.get("labelling"):  # given: the first pass labels too (CorrespondenceRun.run pops it)
        record["labelling"] = True
    if safeguard:
        from core.correspondence.safeguard import REMESH_TRIAL_SHARE, choose_remesh

        # the trial reports (and so can be cancelled) like the run itself
        groom, trial = choose_remesh(list(meshes), reference, groom, vertices, n_jobs, cpd_params,
                                     sub_progress(progress, 0.0, REMESH_TRIAL_SHARE,
                                                  "remesh trial: "))
        if trial:
            record["stages"].append(trial)
            progress = sub_progress(progress, REMESH_TRIAL_SHARE, 1.0)
    store = None if scratch is None else Scratch(scratch)
    try:
        run = CorrespondenceRun(list(meshes), params, store, record,
                                (os.cpu_count() or 1) if n_jobs is None else int(n_jobs),
                                progress, on_shape)
        return run.run(reference, n_references=n_references, selection=selection,
                       selection_shapes=selection_shapes, groom=groom, vertices=vertices,
                       refine=refine, on_provisional=on_provisional, on_unreadable=on_unreadable,
                       keep_meshes=keep_meshes)
    finally:
        if store is not None:
            store.remove()
