"""Local-support deformation factors by graph-based structured matrix factorisation (LSF).

Bernard, Gemmar, Hertel, Goncalves & Thunberg, "Linear Shape Deformation Models with Local
Support using Graph-based Structured Matrix Factorisation", CVPR 2016; the optimisation
framework is Haeffele, Young & Vidal, "Structured Low-Rank Matrix Factorization: Optimality,
Algorithm, and Applications to Image Processing", ICML 2014; block coordinate descent with
prox-linear steps and extrapolation is Xu & Yin, SIAM J. Imaging Sci. 2013.

Problem (X: centred data, 3N x K, scaled to unit standard deviation)::

    min_{Phi, A}  1/2 ||X - Phi A||_F^2 + lam * sum_m ||Phi_m||_Phi * ||A_m,:||_A         # Eq. 5

    ||z||_Phi = c1 ||z||_1 + c2 ||z||_2 + cg sum_i ||z_(i)||_2 + cG ||E z||_2              # Eq. 6
    ||a||_A   = ||a||_2

with z_(i) the x/y/z triple of vertex i (group sparsity) and E the weighted graph gradient:
one row per graph edge (i, j) and coordinate, sqrt(w_ij) (z_i - z_j), so that ||E z||^2 is the
graph-Laplacian energy; w_ij = exp(-(d_ij / d_mean)^2) on the mean shape, edges with
w_ij < ``graph_threshold`` dropped. The graph is the mesh's edges (``graph="mesh"``, as the
paper's body-shape experiment) or all vertex pairs with w_ij >= threshold
(``graph="euclidean"``). Both norms are positively homogeneous, as the framework requires (the
graph term is ||E z||, not its square; ||E z||^2 is the Laplacian energy it is built from).

Algorithm: alternate a proximal-gradient step on A (row-wise l2 shrinkage with threshold
lam ||Phi_m||_Phi / L_A,m) and on Phi (threshold lam ||A_m|| / L_Phi,m for column m), with
Nesterov-type extrapolation and a restart without extrapolation whenever the objective
increases (Xu & Yin). The step sizes come from a diagonal majoriser of the quadratic part
(L_m = absolute row sums of Phi^T Phi, resp. A A^T, which dominate the Hessian by
Gershgorin) rather than one global Lipschitz constant ||Phi^T Phi||_2: the block is still a
valid prox-linear step, and the many small factors are not slowed down by the largest one.
The proximal operator of the factor norm has no closed form because of E; it is computed by
an accelerated projected gradient iteration on its dual (warm-started between outer
iterations): with
h = c1||.||_1 + cg sum_i||._(i)|| + c2||.||_2 (scaled by the threshold),

    x(v) = prox_h(y - E^T v),   v <- Proj_{||v||_2 <= t cG}(v + E x(v) / ||E||_2^2),

and prox_h itself is exact in closed form as the composition soft-threshold -> vertex-group
shrinkage -> whole-vector shrinkage (the three group structures are nested: singletons inside
vertex triples inside the whole vector; Jenatton et al., JMLR 2011, prox of tree-structured
norms). All factors are updated at once as one (N, 3, M) array.

Parameters follow the authors' public reference code in their meaning and defaults and in how
they are made independent of the problem size: lam = lambda_ * lambda_coef * 3N * K / (M sqrt K),
c1 = lambda_1 / sqrt(3N), c2 = lambda_2 / sqrt(3N), cg = lambda_group / sqrt(N),
cG = lambda_graph / sqrt(3 |E|). Factors whose product norm ||Phi_m|| ||A_m|| vanishes are
removed (the rank adapts). Factor splitting (paper, section 2.6; not in the reference code): a
factor whose support (vertices with displacement magnitude above ``split_threshold`` times its
maximum) has several connected components on the mesh graph is split into one factor per
component carrying at least ``split_min_energy`` of the factor's energy (smaller pieces and
sub-threshold tails are dropped; a factor with one such component is kept whole). No initialisation of support regions is needed: Phi starts as M random coordinate
vectors (as in Haeffele's code), drawn with probability proportional to each coordinate's
variance over the training set (a uniform draw leaves many factors dead from the first step
on data that vary only in places).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from core import mesh as meshops
from core.models.base import DeformationModel
from core.progress import ProgressCallback, report


# --------------------------------------------------------------------------------------
# Graph operator
# --------------------------------------------------------------------------------------


def graph_gradient(vertices: np.ndarray, faces: np.ndarray, *, graph: str = "mesh",
                   threshold: float = 0.1) -> sp.csr_matrix:
    """Weighted graph gradient E (|E|, N): row e = sqrt(w_ij) (e_i - e_j).

    Parameters
    ----------
    vertices : (N, 3) mean shape; faces : (F, 3)
    graph : "mesh" (edges of the triangulation) or "euclidean" (all pairs within the radius
        where the weight reaches ``threshold``)
    threshold : weights w_ij = exp(-(d_ij / d_mean)^2) below it are dropped; d_mean is the mean
        mesh edge length.
    """
    n = len(vertices)
    mesh_edges = meshops.edges(faces)
    d_mean = float(np.linalg.norm(vertices[mesh_edges[:, 0]] - vertices[mesh_edges[:, 1]],
                                  axis=1).mean())
    d_mean = d_mean if d_mean > 0 else 1.0
    if graph == "mesh":
        pairs = mesh_edges
    elif graph == "euclidean":
        from scipy.spatial import cKDTree

        radius = d_mean * np.sqrt(np.log(1.0 / threshold)) if threshold < 1 else d_mean
        pairs = cKDTree(vertices).query_pairs(radius, output_type="ndarray")
        pairs = np.sort(pairs.reshape(-1, 2), axis=1)
    else:
        raise ValueError(f"graph must be 'mesh' or 'euclidean'; got {graph!r}")
    d = np.linalg.norm(vertices[pairs[:, 0]] - vertices[pairs[:, 1]], axis=1)
    w = np.exp(-(d / d_mean) ** 2)
    keep = w >= threshold
    pairs, w = pairs[keep], w[keep]
    rows = np.repeat(np.arange(len(pairs)), 2)
    cols = pairs.reshape(-1)
    vals = np.stack([np.sqrt(w), -np.sqrt(w)], axis=1).reshape(-1)
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(pairs), n))


def _spectral_norm_sq(E: sp.csr_matrix) -> float:
    """||E||_2^2 = largest eigenvalue of the weighted Laplacian E^T E."""
    if E.shape[0] == 0:
        return 0.0
    lap = (E.T @ E).tocsr()
    bound = 2.0 * float(np.abs(lap).sum(axis=1).max())  # Gershgorin bound
    try:
        from scipy.sparse.linalg import eigsh

        val = float(eigsh(lap, k=1, which="LA", tol=1e-4, return_eigenvectors=False)[0])
        return min(val * 1.01, bound)
    except Exception:  # ARPACK non-convergence: the bound is safe
        return bound


# --------------------------------------------------------------------------------------
# Proximal operators (all vectorised over the M factor columns)
# --------------------------------------------------------------------------------------


def prox_sparse_group(Y: np.ndarray, t1: np.ndarray, tg: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Exact prox of t1||z||_1 + tg sum_i ||z_(i)||_2 + t2||z||_2 for each column z of Y.

    Y : (N, 3, M); t1, tg, t2 : (M,) thresholds. Composition soft-threshold -> group
    shrinkage -> l2 shrinkage (nested groups; exact).
    """
    Z = np.sign(Y) * np.maximum(np.abs(Y) - t1, 0.0)
    gn = np.sqrt(np.einsum("ncm,ncm->nm", Z, Z))[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        Z *= np.where(gn > 0, np.maximum(1.0 - tg / gn, 0.0), 0.0)
    cn = np.sqrt(np.einsum("ncm,ncm->m", Z, Z))
    with np.errstate(divide="ignore", invalid="ignore"):
        Z *= np.where(cn > 0, np.maximum(1.0 - t2 / cn, 0.0), 0.0)
    return Z


class _FactorNorm:
    """||z||_Phi of Eq. 6 and its proximal operator for (N, 3, M) factor arrays."""

    def __init__(self, E: sp.csr_matrix, c1: float, c2: float, cg: float, cG: float,
                 n_inner: int):
        self.E = E
        self.ET = E.T.tocsr()
        self.c1, self.c2, self.cg, self.cG = c1, c2, cg, cG
        self.n_inner = n_inner
        self.step = 1.0 / max(_spectral_norm_sq(E), 1e-12)
        self.dual: np.ndarray | None = None  # warm start, (|E|, 3, M)

    def grad(self, P: np.ndarray) -> np.ndarray:
        n, _, m = P.shape
        return (self.E @ P.reshape(n, 3 * m)).reshape(-1, 3, m)

    def values(self, P: np.ndarray) -> np.ndarray:
        """||P_m||_Phi for each column, (M,)."""
        l1 = np.abs(P).sum(axis=(0, 1))
        l2 = np.sqrt(np.einsum("ncm,ncm->m", P, P))
        grp = np.sqrt(np.einsum("ncm,ncm->nm", P, P)).sum(axis=0)
        val = self.c1 * l1 + self.c2 * l2 + self.cg * grp
        if self.cG > 0 and self.E.shape[0] > 0:
            EP = self.grad(P)
            val = val + self.cG * np.sqrt(np.einsum("ecm,ecm->m", EP, EP))
        return val

    def prox(self, Y: np.ndarray, t: np.ndarray) -> np.ndarray:
        """argmin_X 1/2||X - Y||^2 + sum_m t_m ||X_m||_Phi, column by column (Y (N, 3, M))."""
        n, _, m = Y.shape
        t1, tg, t2 = t * self.c1, t * self.cg, t * self.c2
        if self.cG <= 0 or self.E.shape[0] == 0:
            return prox_sparse_group(Y, t1, tg, t2)
        radius = t * self.cG
        n_e = self.E.shape[0]
        if self.dual is None or self.dual.shape[2] != m:
            self.dual = np.zeros((n_e, 3, m))
        V = self._project(self.dual, radius)
        W = V
        tk = 1.0
        for _ in range(self.n_inner):  # accelerated projected gradient ascent on the dual
            X = prox_sparse_group(Y - (self.ET @ W.reshape(n_e, 3 * m)).reshape(n, 3, m),
                                  t1, tg, t2)
            V_new = (self.E @ X.reshape(n, 3 * m)).reshape(n_e, 3, m)
            V_new *= self.step
            V_new += W
            V_new = self._project(V_new, radius, out=V_new)
            tk_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * tk * tk))
            beta = (tk - 1.0) / tk_new
            if beta > 0:
                W = V_new * (1.0 + beta)
                W -= beta * V
            else:
                W = V_new
            V, tk = V_new, tk_new
        self.dual = V
        return prox_sparse_group(Y - (self.ET @ V.reshape(n_e, 3 * m)).reshape(n, 3, m),
                                 t1, tg, t2)

    @staticmethod
    def _project(V: np.ndarray, radius: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Project each column V[:, :, m] onto the l2 ball of radius radius[m]."""
        norms = np.sqrt(np.einsum("ecm,ecm->m", V, V))
        scale = np.ones_like(norms)
        big = norms > radius
        scale[big] = radius[big] / norms[big]
        if out is None:
            return V * scale
        out *= scale
        return out


def _row_shrink(Y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Prox of sum_m t_m ||Y_m,:||_2 (rows of Y (M, K))."""
    norms = np.linalg.norm(Y, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(norms > 0, np.maximum(1.0 - t / norms, 0.0), 0.0)
    return Y * scale[:, None]


def _diag_majoriser(G: np.ndarray) -> np.ndarray:
    """Diagonal D with D - G positive semi-definite (absolute row sums of symmetric G), (M,)."""
    d = np.abs(G).sum(axis=1)
    return np.where(d > 1e-12 * max(float(d.max(initial=0.0)), 1e-300), d, 1.0)


# --------------------------------------------------------------------------------------
# Block coordinate descent
# --------------------------------------------------------------------------------------


def structured_factorisation(X: np.ndarray, n_factors: int, norm: _FactorNorm, lam: float, *,
                             max_iter: int, tol: float, rng: np.random.Generator,
                             progress: ProgressCallback | None = None):
    """Solve Eq. 5 by block coordinate descent.

    Parameters
    ----------
    X : (N, 3, K) centred, scaled data; n_factors : M (maximum rank)

    Returns
    -------
    P : (N, 3, M) factors; A : (M, K) coefficients; objective : list of values; n_iter;
    converged
    """
    n, _, k = X.shape
    m = int(n_factors)
    Xf = X.reshape(3 * n, k)
    P = np.zeros((n, 3, m))
    # Start from M coordinate vectors (Haeffele's initialisation), drawn with probability
    # proportional to the data energy of each coordinate: a uniform draw wastes factors on
    # coordinates that barely vary, whose coefficients are shrunk to zero at once.
    energy = np.einsum("ik,ik->i", Xf, Xf)
    prob = energy / energy.sum() if energy.sum() > 0 else None
    replace = m > np.count_nonzero(energy) if prob is not None else m > 3 * n
    coords = rng.choice(3 * n, size=m, replace=replace, p=prob)
    P.reshape(3 * n, m)[coords, np.arange(m)] = 1.0
    A = np.zeros((m, k))
    r = norm.values(P)

    def objective(P, A, r):
        R = Xf - P.reshape(3 * n, m) @ A
        return 0.5 * float(np.sum(R * R)) + lam * float(np.sum(r * np.linalg.norm(A, axis=1)))

    obj_old = objective(P, A, r)
    history = [obj_old]
    P_old, A_old, r_old = P, A, r
    Pe, Ae = P, A
    LA_old = np.ones(m)
    LP_old = np.ones(m)
    t_old = 1.0
    restarted = False
    converged = False
    stall = 0
    it = 0
    for it in range(1, max_iter + 1):
        # Coefficient step (Eq. 5 in A; prox of the row-wise l2 norm). The quadratic is
        # majorised with the diagonal D_A >= Phi^T Phi (row sums of |Phi^T Phi|, Gershgorin):
        # one step size per factor instead of 1 / ||Phi^T Phi||_2, which matters because
        # local-support factors are nearly orthogonal but of very different sizes.
        Pf = P.reshape(3 * n, m)
        G = Pf.T @ Pf
        LA = _diag_majoriser(G)
        gradA = G @ Ae - Pf.T @ Xf
        A = _row_shrink(Ae - gradA / LA[:, None], lam * r / LA)
        A[r <= 0] = 0.0
        # Factor step (Eq. 5 in Phi; prox of the factor norm, Eq. 6), same majoriser on A A^T.
        H = A @ A.T
        LP = _diag_majoriser(H)
        gradP = (Pe.reshape(3 * n, m) @ H - Xf @ A.T).reshape(n, 3, m)
        a_norm = np.linalg.norm(A, axis=1)
        P = norm.prox(Pe - gradP / LP, lam * a_norm / LP)
        P[:, :, a_norm <= 0] = 0.0
        r = norm.values(P)
        obj = objective(P, A, r)
        if obj >= obj_old and not restarted:
            # No decrease: restart from the last iterate without extrapolation.
            P, A, r = P_old, A_old, r_old
            Pe, Ae = P_old, A_old
            restarted = True
            history.append(obj_old)
        else:
            restarted = False
            tk = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t_old * t_old))
            w = (t_old - 1.0) / tk
            Ae = A + (np.minimum(w, np.sqrt(LA_old / LA)))[:, None] * (A - A_old)
            Pe = P + np.minimum(w, np.sqrt(LP_old / LP)) * (P - P_old)
            P_old, A_old, r_old = P, A, r
            t_old, LA_old, LP_old = tk, LA, LP
            history.append(obj)
            change = abs(obj_old - obj) / max(abs(obj_old), 1e-300)
            obj_old = obj
            stall = stall + 1 if change < tol else 0
            if stall >= 3:
                converged = True
        n_active = int(np.count_nonzero(np.linalg.norm(A_old, axis=1) > 0))
        report(progress, it / max_iter,
               f"LSF iteration {it}/{max_iter}, {n_active} factors, objective {obj_old:.4g}")
        if converged:
            break
    return P_old, A_old, history, it, converged


def split_factors(P: np.ndarray, adjacency: sp.csr_matrix, *, threshold: float = 0.01,
                  min_energy: float = 0.01) -> np.ndarray:
    """Split factors whose support has several connected regions (paper, section 2.6).

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
    for f in P:
        mag = np.linalg.norm(f, axis=1)
        peak = mag.max(initial=0.0)
        if peak <= 0:
            continue
        support = np.flatnonzero(mag > threshold * peak)
        n_comp, labels = connected_components(adjacency[support][:, support], directed=False)
        total = float(np.sum(mag ** 2))
        energy = np.bincount(labels, weights=mag[support] ** 2, minlength=n_comp)
        significant = np.flatnonzero(energy >= min_energy * total)
        if len(significant) <= 1:
            out.append(f)
            continue
        for c in significant:
            piece = np.zeros_like(f)
            idx = support[labels == c]
            piece[idx] = f[idx]
            out.append(piece)
    return np.array(out).reshape(-1, *P.shape[1:])


class LSF(DeformationModel):
    """Local-support deformation factors (Bernard et al., CVPR 2016).

    Parameters
    ----------
    n_factors : int, default 96
        Maximum number of factors M (rank); unused factors are removed, factor splitting may
        add factors.
    lambda_ : float, default 64
        Overall regularisation weight (the paper's lambda).
    lambda_coef : float, default 1e-4
        Weight of the coefficient norm ||A_m||_2 (multiplies ``lambda_``).
    lambda_1 : float, default 1
        l1 sparsity weight of the factor norm.
    lambda_2 : float, default 1
        l2 weight of the factor norm (drives unused factors to zero).
    lambda_group : float, default 2
        Group-sparsity weight (x/y/z triple of each vertex).
    lambda_graph : float, default 1
        Graph smoothness weight (||E z||_2).
    graph : {"mesh", "euclidean"}, default "mesh"
        Edge set of E (mesh edges, or all pairs within the threshold radius).
    graph_threshold : float, default 0.1
        Edges with weight exp(-(d/d_mean)^2) below this are dropped.
    max_iter : int, default 400
        Outer block-coordinate-descent iterations.
    n_inner : int, default 3
        Dual iterations per proximal operator (warm-started from the previous outer
        iteration's dual, so a few suffice).
    tol : float, default 1e-4
        Stop when the relative objective decrease stays below tol for 3 iterations.
    split : bool, default True
        Factor splitting by connected support regions.
    split_threshold : float, default 0.01
    split_min_energy : float, default 0.05
    random_state : int or None, default 0
        Seed of the random coordinate initialisation.

    Attributes
    ----------
    mean_, factors_, coef_var_ (see DeformationModel); n_iter_, converged_;
    objective_ : list of objective values (scaled data); n_split_ : factors added by splitting.
    """

    method = "lsf"
    needs_faces = True
    _parameter_constraints = {
        "n_factors": ("int", 1, None),
        "lambda_": ("float", 0.0, None),
        "lambda_coef": ("float", 0.0, None),
        "lambda_1": ("float", 0.0, None),
        "lambda_2": ("float", 0.0, None),
        "lambda_group": ("float", 0.0, None),
        "lambda_graph": ("float", 0.0, None),
        "graph": ("options", ("mesh", "euclidean")),
        "graph_threshold": ("float", 1e-12, 1.0),
        "max_iter": ("int", 1, None),
        "n_inner": ("int", 1, None),
        "tol": ("float", 0.0, None),
        "split": ("bool",),
        "split_threshold": ("float", 0.0, 1.0),
        "split_min_energy": ("float", 0.0, 1.0),
        "random_state": ("int", 0, None, True),
    }

    def __init__(self, n_factors: int = 96, *, lambda_: float = 64.0, lambda_coef: float = 1e-4,
                 lambda_1: float = 1.0, lambda_2: float = 1.0, lambda_group: float = 2.0,
                 lambda_graph: float = 1.0, graph: str = "mesh", graph_threshold: float = 0.1,
                 max_iter: int = 400, n_inner: int = 3, tol: float = 1e-4, split: bool = True,
                 split_threshold: float = 0.01, split_min_energy: float = 0.05,
                 random_state: int | None = 0):
        self.n_factors = n_factors
        self.lambda_ = lambda_
        self.lambda_coef = lambda_coef
        self.lambda_1 = lambda_1
        self.lambda_2 = lambda_2
        self.lambda_group = lambda_group
        self.lambda_graph = lambda_graph
        self.graph = graph
        self.graph_threshold = graph_threshold
        self.max_iter = max_iter
        self.n_inner = n_inner
        self.tol = tol
        self.split = split
        self.split_threshold = split_threshold
        self.split_min_energy = split_min_energy
        self.random_state = random_state

    def _fit(self, X, faces, progress: ProgressCallback | None):
        k, n, _ = X.shape
        m = int(self.n_factors)
        mean = X.mean(axis=0)
        centred = X - mean
        scale = float(centred.std())
        if scale <= 0:
            raise ValueError("the training shapes are identical: nothing to factorise")
        data = np.ascontiguousarray((centred / scale).transpose(1, 2, 0))  # (N, 3, K)
        E = graph_gradient(mean, faces, graph=self.graph, threshold=float(self.graph_threshold))
        n_rows = max(3 * E.shape[0], 1)
        norm = _FactorNorm(E, c1=self.lambda_1 / np.sqrt(3 * n), c2=self.lambda_2 / np.sqrt(3 * n),
                           cg=self.lambda_group / np.sqrt(n),
                           cG=self.lambda_graph / np.sqrt(n_rows), n_inner=int(self.n_inner))
        lam = self.lambda_ * self.lambda_coef * 3 * n * k / (m * np.sqrt(k))
        rng = np.random.default_rng(self.random_state)
        P, A, history, self.n_iter_, self.converged_ = structured_factorisation(
            data, m, norm, lam, max_iter=int(self.max_iter), tol=float(self.tol), rng=rng,
            progress=progress)
        self.objective_ = history
        size = np.linalg.norm(P.reshape(3 * n, m), axis=0) * np.linalg.norm(A, axis=1)
        keep = size > 1e-8 * max(float(size.max(initial=0.0)), 1e-300)
        # Scale each factor by its coefficient spread so factors carry the deformation size.
        factors = (P[:, :, keep] * A[keep].std(axis=1, ddof=1)).transpose(2, 0, 1) * scale
        n_before = len(factors)
        if self.split and len(factors):
            adj = meshops.adjacency(faces, n)
            factors = split_factors(factors, adj, threshold=float(self.split_threshold),
                                    min_energy=float(self.split_min_energy))
        self.n_split_ = len(factors) - n_before
        report(progress, 1.0, f"LSF: {len(factors)} factors")
        return mean, factors
