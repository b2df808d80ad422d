"""The reference of a training-set run: candidates, resolution of what was given, selection.

Bernard et al., SPIE MI 2016 correspond every shape to one reference; which one matters
(its bumps and its tessellation become the model's until the groupwise refinement removes
most of that bias). ``reference="auto"`` takes the most typical input: closest to the median
of a pose- and scale-invariant descriptor (principal extents and the isoperimetric ratio),
excluding coarse, repaired and unrepresentative inputs (:func:`pick_reference_candidates`).
With several candidates each is tried on a subset of the shapes and the most compact model
kept (compactness after Davies et al., "Minimum Description Length Shape Modelling", 2002,
as the mean per-vertex variance after similarity GPA; :func:`compactness`), or the lowest
mean pair residual. Used by :mod:`core.correspondence.batch`.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np

from core.correspondence.grooming import GroomingError, describe, groom_mesh
from core.correspondence.pair import mesh_problem, normalise
from core.correspondence.store import open_mesh
from core.correspondence.tasks import make_tasks, run_tasks, spread_pick
from core.geometry import mesh as meshops
from core.types import TriMesh

if TYPE_CHECKING:
    from core.correspondence.batch import CorrespondenceRun


def descriptor(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Pose- and scale-invariant shape summary: principal extents and the isoperimetric ratio."""
    xn, _, scale = normalise(np.asarray(vertices, dtype=np.float64))
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
                "descriptor": descriptor(prepared[i].vertices, prepared[i].faces)} for i in usable}
    return pick_candidates(info, usable, n, grooming, names)


def pick_candidates(info: dict[int, dict], usable: list[int], n: int, grooming: dict,
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


def compactness(shapes: np.ndarray) -> float:
    """Mean per-vertex variance after similarity GPA, over the squared mean size (lower = compact)."""
    from core.alignment.transforms import generalized_procrustes

    if len(shapes) < 2:
        return 0.0
    res = generalized_procrustes(shapes, "similarity", max_iter=20, tol=1e-5)
    size2 = float(((res.mean - res.mean.mean(axis=0)) ** 2).sum(axis=1).mean())
    return float(((res.aligned - res.mean) ** 2).sum(axis=2).mean() / max(size2, 1e-300))


def resolve_reference(run: CorrespondenceRun, reference: Any, n_references: int
                      ) -> tuple[list, TriMesh | None, str]:
    """(candidate indices or [None], external reference mesh or None, reason)."""
    names, prepared = run.names, run.prepared
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
            raise ValueError(f"{names[idx]}: {run.failures.get(names[idx])}")
        problem = mesh_problem(open_mesh(prepared[idx]), need_closed=True)
        if problem:
            raise ValueError(f"{names[idx]}: {problem}")
        return [idx], None, "given (by index or name)"
    if reference != "auto":
        raise ValueError(f"reference must be 'auto', an index or a TriMesh, got {reference!r}")
    return _automatic(run, n_references)


def _automatic(run: CorrespondenceRun, n_references: int) -> tuple[list, TriMesh | None, str]:
    """:func:`resolve_reference` for ``"auto"``: the most typical closed inputs, or a
    repaired copy of the most typical one when none is closed as given."""
    names, usable, info, failures = run.names, run.usable, run.info, run.failures
    closed = [i for i in usable if info[i]["closed"]]
    if not closed and usable:
        # None is closed as given (grooming off): the most typical one that grooming repairs
        # serves, as a repaired copy (every input is still corresponded as it is)
        order, _ = pick_candidates(info, usable, len(usable), run.grooming, names)
        problems = {}
        for i in order:
            try:
                repaired, rep = groom_mesh(open_mesh(run.prepared[i]), {"remesh": False})
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
    candidates, why = pick_candidates(info, closed, n_references, run.grooming, names)
    return candidates, None, why


def select_reference(run: CorrespondenceRun, candidates: list, external: TriMesh | None,
                     params: dict, selection: str, selection_shapes: int
                     ) -> tuple[int | None, dict, dict, list[int], float]:
    """Correspond the selection subset to every candidate; keep the best (compactness or
    residual). Returns (chosen, scores, results so far, shapes still to do, progress).

    A single candidate is the reference without trials: every shape is left to the main
    pass (whose results stream; its score, the mean pair residual, is 0.0 as those are
    not computed for one candidate)."""
    names, usable, prepared = run.names, run.usable, run.prepared
    if len(candidates) == 1:
        c = candidates[0]
        name = _external_name(external) if c is None else names[c]
        return c, {name: 0.0, "_n_registrations": 0}, {}, [i for i in usable if i != c], 0.1
    if len(candidates) > 1 and len(usable) > max(int(selection_shapes), len(candidates)):
        others = [i for i in usable if i not in candidates]
        n_more = max(int(selection_shapes) - len(candidates), 1)
        subset = sorted(set(candidates) | set(spread_pick(others, n_more)))
    else:
        subset = list(usable)
    tasks = []
    for c in candidates:
        ref = external if c is None else open_mesh(prepared[c])
        assert ref is not None  # a None candidate comes with its external mesh
        tasks += make_tasks(ref, c, {i: prepared[i] for i in subset if i != c}, params)
    rest = [i for i in usable if i not in subset]
    split = 0.1 + 0.5 * len(tasks) / max(len(tasks) + len(rest), 1)
    results = run_tasks(tasks, run.n_jobs, run.progress, 0.1, split)
    scores: dict[str, Any] = {}
    best: tuple[tuple[int, float], int | None] | None = None
    for c in candidates:
        score, n_shapes = _score(run, c, results, subset, selection, len(candidates))
        scores[_external_name(external) if c is None else names[c]] = score
        key = (-n_shapes, score)
        if best is None or key < best[0]:
            best = (key, c)
    assert best is not None  # at least two candidates here
    chosen = best[1]
    done = {i: results[(chosen, i)] for i in subset if chosen is None or i != chosen}
    scores["_n_registrations"] = len(tasks)
    return chosen, scores, done, rest, split


def _external_name(external: TriMesh | None) -> str:
    return (external.name if external is not None else None) or "reference"


def _score(run: CorrespondenceRun, c: int | None, results: dict, subset: list[int], selection: str,
           n_candidates: int) -> tuple[float, int]:
    """(selection score, shapes corresponded) of candidate ``c`` on the subset."""
    outs = [results[(c, i)][0] for i in subset if c is None or i != c]
    shapes = [o["vertices"] for o in outs if o is not None]
    if c is not None:
        shapes.append(np.asarray(open_mesh(run.prepared[c]).vertices, float))
    resid = [o["residual_mm"] for o in outs if o is not None and o["residual_mm"] is not None]
    if selection == "compactness" and n_candidates > 1:
        score = compactness(np.stack(shapes)) if len(shapes) >= 2 else np.inf
    else:
        score = float(np.mean(resid)) if resid else 0.0
    return score, len(shapes)
