"""A safeguard on the optional stages of correspondence: each is kept only where it helps.

Grooming's remesh to a common vertex count and every groupwise refinement pass
(:mod:`core.correspondence.batch`) are optional stages that help on some data and hurt on
other data (issue 27: on a population of uneven tessellations the remesh doubled the
homology spread and a normal-offsets pass doubled it again). The batch cannot see the true
homologies, so each stage is judged by a criterion computed on the data set alone, the
**generalisation ability** of the resulting linear shape model (Davies, Twining, Cootes,
Waterton & Taylor, IEEE TMI 2002; Styner, Rajamani, Nolte, Zsemlye, Szekely, Taylor &
Davies, "Evaluation of 3D correspondence methods for model building", IPMI 2003): every
shape of a subset is left out in turn, a PCA model is built from the others (similarity
GPA, all their modes), and the left-out shape's correspondence is reconstructed by the
model (projection onto its modes in the mean's frame, mapped back to the shape's pose). The
error of a fold is the mean distance (mm) of the reconstruction's points from the shape's
corresponded points, plus the mean distance of those points from the shape's **raw input
surface** (not its groomed, remeshed one), so that a stage whose points leave the input
surface cannot look good. Lower is better. Inconsistent correspondences (a point that slides
one way on one shape and another way on the next) are what the others' model cannot
predict, so the criterion rises with them.

The reconstruction's surface distance to the raw input alone (``surface_mm``, also
returned) was tried first and is blind to sliding along the surface: on a population of
uneven tubes (``bench_safeguard.py``, tube-uneven) a normal-offsets pass lowered the true
spread from 2.54 to 0.66 mm and that criterion by 1.2 % only (the point error above by 28 %).

The stages are judged as follows (each choice, its criterion values and what was kept are
recorded in ``CorrespondenceResult.safeguard`` and so in ``correspondence.json``):

- the remesh: the batch is run on a subset of at most :data:`REMESH_SHAPES` shapes with and
  without it (reference-based, no refinement), and the remesh is kept only when the
  criterion is lower with it by more than :data:`KEEP_MARGIN` (the run that fails fewer
  inputs wins first; both are judged on the shapes both kept). The subset includes the
  reference the whole batch takes (:func:`batch_reference`), which the remesh is of (until
  2026-12-07 a subset of a larger set took its own most typical shape, and so judged another
  shape's remesh);
- a refinement pass: both deformations (``refine_deformation``, by default
  ``"normal_offsets"``, and the other one, ``"cpd"``) are run from the same start and judged
  by the criterion on at most :data:`MODEL_SHAPES` shapes. The configured one is kept if it
  lowers the criterion by more than :data:`KEEP_MARGIN`; the other one replaces it if it
  lowers the criterion by more than the margin again, below the configured one's (or below
  the start's, when the configured one does not pass). Otherwise the pass is rolled back
  (the shapes' previous correspondences restored) and refinement stops there. (Until
  2026-12-04 the other deformation was tried only after a roll-back, so a far better pass
  could stay untried.)
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, MutableMapping, Sequence

import numpy as np

from core.correspondence.store import VertexRows
from core.correspondence.tasks import spread_pick
from core.runtime.progress import ProgressCallback, sub_progress
from core.types import TriMesh

MODEL_SHAPES = 24   # shapes of the generalisation model (evenly spread over the data set)
FOLDS = 12          # of them left out in turn
REMESH_SHAPES = 8   # shapes of the remesh trial
MIN_SHAPES = 4      # fewer usable shapes: no safeguard (a model of 2 shapes says nothing)
REMESH_TRIAL_SHARE = 0.25  # of a batch's progress bar (the trial runs a subset twice)
KEEP_MARGIN = 0.05  # a stage is kept only when it lowers the criterion by more than this share.
# Chosen on the tuning populations (bench_safeguard.py): the stages that truly helped lowered
# it by 7-11 %; a remesh that truly hurt by 1.7 % (bean-even, true spread 1.165 against 1.009
# mm) and a CPD pass that truly hurt by 2.5 % (six uneven beans, 1.665 against 1.458 mm).


def loo_generalisation(shapes: Sequence[np.ndarray], faces: np.ndarray, raw: Sequence[TriMesh],
                       *, folds: int = FOLDS) -> dict:
    """Leave-one-out generalisation (module docstring) of corresponded ``shapes`` (K, N, 3)
    with ``faces``, against the raw input surfaces ``raw`` (one per shape): ``{"value":
    mean over the folds (mm), "folds": per left-out shape (mm), "surface_mm": the
    reconstruction's symmetric surface distance to the raw input, for comparison}``."""
    from core.alignment.transforms import apply_transform, fit_transform, generalized_procrustes
    from core.geometry.toolkit import closest_points_on_surface, symmetric_surface_distance

    stack = np.stack([np.asarray(s, dtype=np.float64) for s in shapes])
    k_all = len(stack)
    if k_all < 3:
        raise ValueError(f"leave-one-out generalisation needs at least 3 shapes, got {k_all}")
    aligned = generalized_procrustes(stack, "similarity", max_iter=20, tol=1e-6).aligned
    errors, surface = [], []
    for k in spread_pick(range(k_all), folds):
        others = np.delete(aligned, k, axis=0).reshape(k_all - 1, -1)
        mean = others.mean(axis=0)
        _, _, vt = np.linalg.svd(others - mean, full_matrices=False)
        basis = vt[:k_all - 2]  # every mode of the others (K - 2 for K - 1 centred shapes)
        pose = fit_transform(stack[k], mean.reshape(-1, 3), "similarity")
        y = apply_transform(pose, stack[k]).ravel() - mean
        rebuilt = (mean + basis.T @ (basis @ y)).reshape(-1, 3)
        back = apply_transform(np.linalg.inv(pose), rebuilt)
        rv, rf = np.asarray(raw[k].vertices, float), np.asarray(raw[k].faces)
        off_raw = float(closest_points_on_surface(stack[k], rv, rf)[1].mean())
        errors.append(float(np.linalg.norm(back - stack[k], axis=1).mean()) + off_raw)
        surface.append(symmetric_surface_distance(back, faces, rv, rf))
    return {"value": float(np.mean(errors)), "folds": [float(e) for e in errors],
            "surface_mm": float(np.mean(surface))}


def raw_mesh(handle) -> TriMesh:
    """The raw input behind a batch input (a TriMesh, an InputFile or a path)."""
    from core.correspondence.store import InputFile, read_input

    if isinstance(handle, TriMesh):
        return handle
    path = handle.path if isinstance(handle, InputFile) else str(handle)
    mesh, problem, _ = read_input(path)
    if mesh is None:
        raise ValueError(f"{path}: {problem}")
    return mesh


def _remesh_on(groom) -> bool:
    return groom is not False and (not isinstance(groom, dict) or groom.get("remesh", True) is not False)


def choose_remesh(meshes: Sequence, reference, groom, vertices: int | None, n_jobs: int | None,
                  cpd_params: dict, progress: ProgressCallback | None = None
                  ) -> tuple[bool | dict, dict | None]:
    """(grooming options to use, the record) after the remesh trial (module docstring); the
    options unchanged and no record when the remesh is off or there are too few shapes.
    ``progress`` may raise :class:`core.runtime.progress.Cancelled` to stop the trial."""
    from core.correspondence.batch import default_vertex_count, establish_correspondence

    if not _remesh_on(groom) or len(meshes) < MIN_SHAPES:
        return groom, None
    pick = spread_pick(range(len(meshes)), REMESH_SHAPES)
    options = dict(groom) if isinstance(groom, dict) else {}
    ref = reference
    if not isinstance(reference, (int, np.integer, TriMesh)) and not (
            isinstance(reference, (str, os.PathLike)) and os.path.isfile(str(reference))):
        try:  # "auto" or an input's name: the input the whole batch will take
            ref = batch_reference(meshes, reference, options, vertices, n_jobs, cpd_params,
                                  sub_progress(progress, 0.0, 0.2, "reference: "))
        except ValueError:  # no input can serve: the batch says so itself
            return groom, None
    if isinstance(ref, (int, np.integer)) and not isinstance(ref, bool):
        reference = ref
        pick = sorted(set(pick[:-1]) | {int(reference)}) if int(reference) not in pick else pick
        ref = pick.index(int(reference))
    elif ref is None:
        ref = "auto"  # a repaired copy of an input: the subset's own choice
    raw = []
    for i in list(pick):
        try:
            raw.append(raw_mesh(meshes[i]))
        except ValueError:  # an unreadable input: the batch reports it; the trial goes without
            if isinstance(ref, int) and not isinstance(ref, bool):
                if pick.index(i) == ref:
                    return groom, None  # the reference itself: the batch refuses it
                ref -= int(pick.index(i) < ref)
            pick.remove(i)
    if len(raw) < MIN_SHAPES:
        return groom, None
    if vertices is None and all(isinstance(m, TriMesh) for m in meshes):
        vertices = default_vertex_count(list(meshes))
    values, results = {}, {}
    for span, (label, remesh) in zip(((0.2, 0.6), (0.6, 1.0)), (("remesh", True),
                                                               ("no remesh", False))):
        try:
            results[label] = establish_correspondence(
                raw, ref, groom=dict(options, remesh=remesh), vertices=vertices, refine=0,
                n_jobs=n_jobs, safeguard=False, progress=sub_progress(progress, *span, f"{label}: "),
                **cpd_params)
        except ValueError as exc:
            values[label] = {"value": None, "error": str(exc)}
    # both judged on the shapes both kept (the mirror check may leave out different members
    # of a two-handed population in each run): a mean over different shapes is no comparison
    common = set(range(len(raw)))
    for res in results.values():
        common &= {j for j, m in enumerate(res.meshes) if m is not None}
    for label, res in results.items():
        values[label] = _criterion_of(res, raw, common if len(common) >= 3 else None)
    keep = _better(values["remesh"], values["no remesh"])
    record = {"stage": "remesh", "tried": ["remesh", "no remesh"], "shapes": [raw[j].name for j in
                                                                               range(len(pick))],
              "criterion_mm": {k: v.get("value") for k, v in values.items()},
              "failed": {k: v.get("failed") for k, v in values.items()},
              "kept": "remesh" if keep else "no remesh"}
    if isinstance(ref, int) and not isinstance(ref, bool):
        record["reference"] = raw[ref].name
    return (groom if keep else dict(options, remesh=False)), record


def batch_reference(meshes: Sequence, reference, options: dict, vertices: int | None,
                    n_jobs: int | None, cpd_params: dict,
                    progress: ProgressCallback | None = None) -> int | None:
    """The index of the input that the batch of all ``meshes`` takes as its reference
    (``"auto"``: the most typical one; or an input's name), from the inputs groomed as the
    batch grooms them but without the remesh (a remesh hardly moves the pose- and
    scale-invariant descriptor the choice is made by); with several candidates
    (``n_references``), the most typical. None when the batch would use a repaired copy.

    The remesh trial must judge this reference's remesh: the remesh is of the reference
    alone (``core.correspondence.inputs.remesh_reference``), and the most typical shape of
    a subset is often another one (issue 27: in a population of 12 thin tubes the trial's
    own reference lowered the criterion by 35 % with the remesh, where the batch's reference
    gave the same true spread with or without it)."""
    from core.correspondence.batch import CorrespondenceRun, _check_params
    from core.correspondence.reference import resolve_reference

    run = CorrespondenceRun(list(meshes), _check_params(dict(cpd_params), "compactness"), None,
                            {"enabled": False, "stages": []},
                            (os.cpu_count() or 1) if n_jobs is None else int(n_jobs), progress)
    run.prepare(dict(options, remesh=False), vertices, None)
    candidates, external, _ = resolve_reference(run, reference, 1)
    return None if external is not None or candidates[0] is None else int(candidates[0])


def _criterion_of(result, raw: Sequence[TriMesh], shapes: set[int] | None = None) -> dict:
    """The criterion of a trial run over its corresponded shapes among ``shapes`` (all when
    None), and how many of the inputs the run failed."""
    ok = [j for j, m in enumerate(result.meshes) if m is not None]
    failed = len(raw) - len(ok)
    ok = [j for j in ok if shapes is None or j in shapes]
    if len(ok) < 3:
        return {"value": None, "error": "fewer than 3 shapes corresponded", "failed": failed}
    return dict(loo_generalisation([result.meshes[j].vertices for j in ok], result.faces,
                                   [raw[j] for j in ok]), failed=failed)


def _better(with_stage: dict, without: dict) -> bool:
    """Keep the stage: fewer shapes failed with it, or as many and its criterion is lower
    (a criterion over fewer shapes is no comparison)."""
    if with_stage.get("value") is None:
        return False
    if without.get("value") is None or with_stage["failed"] != without["failed"]:
        return without.get("value") is None or with_stage["failed"] < without["failed"]
    return with_stage["value"] < (1.0 - KEEP_MARGIN) * without["value"]


def refinement_choice(before: float, criterion: Mapping[str, float], first: str,
                      margin: float = KEEP_MARGIN) -> str | None:
    """The deformation a refinement pass keeps (module docstring), or None to roll it back.

    ``before``: the criterion before the pass; ``criterion``: after each deformation tried,
    from the same start; ``first``: the configured one. It is kept if it lowers the criterion
    by more than ``margin`` (:data:`KEEP_MARGIN`; other margins for the benchmarks' offline
    scoring); another replaces it only if it lowers the criterion by more than the margin
    again (the criterion's own noise is a few per cent, and the margin is for every choice
    the guard makes)."""
    keep = 1.0 - margin
    kept = first if criterion[first] < keep * before else None
    for deformation, value in criterion.items():
        if deformation != first and value < keep * (before if kept is None else criterion[kept]):
            kept = deformation
    return kept


class RefinementGuard:
    """Judges the groupwise refinement passes of one batch (module docstring).

    ``raw`` gives the raw input of a shape index (read on demand, kept for the model's
    shapes only); :meth:`refine` runs the passes through ``run_pass`` (one pass of
    :func:`core.correspondence.refinement.refine`) and returns their mean vertex changes."""

    def __init__(self, raw: Callable[[int], TriMesh]):
        self._raw_of = raw
        self._raw: dict[int, TriMesh] = {}
        self.record: dict = {"stage": "refinement", "passes": []}

    def criterion(self, vertices: Mapping, faces: np.ndarray, keys: list[int]) -> float:
        for k in keys:
            if k not in self._raw:
                self._raw[k] = self._raw_of(k)
        return loo_generalisation([vertices[k] for k in keys], faces,
                                  [self._raw[k] for k in keys])["value"]

    def refine(self, vertices: MutableMapping, faces: np.ndarray, params: dict, passes: int,
               run_pass: Callable[[dict], list[float]]) -> list[float]:
        """Up to ``passes`` guarded passes of ``params["refine_deformation"]``."""
        keys = spread_pick(sorted(vertices), MODEL_SHAPES)
        if passes <= 0:
            return []
        if len(keys) < MIN_SHAPES:
            self.record["note"] = f"not judged: {len(keys)} shapes (at least {MIN_SHAPES})"
            return _unguarded(run_pass, params, passes)
        best = self.criterion(vertices, faces, keys)
        self.record["before_mm"] = best
        changes: list[float] = []
        for it in range(int(passes)):
            entry, value, change = self._one_pass(vertices, faces, params, keys, best, run_pass)
            entry["pass"] = it + 1
            self.record["passes"].append(entry)
            if value is None:
                break
            best = value
            params = dict(params, refine_deformation=entry["kept"])
            changes.append(change)
        self.record["after_mm"] = best
        return changes

    def _one_pass(self, vertices: MutableMapping, faces: np.ndarray, params: dict,
                  keys: list[int], best: float, run_pass: Callable) -> tuple[dict, float | None, float]:
        """One pass: both deformations from the same start, the kept one chosen by
        :func:`refinement_choice` (none: the pass is rolled back).
        Returns (record entry, new criterion or None when rolled back, mean change).

        Both are always judged: trying the other one only after a roll-back left a far
        better pass untried (issue 27: on thin tubes a normal-offsets pass lowered the
        criterion from 0.947 to 0.737 mm and was kept, where a CPD pass, never tried, gave
        0.472 mm and the lower true spread, 1.08 against 1.52 mm)."""
        first = params["refine_deformation"]
        other = "cpd" if first == "normal_offsets" else "normal_offsets"
        before = _snapshot(vertices, "before")
        first_result: MutableMapping | None = None
        try:
            tried: dict[str, float] = {}
            changes: dict[str, float] = {}
            for deformation in (first, other):
                if tried:
                    _restore(vertices, before)
                change = run_pass(dict(params, refine_deformation=deformation))
                tried[deformation] = self.criterion(vertices, faces, keys)
                changes[deformation] = float(change[0]) if change else 0.0
                if deformation == first and tried[first] < (1.0 - KEEP_MARGIN) * best:
                    first_result = _snapshot(vertices, "first")  # it may be kept
            kept = refinement_choice(best, tried, first)
            if kept is not None:
                if kept == first and first_result is not None:
                    _restore(vertices, first_result)
                return ({"before_mm": best, "criterion_mm": tried, "kept": kept},
                        tried[kept], changes[kept])
            _restore(vertices, before)
            return ({"before_mm": best, "criterion_mm": tried, "kept": "none (rolled back)"},
                    None, 0.0)
        finally:
            for copy in (before, first_result):
                if isinstance(copy, VertexRows):
                    copy.close()
                    os.remove(copy.path)


def _restore(vertices: MutableMapping, copy: Mapping) -> None:
    """Every shape's correspondence set back to ``copy`` (one row at a time)."""
    for k in copy:
        vertices[k] = copy[k]


def _snapshot(vertices: MutableMapping, name: str) -> MutableMapping:
    """A copy of every shape's correspondence to roll a pass back to: beside the rows file
    when they are kept on disk (the streaming client holds no mesh per shape), else in
    memory."""
    if isinstance(vertices, VertexRows):
        copy: MutableMapping = VertexRows(f"{vertices.path}.{name}", vertices.n_vertices)
    else:
        copy = {}
    for k in sorted(vertices):  # one row at a time
        copy[k] = np.array(vertices[k])
    return copy


def _unguarded(run_pass: Callable, params: dict, passes: int) -> list[float]:
    changes: list[float] = []
    for _ in range(int(passes)):
        changes += run_pass(params)
    return changes


def describe(record: Mapping) -> list[str]:
    """One line a judged stage of ``CorrespondenceResult.safeguard`` (the record above): what
    was tried, the criterion's values (mm) and what was kept, for the command line and the
    builder; ["off: ..."] when it was disabled, [] when nothing was judged."""
    if not record:
        return []
    if not record.get("enabled", True):
        return ["off: the remesh and every refinement pass kept as configured"]
    lines = []
    for stage in record.get("stages", ()):
        if stage.get("stage") == "remesh":
            values = stage.get("criterion_mm", {})
            with_it, without = values.get("remesh"), values.get("no remesh")
            shapes = len(stage.get("shapes", ()))
            if with_it is not None and with_it == without:  # grooming kept the tessellations
                lines.append(f"remesh left out: it changed nothing here (leave-one-out error "
                             f"{_mm(with_it)} either way, on {shapes} shapes)")
                continue
            lines.append(f"remesh {'kept' if stage.get('kept') == 'remesh' else 'left out'}: "
                         f"leave-one-out error {_mm(with_it)} with it, {_mm(without)} without "
                         f"(on {shapes} shapes)")
        elif stage.get("stage") == "refinement":
            if stage.get("note"):
                lines.append(f"refinement {stage['note']}")
            for entry in stage.get("passes", ()):
                tried = ", ".join(f"{name.replace('_', ' ')} {_mm(value)}"
                                  for name, value in entry.get("criterion_mm", {}).items())
                kept = str(entry.get("kept", ""))
                verdict = (f"rolled back (no deformation {100 * KEEP_MARGIN:.0f} % better)"
                           if kept.startswith("none") else f"{kept.replace('_', ' ')} kept")
                lines.append(f"refinement pass {entry.get('pass')}: {verdict}; leave-one-out "
                             f"error {_mm(entry.get('before_mm'))} before, {tried}")
    return lines


def _mm(value) -> str:
    return "n/a" if value is None else f"{float(value):.3f} mm"
