"""Block coordinate descent for LSF's structured low-rank factorisation (Eq. 5).

    min_{Phi, A}  1/2 ||X - Phi A||_F^2 + lam * sum_m ||Phi_m||_Phi * ||A_m,:||_2

(Haeffele, Young & Vidal, ICML 2014; prox-linear block coordinate descent with extrapolation
and restarts: Xu & Yin, SIAM J. Imaging Sci. 2013.) Alternate a proximal-gradient step on A
(row-wise l2 shrinkage with threshold lam ||Phi_m||_Phi / L_A,m) and on Phi (prox of the factor
norm with threshold lam ||A_m|| / L_Phi,m), with Nesterov-type extrapolation and a restart
without extrapolation whenever the objective increases. The step sizes come from a diagonal
majoriser of the quadratic part (L_m = absolute row sums of Phi^T Phi, resp. A A^T, which
dominate the Hessian by Gershgorin) rather than one global Lipschitz constant: the block is
still a valid prox-linear step, and small factors are not slowed down by the largest one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.models.lsf.prox import FactorNorm, row_shrink
from core.runtime.progress import ProgressCallback, report


@dataclass
class FactorisationResult:
    """P (N, 3, M) factors; A (M, K) coefficients; objective per iteration; n_iter; converged."""

    P: np.ndarray
    A: np.ndarray
    objective: list[float] = field(default_factory=list)
    n_iter: int = 0
    converged: bool = False


def _diag_majoriser(G: np.ndarray) -> np.ndarray:
    """Diagonal D with D - G positive semi-definite (absolute row sums of symmetric G), (M,)."""
    d = np.abs(G).sum(axis=1)
    return np.where(d > 1e-12 * max(float(d.max(initial=0.0)), 1e-300), d, 1.0)


def initial_factors(Xf: np.ndarray, n: int, m: int, rng: np.random.Generator) -> np.ndarray:
    """M coordinate vectors (Haeffele's initialisation), (N, 3, M).

    Coordinates are drawn with probability proportional to their data energy: a uniform draw
    wastes factors on coordinates that barely vary, whose coefficients are shrunk to zero at once.
    """
    P = np.zeros((n, 3, m))
    energy = np.einsum("ik,ik->i", Xf, Xf)
    prob = energy / energy.sum() if energy.sum() > 0 else None
    replace = bool(m > np.count_nonzero(energy)) if prob is not None else m > 3 * n
    coords = rng.choice(3 * n, size=m, replace=replace, p=prob)
    P.reshape(3 * n, m)[coords, np.arange(m)] = 1.0
    return P


class _BCD:
    """State of the block coordinate descent: iterates, extrapolation points, step sizes."""

    def __init__(self, X: np.ndarray, P: np.ndarray, norm: FactorNorm, lam: float):
        n, _, k = X.shape
        self.n, self.m = n, P.shape[2]
        self.Xf = X.reshape(3 * n, k)
        self.norm, self.lam = norm, lam
        self.P = self.P_old = self.Pe = P
        self.A = self.A_old = self.Ae = np.zeros((self.m, k))
        self.r = self.r_old = norm.values(P)
        self.LA_old = self.LP_old = np.ones(self.m)
        self.t_old = 1.0

    def objective(self, P: np.ndarray, A: np.ndarray, r: np.ndarray) -> float:
        R = self.Xf - P.reshape(-1, self.m) @ A
        return 0.5 * float(np.sum(R * R)) + self.lam * float(np.sum(r * np.linalg.norm(A, axis=1)))

    def step(self) -> None:
        """One prox-linear step on A, then on Phi (from the extrapolated points)."""
        Pf = self.P.reshape(-1, self.m)
        G = Pf.T @ Pf
        self.LA = _diag_majoriser(G)
        gradA = G @ self.Ae - Pf.T @ self.Xf
        A = row_shrink(self.Ae - gradA / self.LA[:, None], self.lam * self.r / self.LA)
        A[self.r <= 0] = 0.0
        H = A @ A.T
        self.LP = _diag_majoriser(H)
        gradP = (self.Pe.reshape(-1, self.m) @ H - self.Xf @ A.T).reshape(self.n, 3, self.m)
        a_norm = np.linalg.norm(A, axis=1)
        P = self.norm.prox(self.Pe - gradP / self.LP, self.lam * a_norm / self.LP)
        P[:, :, a_norm <= 0] = 0.0
        self.P, self.A, self.r = P, A, self.norm.values(P)

    def restart(self) -> None:
        """Back to the last accepted iterate, without extrapolation."""
        self.P, self.A, self.r = self.P_old, self.A_old, self.r_old
        self.Pe, self.Ae = self.P_old, self.A_old

    def accept(self) -> None:
        """Keep the new iterate and extrapolate from it (weights capped by the step ratio)."""
        tk = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * self.t_old * self.t_old))
        w = (self.t_old - 1.0) / tk
        self.Ae = self.A + np.minimum(w, np.sqrt(self.LA_old / self.LA))[:, None] * \
            (self.A - self.A_old)
        self.Pe = self.P + np.minimum(w, np.sqrt(self.LP_old / self.LP)) * (self.P - self.P_old)
        self.P_old, self.A_old, self.r_old = self.P, self.A, self.r
        self.t_old, self.LA_old, self.LP_old = tk, self.LA, self.LP


def structured_factorisation(X: np.ndarray, n_factors: int, norm: FactorNorm, lam: float, *,
                             max_iter: int, tol: float, rng: np.random.Generator,
                             progress: ProgressCallback | None = None) -> FactorisationResult:
    """Solve Eq. 5 by block coordinate descent.

    Parameters
    ----------
    X : (N, 3, K) centred, scaled data; n_factors : M (maximum rank); norm : the factor norm;
    lam : overall weight; max_iter; tol : stop when the relative objective decrease stays below
    tol for 3 accepted iterations; rng : initialisation draw; progress : per-iteration report
    """
    n = X.shape[0]
    state = _BCD(X, initial_factors(X.reshape(3 * n, -1), n, int(n_factors), rng), norm, lam)
    obj_old = state.objective(state.P, state.A, state.r)
    result = FactorisationResult(state.P, state.A, [obj_old])
    restarted, stall = False, 0
    for it in range(1, max_iter + 1):
        state.step()
        obj = state.objective(state.P, state.A, state.r)
        if obj >= obj_old and not restarted:
            state.restart()  # no decrease: retry from the last iterate without extrapolation
            restarted = True
            result.objective.append(obj_old)
        else:
            restarted = False
            state.accept()
            result.objective.append(obj)
            change = abs(obj_old - obj) / max(abs(obj_old), 1e-300)
            obj_old = obj
            stall = stall + 1 if change < tol else 0
        result.n_iter, result.converged = it, stall >= 3
        n_active = int(np.count_nonzero(np.linalg.norm(state.A_old, axis=1) > 0))
        report(progress, it / max_iter,
               f"LSF iteration {it}/{max_iter}, {n_active} factors, objective {obj_old:.4g}")
        if result.converged:
            break
    result.P, result.A = state.P_old, state.A_old
    return result
