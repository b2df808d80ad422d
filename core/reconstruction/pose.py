"""The pose part of the fit: similarity transforms, the M-step for the pose, the pose prior.

Bernard et al., Medical Image Analysis 38 (2017): the pose of the model is a similarity
x = s R z + t of the base-frame shape z (Eq. 3). For isotropic components without a pose
prior the weighted Procrustes problem has the closed form of Umeyama (IEEE TPAMI 13(4), 1991:
SVD of the weighted cross-covariance); for anisotropic components (or with the prior) there
is none, and :func:`gauss_newton_step` takes one Gauss-Newton step in (log scale, rotation
vector, translation) linearised at the current pose (the fitter halves it when it does not
decrease the objective). :class:`PosePrior` is the Gaussian prior on the deviation from the
user's placement (Eq. 6 of the paper's optional pose term).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.geometry.toolkit import rodrigues, rotation_vector, skew, umeyama


@dataclass(frozen=True)
class Similarity:
    """x = scale * rot @ z + trans (base frame -> world)."""

    scale: float
    rot: np.ndarray
    trans: np.ndarray

    @classmethod
    def identity(cls) -> "Similarity":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> "Similarity":
        """From a 4x4 similarity (nearest rotation by SVD)."""
        lin = np.asarray(matrix, dtype=np.float64)[:3, :3]
        scale = float(abs(np.linalg.det(lin)) ** (1.0 / 3.0))
        rot = lin / scale
        if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-12 or np.linalg.det(rot) < 0:
            u, _, vt = np.linalg.svd(rot)  # not a similarity: the nearest rotation
            rot = u @ vt
        return cls(scale, rot, np.array(matrix, dtype=np.float64)[:3, 3].copy())

    def matrix(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rot
        out[:3, 3] = self.trans
        return out

    def apply(self, z: np.ndarray) -> np.ndarray:
        return self.scale * z @ self.rot.T + self.trans

    def interpolate(self, other: "Similarity", alpha: float) -> "Similarity":
        """The pose a fraction ``alpha`` of the way to ``other`` (geodesic in rotation)."""
        if alpha == 1.0:
            return other
        rot = rodrigues(alpha * rotation_vector(other.rot @ self.rot.T)) @ self.rot
        scale = self.scale * (other.scale / self.scale) ** alpha
        return Similarity(scale, rot, self.trans + alpha * (other.trans - self.trans))


def procrustes(wj: np.ndarray, ybar: np.ndarray, z: np.ndarray, with_scale: bool,
               fixed_scale: float = 1.0) -> Similarity:
    """Weighted similarity y ~ s R z + t (Eq. 3) from per-vertex sums ``wj`` = sum_i p_ij and
    ``ybar`` = sum_i p_ij y_i; without ``with_scale`` s = ``fixed_scale``.

    The weighted Umeyama fit of z_j onto ybar_j / w_j with weights w_j (the same cross
    covariance as over all pairs (i, j) weighted by p_ij).
    """
    target = np.divide(ybar, wj[:, None], out=np.zeros_like(ybar), where=wj[:, None] > 0)
    if with_scale:
        return Similarity(*umeyama(z, target, wj, scaling=True))
    _, rot, _ = umeyama(z, target, wj, scaling=False)
    w = wj / wj.sum()
    return Similarity(float(fixed_scale), rot, w @ target - float(fixed_scale) * rot @ (w @ z))


@dataclass(frozen=True)
class PosePrior:
    """Gaussian prior on the pose's deviation from the placement (Eq. 6).

    The deviation is (log of the scale ratio, rotation vector of R R0^T, displacement of the
    model's centre in mm); ``precision`` holds the inverse variances of these 7 numbers.
    """

    placement: Similarity
    centre: np.ndarray        # the model's centre in the base frame
    precision: np.ndarray     # (7,)

    @classmethod
    def from_sd(cls, placement: Similarity, centre: np.ndarray, rotation_deg: float,
                translation_mm: float, log_scale: float) -> "PosePrior":
        sd = np.array([log_scale] + [np.deg2rad(rotation_deg)] * 3 + [translation_mm] * 3)
        return cls(placement, np.asarray(centre, dtype=np.float64), 1.0 / sd**2)

    def deviation(self, pose: Similarity) -> np.ndarray:
        p0 = self.placement
        return np.concatenate([[np.log(pose.scale / p0.scale)], rotation_vector(pose.rot @ p0.rot.T),
                               pose.apply(self.centre) - p0.apply(self.centre)])

    def energy(self, pose: Similarity) -> float:
        return 0.5 * float((self.precision * self.deviation(pose) ** 2).sum())

    def normal_equations(self, pose: Similarity, pivot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(J^T P J, -J^T P r) of the prior, linearised in the step parameters of
        :func:`gauss_newton_step` (rotation and scaling about ``pivot``)."""
        q0 = pose.apply(self.centre) - pivot
        jac = np.zeros((7, 7))
        jac[0, 0] = 1.0
        jac[1:4, 1:4] = np.eye(3)
        jac[4:, 0] = q0
        jac[4:, 1:4] = -skew(q0)
        jac[4:, 4:] = np.eye(3)
        weighted = jac.T * self.precision
        return weighted @ jac, -weighted @ self.deviation(pose)


def gauss_newton_step(pose: Similarity, wj: np.ndarray, ybar: np.ndarray, xj: np.ndarray,
                      nv: np.ndarray | None, eta: float, sigma2: float,
                      prior: PosePrior | None, rigid: bool) -> Similarity:
    """One Gauss-Newton step of sum_ij p_ij |y_i - x_j|^2_W / (2 s2) (+ the prior) in the pose.

    ``xj`` (V, 3) are the candidate vertices in world, ``wj``/``ybar`` their per-vertex sums,
    ``nv`` their unit normals (W_j = I + (eta - 1) n_j n_j^T; None: W_j = I). Parameters:
    d(log scale), rotation vector, translation, about the weighted centre of the vertices.
    """
    pivot = (wj[:, None] * xj).sum(axis=0) / wj.sum()
    q = xj - pivot
    n_cand = len(xj)
    jac = np.zeros((n_cand, 3, 7))  # Jacobian of x_j: [q | -[q]_x | I]
    jac[:, :, 0] = q
    jac[:, 0, 2], jac[:, 0, 3] = q[:, 2], -q[:, 1]
    jac[:, 1, 1], jac[:, 1, 3] = -q[:, 2], q[:, 0]
    jac[:, 2, 1], jac[:, 2, 2] = q[:, 1], -q[:, 0]
    jac[:, :, 4:] = np.eye(3)
    wjac = jac
    if nv is not None and eta != 1.0:
        wjac = jac + (eta - 1.0) * nv[:, :, None] * np.einsum("jc,jcq->jq", nv, jac)[:, None, :]
    resid = ybar - wj[:, None] * xj  # sum_i p_ij (y_i - x_j)
    lhs = (jac * wj[:, None, None]).reshape(-1, 7).T @ wjac.reshape(-1, 7)
    rhs = wjac.reshape(-1, 7).T @ resid.reshape(-1)
    if prior is not None:  # weighted by s2: the data term carries 1/s2
        a_p, b_p = prior.normal_equations(pose, pivot)
        lhs, rhs = lhs + sigma2 * a_p, rhs + sigma2 * b_p
    free = slice(1, 7) if rigid else slice(0, 7)
    lhs, rhs = lhs[free, free], rhs[free]
    lhs = lhs + 1e-9 * np.trace(lhs) * np.eye(len(lhs))
    theta = np.linalg.solve(lhs, rhs)
    if rigid:
        theta = np.concatenate([[0.0], theta])
    grow = 1.0 + theta[0]
    rot_d = rodrigues(theta[1:4])
    return Similarity(pose.scale * grow, rot_d @ pose.rot,
                      grow * rot_d @ (pose.trans - pivot) + pivot + theta[4:])
