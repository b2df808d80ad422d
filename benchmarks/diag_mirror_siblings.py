"""Diagnostic of the mirror check (issue 27 item 5; RESULTS "The safeguard's hit rate with
today's pose; the mirror check on the tuning half").

For every mirror suspect of :func:`core.correspondence.checks.flag_mirrored`, the rigid mirror
ratio (:func:`core.correspondence.pair.mirror_fit_ratio`) against each other input, to see
whether a "same-handed sibling" separates populations whose chiral feature takes either sign
(the tuning half's global modes) from a true left/right mix-up (twisted beans with one or two
inputs mirrored); and the handedness of the other inputs
(:func:`core.correspondence.checks.population_handedness`), which the check now requires.

    PYTHONPATH=. python benchmarks/diag_mirror_siblings.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.correspondence import checks, establish_correspondence  # noqa: E402
from core.correspondence.pair import mirror_fit_ratio  # noqa: E402
from core.correspondence.store import open_mesh  # noqa: E402
from core.datasets.families import population  # noqa: E402
from core.datasets.shapes import known_homology_shapes  # noqa: E402
from core.types import TriMesh  # noqa: E402

_flag_mirrored = checks.flag_mirrored


def _flag_and_report(run, results):
    """The product's check, then every suspect's ratio against each other input."""
    flagged = _flag_mirrored(run, results)
    ratios = {i: results[i][0].get("mirror_ratio") for i in run.usable
              if i in results and results[i][0] is not None}
    suspects = [i for i, r in ratios.items() if r is not None and r < checks.MIRROR_SUSPECT]
    if suspects:
        others = [k for k in sorted(run.corresponded) if k not in suspects]
        print(f"  handedness of the {len(others)} others: "
              f"{checks.population_handedness(run, others):.2f}", flush=True)
    for i, ratio in sorted(ratios.items()):
        if ratio is None or ratio >= checks.MIRROR_SUSPECT:
            continue
        suspect = open_mesh(run.prepared[i]).vertices
        against = sorted(mirror_fit_ratio(open_mesh(run.prepared[j]).vertices, suspect, run.params)
                         for j in sorted(run.corresponded) if j != i)
        print(f"  suspect {run.names[i]}: ratio against the reference {ratio:.2f}, flagged "
              f"{i in flagged}, against each other input {np.round(against, 2)}", flush=True)
    return flagged


def _mirrored(meshes: list[TriMesh], which: tuple[int, ...]) -> list[TriMesh]:
    out = list(meshes)
    for k in which:  # mirrored in x, faces flipped to stay outward
        m = out[k]
        out[k] = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], f"mirrored{k}")
    return out


def _run(label: str, meshes: list[TriMesh]) -> None:
    print(label, flush=True)
    result = establish_correspondence(meshes, "auto", n_jobs=1, refine=0, safeguard=False)
    print("  left out:", sorted(result.failures), flush=True)


def main() -> None:
    checks.flag_mirrored = _flag_and_report
    for seed in (100, 101, 102):
        _run(f"global {seed}", list(population("global", 6, seed).meshes))
    for seed in (2, 3, 4):
        pop = known_homology_shapes("twist", 6, seed=seed, n_points=(380, 420))
        _run(f"twist {seed}, input 4 mirrored", _mirrored(list(pop.meshes), (4,)))
        _run(f"twist {seed}, inputs 1 and 4 mirrored", _mirrored(list(pop.meshes), (1, 4)))


if __name__ == "__main__":
    main()
