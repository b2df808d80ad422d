"""Factor splitting (Bernard et al., CVPR 2016, section 2.6; not in the authors' reference code).

A factor whose support (vertices moving more than a fraction of its maximum) has several
connected regions on the mesh graph is split into one factor per significant region, so each
factor keeps one local support region.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


def split_factors(P: np.ndarray, adjacency: sp.csr_matrix, *, threshold: float = 0.01,
                  min_energy: float = 0.01) -> np.ndarray:
    """Split factors whose support has several connected regions.

    Parameters
    ----------
    P : (M, N, 3) factors; adjacency : (N, N) vertex graph of the mesh
    threshold : a vertex is in the support if its displacement magnitude exceeds this
        fraction of the factor's maximum
    min_energy : a region is significant if it carries at least this fraction of the factor's
        squared norm; a factor with two or more significant regions is split into them (the
        rest of its support, small regions and sub-threshold tails, is dropped); a factor
        with one significant region is kept unchanged

    Returns
    -------
    (M', N, 3) factors, M' >= number of non-zero input factors.
    """
    out = []
    for f in P:  # one connected-components call per factor (M of them, not per vertex)
        mag = np.linalg.norm(f, axis=1)
        peak = mag.max(initial=0.0)
        if peak <= 0:
            continue
        support = np.flatnonzero(mag > threshold * peak)
        n_comp, labels = connected_components(adjacency[support][:, support], directed=False)
        energy = np.bincount(labels, weights=mag[support] ** 2, minlength=n_comp)
        significant = np.flatnonzero(energy >= min_energy * float(np.sum(mag ** 2)))
        if len(significant) <= 1:
            out.append(f)
            continue
        for c in significant:
            piece = np.zeros_like(f)
            idx = support[labels == c]
            piece[idx] = f[idx]
            out.append(piece)
    return np.array(out).reshape(-1, *P.shape[1:])
