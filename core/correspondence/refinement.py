"""The groupwise refinement of a training-set run: every shape corresponded again to the mean.

After the reference-based pass of Bernard et al., SPIE MI 2016, every shape is corresponded
again to the evolving mean shape, as population-based methods do (Heimann & Meinzer,
Medical Image Analysis 2009), which removes most of the chosen reference's bias. A pass
poses the similarity-GPA mean on each shape by a fit over the shape's current
correspondence and moves it onto the shape by an affine map and smooth offsets along the
mean's normals (:mod:`core.correspondence.offsets`) or nonrigid CPD, then labels and fairs
(:func:`core.correspondence.pair.correspond_pair`). With the safeguard each pass is kept only
where the model's leave-one-out generalisation says it helps
(:class:`core.correspondence.safeguard.RefinementGuard`). Used by
:mod:`core.correspondence.batch`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from core.correspondence.tasks import add_timings, gpa, make_tasks, run_tasks, vertex_handle
from core.types import TriMesh

if TYPE_CHECKING:
    from core.correspondence.batch import CorrespondenceRun


def refine(run: CorrespondenceRun, params: dict, passes: int,
           on_last_pass: Callable | None = None,
           progress_span: tuple[float, float] = (0.6, 0.95)) -> list[float]:
    """Groupwise refinement: correspond every shape of ``run.corresponded`` again to the
    current mean shape, ``passes`` times; the mean vertex change (mm) of each pass.

    The mean of the similarity-aligned corresponded shapes is posed on each shape by a fit
    over the current correspondences (no rigid CPD needed; in the worker,
    :func:`core.correspondence.tasks.task_job`: affine for the default
    ``refine_deformation="normal_offsets"``, similarity for ``"cpd"``), moved onto the shape
    (:mod:`core.correspondence.offsets`, or nonrigid CPD), then labelled and faired as in the
    pairwise step. Each result replaces the shape's correspondence as it arrives (its job was
    the only reader of it); ``on_last_pass(key, (out, err))`` sees the last pass's results as
    they arrive (final). The passes report progress over ``progress_span`` of the run.
    """
    vertices = run.corresponded
    changes = []
    for it in range(int(passes)):
        keys = sorted(vertices)
        if len(keys) < 3:
            break
        mean_v, _ = gpa(vertices, keys, tol=1e-6)
        current = {k: vertex_handle(vertices, k) for k in keys}
        tasks = make_tasks(TriMesh(mean_v, run.faces, "mean"), "mean",
                           {k: run.prepared[k] for k in keys}, params, current)
        moved: dict[int, float] = {}
        last = it == int(passes) - 1

        def absorb(key: tuple, value: tuple, last: bool = last, moved: dict = moved) -> tuple:
            out, err = value
            k = key[1]
            if out is not None:  # else: keep the previous correspondence of this shape
                moved[k] = float(np.linalg.norm(out["vertices"] - vertices[k], axis=1).mean())
                vertices[k] = out["vertices"]
                add_timings(run.timings, k, out)
            if last and on_last_pass is not None:
                on_last_pass(key, value)
            return None, err

        lo, hi = progress_span
        start = lo + (hi - lo) * it / passes
        run_tasks(tasks, run.n_jobs, run.progress, start, start + (hi - lo) / passes,
                  on_result=absorb)
        ok = [moved[k] for k in keys if k in moved]
        changes.append(float(np.mean(ok)) if ok else 0.0)
    return changes


def pass_params(params: dict) -> dict:
    """The correspondence parameters of a refinement pass (its deformation, no residual)."""
    return dict(params, pair_residual=False, max_iterations=int(params["refine_iterations"]),
                deformation=params["refine_deformation"])


def refine_guarded(run: CorrespondenceRun, passes: int,
                   on_last_pass: Callable | None) -> tuple[list[float], bool]:
    """:func:`refine`, each pass judged by the safeguard when it is on
    (:class:`core.correspondence.safeguard.RefinementGuard`, its record into ``run.record``).
    Returns the changes and whether the shapes must stream again: the first pass's results
    stream as they arrive (an interrupted run keeps them); with the safeguard, when another
    deformation is kept, the pass is rolled back or another pass follows, the kept results
    replace them (``on_shape`` is called again for those shapes)."""
    if not run.record["enabled"]:
        return refine(run, pass_params(run.params), passes, on_last_pass=on_last_pass), False
    from core.correspondence.safeguard import RefinementGuard, raw_mesh

    handles = run.handles
    guard = RefinementGuard(lambda k: raw_mesh(handles[k]))

    calls: list[str] = []

    def run_pass(p: dict) -> list[float]:
        # every guarded pass runs both deformations: each run gets its own share of the
        # progress bar, so that it never goes back
        share = 0.35 / (2 * max(int(passes), 1))
        start = min(0.6 + share * len(calls), 0.95 - share)
        calls.append(p["refine_deformation"])
        return refine(run, pass_params(p), 1, on_last_pass=on_last_pass if len(calls) == 1 else None,
                      progress_span=(start, start + share))
    changes = guard.refine(run.corresponded, run.faces, run.params, passes, run_pass)
    run.record["stages"] += [guard.record] if passes > 0 else []
    done = guard.record["passes"]
    # streamed already: the first run's results, when that deformation was kept by the
    # only pass (restored after the other one was tried, the same vertices)
    kept_first = len(done) == 1 and done[0]["kept"] == calls[0]
    return changes, bool(calls) and not kept_first
