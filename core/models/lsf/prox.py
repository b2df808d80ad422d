"""Proximal operators of LSF's factor norm (Bernard et al., CVPR 2016, Eq. 6).

    ||z||_Phi = c1 ||z||_1 + c2 ||z||_2 + cg sum_i ||z_(i)||_g + cG ||E z||_2

with z_(i) the x/y/z triple of vertex i and ||.||_g the group norm: l-infinity (the authors'
method and reference code, parameter ``lambdainf``) or l2. Without the graph term the prox is
exact in closed form: the groups are nested (singletons inside vertex triples inside the whole
vector), so it is the composition soft-threshold -> vertex-group prox -> whole-vector shrinkage
(Jenatton, Mairal, Obozinski & Bach, "Proximal Methods for Hierarchical Sparse Coding", JMLR
2011, for l2 and l-infinity group norms). The prox of t ||.||_inf is the residual of the
projection onto the l1 ball of radius t (Moreau decomposition), computed for all triples at
once by the sort-based projection of Duchi, Shalev-Shwartz, Singer & Chandra (ICML 2008).

The graph term couples vertices; :class:`FactorNorm` computes the full prox by an accelerated
projected-gradient iteration on its dual (warm-started between calls): with h the closed-form
part scaled by the threshold t,

    x(v) = prox_h(y - E^T v),   v <- Proj_{||v||_2 <= t cG}(v + E x(v) / ||E||_2^2).

Everything works on (N, 3, M) arrays: one column (factor) per last index, thresholds (M,).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from core.models.lsf.graph import spectral_norm_sq

GROUP_NORMS = ("linf", "l2")


def project_l1_ball(V: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Euclidean projection of each vertex triple V[i, :, m] onto {||u||_1 <= radius[m]}.

    V : (N, 3, M); radius : (M,) >= 0. Sort-based (Duchi et al. 2008), vectorised.
    """
    a = np.abs(V)
    u = -np.sort(-a, axis=1)  # descending per triple
    css = np.cumsum(u, axis=1)
    j = np.arange(1, V.shape[1] + 1)[None, :, None]
    rho = np.maximum(np.count_nonzero(u - (css - radius) / j > 0, axis=1), 1)[:, None, :]
    theta = (np.take_along_axis(css, rho - 1, axis=1) - radius) / rho
    inside = a.sum(axis=1, keepdims=True) <= radius
    return np.where(inside, V, np.sign(V) * np.maximum(a - theta, 0.0))


def prox_group(Z: np.ndarray, t: np.ndarray, group_norm: str = "linf") -> np.ndarray:
    """Prox of sum_i t_m ||Z[i, :, m]||_g (g = "linf" or "l2") for each column m; Z (N, 3, M)."""
    if group_norm == "linf":
        return Z - project_l1_ball(Z, t)
    gn = np.sqrt(np.einsum("ncm,ncm->nm", Z, Z))[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Z * np.where(gn > 0, np.maximum(1.0 - t / gn, 0.0), 0.0)


def prox_sparse_group(Y: np.ndarray, t1: np.ndarray, tg: np.ndarray, t2: np.ndarray,
                      group_norm: str = "linf") -> np.ndarray:
    """Exact prox of t1||z||_1 + tg sum_i ||z_(i)||_g + t2||z||_2 for each column z of Y.

    Y : (N, 3, M); t1, tg, t2 : (M,) thresholds; group_norm "linf" or "l2".
    Composition soft-threshold -> group prox -> l2 shrinkage (nested groups; exact).
    """
    Z = np.sign(Y) * np.maximum(np.abs(Y) - t1, 0.0)
    Z = prox_group(Z, tg, group_norm)
    cn = np.sqrt(np.einsum("ncm,ncm->m", Z, Z))
    with np.errstate(divide="ignore", invalid="ignore"):
        Z *= np.where(cn > 0, np.maximum(1.0 - t2 / cn, 0.0), 0.0)
    return Z


def group_norm_values(P: np.ndarray, group_norm: str = "linf") -> np.ndarray:
    """sum_i ||P[i, :, m]||_g for each column, (M,)."""
    if group_norm == "linf":
        return np.abs(P).max(axis=1).sum(axis=0)
    return np.sqrt(np.einsum("ncm,ncm->nm", P, P)).sum(axis=0)


def _project_l2_columns(V: np.ndarray, radius: np.ndarray, out: np.ndarray | None = None
                        ) -> np.ndarray:
    """Project each column V[:, :, m] onto the l2 ball of radius radius[m]."""
    norms = np.sqrt(np.einsum("ecm,ecm->m", V, V))
    scale = np.ones_like(norms)
    big = norms > radius
    scale[big] = radius[big] / norms[big]
    if out is None:
        return V * scale
    out *= scale
    return out


class FactorNorm:
    """||z||_Phi (Eq. 6) and its proximal operator for (N, 3, M) factor arrays.

    Parameters
    ----------
    E : (|E|, N) graph gradient; c1, c2, cg, cG : weights of the l1, l2, group and graph terms
    n_inner : dual iterations per prox call (warm-started, so a few suffice in the solver)
    group_norm : "linf" (paper) or "l2"
    """

    def __init__(self, E: sp.csr_matrix, c1: float, c2: float, cg: float, cG: float,
                 n_inner: int, group_norm: str = "linf"):
        if group_norm not in GROUP_NORMS:
            raise ValueError(f"group_norm must be one of {', '.join(GROUP_NORMS)}; "
                             f"got {group_norm!r}")
        self.E = E
        self.ET = E.T.tocsr()
        self.c1, self.c2, self.cg, self.cG = c1, c2, cg, cG
        self.n_inner = n_inner
        self.group_norm = group_norm
        self.step = 1.0 / max(spectral_norm_sq(E), 1e-12)
        self.dual: np.ndarray | None = None  # warm start, (|E|, 3, M)

    def grad(self, P: np.ndarray) -> np.ndarray:
        """E applied to every coordinate of every column: (|E|, 3, M)."""
        n, _, m = P.shape
        return (self.E @ P.reshape(n, 3 * m)).reshape(-1, 3, m)

    def values(self, P: np.ndarray) -> np.ndarray:
        """||P_m||_Phi for each column, (M,)."""
        val = (self.c1 * np.abs(P).sum(axis=(0, 1))
               + self.c2 * np.sqrt(np.einsum("ncm,ncm->m", P, P))
               + self.cg * group_norm_values(P, self.group_norm))
        if self.cG > 0 and self.E.shape[0] > 0:
            EP = self.grad(P)
            val = val + self.cG * np.sqrt(np.einsum("ecm,ecm->m", EP, EP))
        return val

    def _prox_h(self, Y: np.ndarray, t: np.ndarray) -> np.ndarray:
        return prox_sparse_group(Y, t * self.c1, t * self.cg, t * self.c2, self.group_norm)

    def prox(self, Y: np.ndarray, t: np.ndarray) -> np.ndarray:
        """argmin_X 1/2||X - Y||^2 + sum_m t_m ||X_m||_Phi, column by column (Y (N, 3, M))."""
        n, _, m = Y.shape
        if self.cG <= 0 or self.E.shape[0] == 0:
            return self._prox_h(Y, t)
        radius = t * self.cG
        n_e = self.E.shape[0]
        if self.dual is None or self.dual.shape[2] != m:
            self.dual = np.zeros((n_e, 3, m))
        V = _project_l2_columns(self.dual, radius)
        W, tk = V, 1.0
        for _ in range(self.n_inner):  # accelerated projected gradient ascent on the dual
            X = self._prox_h(Y - (self.ET @ W.reshape(n_e, 3 * m)).reshape(n, 3, m), t)
            V_new = (self.E @ X.reshape(n, 3 * m)).reshape(n_e, 3, m)
            V_new *= self.step
            V_new += W
            V_new = _project_l2_columns(V_new, radius, out=V_new)
            tk_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * tk * tk))
            beta = (tk - 1.0) / tk_new
            W = V_new * (1.0 + beta) - beta * V if beta > 0 else V_new
            V, tk = V_new, tk_new
        self.dual = V
        return self._prox_h(Y - (self.ET @ V.reshape(n_e, 3 * m)).reshape(n, 3, m), t)


def row_shrink(Y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Prox of sum_m t_m ||Y_m,:||_2 (rows of Y (M, K)): the coefficient norm ||A_m||_2."""
    norms = np.linalg.norm(Y, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(norms > 0, np.maximum(1.0 - t / norms, 0.0), 0.0)
    return Y * scale[:, None]
