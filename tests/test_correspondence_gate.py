"""Quality gate of the correspondence defaults (issue 27, item 4).

For each of the 8 known-truth families of :mod:`core.datasets.families` (the protocol's tuning
and report halves), a small fixed problem (:func:`~core.datasets.families.gate_problem`: 5
shapes, own tessellations, random poses and vertex order, about 300-1,250 vertices) is
corresponded with the product's DEFAULT ``establish_correspondence(meshes, "auto", n_jobs=1)``;
the spread of homologous output vertices' true material points (mean and 95th percentile, mm)
must stay under the family's thresholds in :data:`THRESHOLDS`. A change of a default that
regresses any family fails ``scripts/test.sh``. Accuracy only, never time.

How the thresholds were set (2026-12-03, re-set after the safeguard of issue 27 item 3
landed): on each gate problem, the measured default times 1.3, rounded up to 0.01 mm; where
the defaults are better than the plain-CPD peer on the same problem (rustcpd rigid + nonrigid
CPD of the defaults' reference onto each raw input, then projection:
``benchmarks/correspondence_common.plain_rustcpd``), not looser than the peer's value times
1.05 (rounded down), so a regression to plain CPD's level fails. The measured numbers are in
the comments. Re-measured 2026-12-06 with 120 fairing iterations (30 before): concave, thin and
two-lobed tightened by the same rule (30 iterations gave concave 0.664, over its new 0.57);
the label-map problems came out worse here (1 mm 0.643 / 0.888, 0.5 mm 0.705 / 0.953 with 30
iterations), where the 9-population protocol runs had them 1.1 % and 1.4 % better; their
thresholds were kept. Re-measured 2026-12-07 with the even subsample of the final rigid
refinement: only the 0.5 mm label-map problem changed (1.6 % worse here, 7 % better over the
protocol's 9 populations); thresholds kept.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.correspondence import establish_correspondence
from core.datasets.families import FAMILIES, REPORT, TUNING, gate_problem
from core.datasets.shapes import homology_spread, material_points

# family: (spread mean, spread p95) thresholds in mm. Comments: measured on the gate problem,
# the product's defaults (mean / p95) and the plain rustcpd peer with the same reference.
THRESHOLDS = {
    "global": (1.21, 2.06),       # default 1.051 / 1.602; plain rustcpd 1.158 / 1.969
    "concave": (0.57, 1.02),      # default 0.498 / 0.780; plain rustcpd 0.547 / 1.052
    "coarse": (1.20, 1.56),       # default 1.031 / 1.344; plain rustcpd 1.148 / 1.495
    "labels_1mm": (0.84, 1.16),   # default 0.741 / 1.038; plain rustcpd 0.887 / 1.229
    "ovoid": (0.69, 1.09),        # default 0.546 / 0.848; plain rustcpd 0.659 / 1.047
    "thin": (0.64, 0.99),         # default 0.486 / 0.759; plain rustcpd 0.686 / 1.074
    "twolobe": (0.38, 0.53),      # default 0.289 / 0.401; plain rustcpd 0.391 / 0.589
    "labels_05mm": (0.85, 1.15),  # default 0.815 / 1.065 (0.802 / 1.057 before the even
                                  # fine rigid subsample); plain rustcpd 0.818 / 1.103
}


def test_every_family_has_a_threshold():
    assert set(THRESHOLDS) == set(FAMILIES) == set(TUNING) | set(REPORT)


@pytest.mark.parametrize("family", FAMILIES)
def test_default_correspondence_accuracy(family):
    problem = gate_problem(family)
    result = establish_correspondence(problem.meshes, reference="auto", n_jobs=1)
    assert not result.failures, result.failures
    spread = problem.spread([m.vertices for m in result.meshes])
    mean, p95 = float(spread.mean()), float(np.percentile(spread, 95))
    limit_mean, limit_p95 = THRESHOLDS[family]
    assert mean <= limit_mean and p95 <= limit_p95, (
        f"{family}: spread {mean:.3f} / {p95:.3f} mm over the gate's {limit_mean} / {limit_p95}")


def test_spread_facts_that_cannot_drift():
    """The measure itself: 0 for a perfect correspondence (each shape's vertices at their own
    material, whatever the tessellation), positive and bounded for a wrong one."""
    problem = gate_problem("coarse")
    mesh, material = problem.meshes[0], problem.material[0]
    exact = material_points(mesh.vertices, mesh, material)
    assert np.abs(exact - material).max() < 1e-9
    assert homology_spread([exact, exact, exact]).max() < 1e-12
    # a reversed vertex order is a random correspondence: of the order of the shape's size
    wrong = homology_spread([exact, exact[::-1]])
    extent = np.ptp(material, axis=0).max()
    assert 0.1 * extent < wrong.mean() < extent
