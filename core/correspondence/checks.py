"""The checks after a run's reference-based pass: mirrored sides, switched poses, outliers.

Bernard et al., SPIE MI 2016 assume every input is the same structure on the same side, in
a pose the rigid CPD (Myronenko & Song, TPAMI 2010) finds. The batch
(:mod:`core.correspondence.batch`) checks that on the whole training set before refining:
shapes whose mirror image fits the others better (:func:`flag_mirrored`), shapes whose rigid
pose switched to a principal-axes start, corresponded again to a closer shape
(:func:`recheck_switched`), and shapes far from every other one after similarity alignment
(:func:`flag_outliers`; Procrustes distances with a robust z-score, as in Goodall, JRSS B
1991), which are first corresponded again to the mean of the others
(:func:`retry_from_mean`: a wrong pose looks like a wrong shape). Flagged shapes are
reported and left out.
"""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import TYPE_CHECKING, Any

import numpy as np

from core.correspondence.pair import mirror_fit_ratio, principal_axes
from core.correspondence.store import open_mesh
from core.correspondence.tasks import add_timings, gpa, make_tasks, run_tasks, spread_pick
from core.types import TriMesh

if TYPE_CHECKING:
    from core.correspondence.batch import CorrespondenceRun

MIRROR_SUSPECT = 0.95  # pair.mirror_fit_ratio against the reference below this: check again
MIRROR_RATIO = 0.8     # ... against the others' mean below this: mirrored
HANDEDNESS_SHAPES = 8  # inputs the population's handedness is measured on
NEIGHBOUR_TRIES = 3  # closest shapes a switched shape is corresponded to again, one by one
NEIGHBOUR_POOL = 64  # unswitched shapes the closest are chosen from
OUTLIER_FACTOR = 3.0  # an outlier's Procrustes distance to the mean: over this many times the median


def drop_flagged(run: CorrespondenceRun, results: dict, first: dict) -> None:
    """The mirror and outlier checks: flagged shapes leave ``run.corresponded``, their reason
    goes to ``run.failures``. ``first``: the parameters of the pass checked (for a retry)."""
    corresponded = run.corresponded
    for k, reason in flag_mirrored(run, results).items():
        run.failures[run.names[k]] = reason
        corresponded.pop(k, None)
    flagged = flag_outliers(corresponded, run.names, run.chosen)
    if flagged:  # a wrong pose looks like a wrong shape: once more from the others' mean
        retry_from_mean(run, list(flagged), first)
        flagged = {k: r for k, r in flag_outliers(corresponded, run.names, run.chosen).items()
                   if k in flagged}
    if flagged and not run.params["mirror_check"]:  # (run.params holds every default)
        flagged = {k: r for k, r in flagged.items() if not chirality_explains(run, k)}
    for k, reason in flagged.items():
        run.failures[run.names[k]] = reason
        del corresponded[k]


def chirality_explains(run: CorrespondenceRun, k: int) -> bool:
    """With the mirror check off (a chiral feature takes either sign in this population), is
    shape ``k``'s distance from the others that of a mirrored side rather than of a different
    structure? Yes when its mirror image fits the others' mean better than any rotation of it
    (:func:`core.correspondence.pair.mirror_fit_ratio` below :data:`MIRROR_RATIO`).

    Why: a mirrored twisted bean among five correctly sided ones lies 2.9-3.2 times the
    median Procrustes distance from the mean (the better the correspondence, the smaller
    the median), at :data:`OUTLIER_FACTOR`; it was left out as "a different structure"
    although the user had said that both sides belong.
    """
    others = [j for j in sorted(run.corresponded) if j != k]
    if len(others) < 2:
        return False
    mean, _ = gpa(run.corresponded, others, tol=1e-5)
    return mirror_fit_ratio(mean, open_mesh(run.prepared[k]).vertices, run.params) < MIRROR_RATIO


def flag_mirrored(run: CorrespondenceRun, results: dict) -> dict[int, str]:
    """Inputs whose mirror image fits better than any rotation of them (a left/right mix-up).

    The pairwise step measured :func:`core.correspondence.pair.mirror_fit_ratio` against the
    reference; a reference's own bumps make that noisy on a nearly achiral shape (0.87 for a
    correctly sided bean), so suspects are checked again against the mean of the others
    (measured: 0.92 and up for correctly sided beans, 1.4 and up for the chiral twisted
    beans, 0.73 and below for mirrored twisted beans). When most inputs are suspects, the
    reference is the odd one and nothing is flagged.

    A mix-up is only told apart where the structure has one handedness: a suspect is flagged
    only when the other inputs fit their own mean (without them) better than their mirror
    images do, by the same factor the other way (:func:`population_handedness` at least
    1 / :data:`MIRROR_RATIO`). In a population whose chiral feature takes either sign (the
    tuning family of global modes, twist of random sign: ratios 0.87-1.12; a 50 mm tube with
    an S-bend of random sign) a shape of the minority sign is a member, not a mix-up;
    correctly sided twisted beans around a mirrored one measure 1.18-1.84.
    """
    vertices = run.corresponded
    ratios = {i: results[i][0].get("mirror_ratio") for i in run.usable
              if i in results and results[i][0] is not None}
    suspects = [i for i, r in ratios.items() if r is not None and r < MIRROR_SUSPECT]
    others = [k for k in sorted(vertices) if k not in suspects]
    if not suspects or 2 * len(suspects) >= len(ratios) or len(others) < 2:
        return {}
    mean, _ = gpa(vertices, others, tol=1e-5)
    found = {i: mirror_fit_ratio(mean, open_mesh(run.prepared[i]).vertices, run.params)
             for i in suspects}
    mirrored = {i: r for i, r in found.items() if r < MIRROR_RATIO}
    hand = population_handedness(run, others) if mirrored else None
    flagged = mirrored if hand is not None and hand >= 1.0 / MIRROR_RATIO else {}
    run.mirror_report = {
        "suspects": {run.names[i]: round(float(r), 4) for i, r in found.items()},
        "handedness": None if hand is None or not np.isfinite(hand) else round(hand, 4),
        "flagged": [run.names[i] for i in flagged],
        "note": ("" if hand is None or flagged else
                 f"kept: their mirror images fit the others better, but the others share no "
                 f"handedness (median mirror ratio {hand:.2f} < {1.0 / MIRROR_RATIO:.2f}): a "
                 "chiral feature of either sign, not a left/right mix-up")}
    return {i: (f"mirrored: its mirror image fits the other shapes better than any "
                f"rotation of it (rigid fit sigma^2 ratio {r:.2f}); a left/right "
                "mix-up? (if a chiral feature takes either sign in this population, "
                "turn the mirror check off)") for i, r in flagged.items()}


def population_handedness(run: CorrespondenceRun, keys: list[int]) -> float:
    """How consistently chiral the inputs ``keys`` are: the median, over at most
    :data:`HANDEDNESS_SHAPES` of them, of :func:`core.correspondence.pair.mirror_fit_ratio`
    of each against the similarity mean of the others (itself left out). Near 1: no common
    handedness (achiral, or a chiral feature of either sign); above 1: one hand."""
    if len(keys) < 3:  # no mean without the shape itself: assume one hand (the check stays on)
        return np.inf
    values = []
    for j in spread_pick(keys, HANDEDNESS_SHAPES):
        mean, _ = gpa(run.corresponded, [k for k in keys if k != j], tol=1e-5)
        values.append(mirror_fit_ratio(mean, open_mesh(run.prepared[j]).vertices, run.params))
    return float(np.median(values))


def recheck_switched(run: CorrespondenceRun, results: dict, params: dict) -> dict:
    """Shapes whose rigid pose switched to a principal-axes start, checked against a closer
    shape.

    The pairwise step keeps the input's orientation unless a principal-axes start fits the
    reference far better (:func:`core.correspondence.pair.rigid_fit`). Against a reference
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
    corresponded = run.corresponded
    switched = [k for k, (res, err) in results.items()
                if err is None and res is not None and res.get("pose_switched") and k in corresponded]
    others = [k for k in sorted(corresponded) if k not in switched]
    if not switched or len(others) <= len(switched):
        return {}
    # The closest shapes are looked for among at most NEIGHBOUR_POOL of the others (a
    # cohort's meshes may be files: each is read once for its long axis).
    pool = others[::max(1, len(others) // NEIGHBOUR_POOL)]
    axis = {k: principal_axes(np.asarray(open_mesh(run.prepared[k]).vertices))[:, 0]
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
                tasks += make_tasks(TriMesh(np.asarray(corresponded[j], float), run.faces, "neighbour"),
                                    j, {k: run.prepared[k]}, params)
        if not tasks:
            break
        for (j, k), (out, _) in run_tasks(tasks, run.n_jobs, None, 0.6, 0.6).items():
            if out is None:
                continue
            add_timings(run.timings, k, out)
            if not out["pose_switched"]:
                corresponded[k] = out["vertices"]
                pending.remove(k)
                notes[k] = ("input orientation kept: against one of its closest shapes the "
                            "input orientation fitted (against the reference a principal-axes "
                            "pose had)")
    return notes


def flag_outliers(vertices: MutableMapping, names: list[str], protect: Any) -> dict[int, str]:
    """Shapes far from every other one after similarity alignment (a different structure
    by mistake; mirrored sides: :func:`flag_mirrored`).

    Flagged: a robust z-score over 5 and a distance over :data:`OUTLIER_FACTOR` times the
    median. Measured on 6-shape sets of :mod:`core.datasets.shapes`: shapes of the
    right structure reach 2.65x the median (bent tubes whose correspondence is
    off by over a millimetre), a ring or a tube among beans 3.9-4.4x. With 2x such a tube
    was dropped from its training set as "a different structure".
    """
    keys = sorted(vertices)
    if len(keys) < 6:  # too few for a robust spread of the distances
        return {}
    mean, rmsd = gpa(vertices, keys, tol=1e-5)
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


def retry_from_mean(run: CorrespondenceRun, keys: list[int], params: dict) -> None:
    """Correspond ``keys`` again, from scratch (rigid starts included), to the mean of the
    other shapes: a reference that is closer to them than the chosen one was."""
    vertices = run.corresponded
    others = [k for k in sorted(vertices) if k not in keys]
    if len(others) < 2:
        return
    mean, _ = gpa(vertices, others, tol=1e-6)
    results = run_tasks(make_tasks(TriMesh(mean, run.faces, "mean"), "retry",
                                   {k: run.prepared[k] for k in keys}, params),
                        run.n_jobs, None, 0.6, 0.6)
    for k in keys:
        out, _ = results[("retry", k)]
        if out is not None:
            vertices[k] = out["vertices"]
            add_timings(run.timings, k, out)
