"""Attitude from bearings (paper Sec. 4.2): Shuster's QUEST, its covariance, and the sensitivity
of its attitude to the position the references are built from."""

from __future__ import annotations

import math

import numpy as np

from pipeline.core.estimation.estimators.base import inverse_if_well_conditioned
from pipeline.core.estimation.measurement import line_of_sight
from pipeline.core.math.rotations import dcm_from_q, positive_scalar

# QUEST falls back to sequential rotations when |scalar part| of its quaternion is below this. At
# least one of the four frames (as is, rotated 180 deg about x, y or z) then has |q4| >= 0.57.
QUEST_MIN_SCALAR = 0.1
_EYE3 = np.eye(3)


def _quest_solve(b: np.ndarray) -> np.ndarray | None:
    """QUEST quaternion (scalar-last, either sign) of the attitude profile matrix
    B = sum a_i b_i r_i^T (sum a_i = 1), or None near the 180-degree singularity.

    lambda_max from Newton-Raphson on Shuster's characteristic equation p(lambda) = det(lambda I -
    K) = 0 from lambda0 = 1, then the adjugate (Gibbs-vector) form q = [x; gamma] / |[x; gamma]|,
    x = (alpha I + beta S + S^2) z, gamma = (lambda + sigma) alpha - det S. [x; gamma] is the last
    column of adj(lambda I - K) = p'(lambda) q q^T, so |[x; gamma]| = |p'(lambda) q4|: when that
    puts |q4| below QUEST_MIN_SCALAR the direction of [x; gamma] is lost to rounding and None is
    returned. In Shuster's convention q is of the body-from-reference attitude matrix A; as a scipy
    (Hamilton) quaternion it is q_ref_from_body.
    """
    s = b + b.T
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = b.tolist()
    sigma = b00 + b11 + b22
    z = np.array([b12 - b21, b20 - b02, b01 - b10])
    sz = s @ z
    (s00, s01, s02), (s10, s11, s12), (s20, s21, s22) = s.tolist()
    kappa = s00 * s11 - s01 * s10 + s00 * s22 - s02 * s20 + s11 * s22 - s12 * s21
    delta = float(np.linalg.det(s))
    a = sigma * sigma - kappa
    bb = sigma * sigma + float(z @ z)
    c = delta + float(z @ sz)
    d = float(sz @ sz)
    c0 = a * bb + c * sigma - d
    lam, fp = 1.0, 0.0
    for _ in range(50):
        lam2 = lam * lam
        f = lam2 * lam2 - (a + bb) * lam2 - c * lam + c0
        fp = 4.0 * lam2 * lam - 2.0 * (a + bb) * lam - c
        if fp == 0.0:
            break
        dlam = f / fp
        lam -= dlam
        if abs(dlam) <= 1e-15:
            break
    alpha = lam * lam - sigma * sigma + kappa
    gamma = (lam + sigma) * alpha - delta
    x = alpha * z + (lam - sigma) * sz + s @ sz
    norm = math.sqrt(float(x @ x) + gamma * gamma)
    if not norm >= QUEST_MIN_SCALAR * abs(fp) or norm == 0.0:
        return None
    x0, x1, x2 = x.tolist()
    return np.array([x0 / norm, x1 / norm, x2 / norm, gamma / norm])


# 180-degree rotations about x, y, z: diagonal of the DCM, and q = e_k * q' undone per axis as
# (index permutation, signs) of q' = (x, y, z, w).
_FLIPS = (np.array([1.0, -1.0, -1.0]), np.array([-1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0]))
_UNDO = ((np.array([3, 2, 1, 0]), np.array([1.0, -1.0, 1.0, -1.0])),
         (np.array([2, 3, 0, 1]), np.array([1.0, 1.0, -1.0, -1.0])),
         (np.array([1, 0, 3, 2]), np.array([-1.0, 1.0, 1.0, -1.0])))


def quest(b_body: np.ndarray, r_ref_mci: np.ndarray, weights: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """Shuster's QUEST (Shuster & Oh 1981): q_mci_from_body minimising Wahba's loss
    sum w_i |b_i - R^T r_i|^2 over unit observations `b_body` (n, 3) and references `r_ref_mci`
    (n, 3), and its covariance [sum w_i (I - b_i b_i^T)]^-1 (body-frame dtheta, rad^2).

    `weights` (n,) are the bearings' inverse variances 1/sigma_i^2 (rad^-2); QUEST normalises
    them (a_i = w_i / sum w, sigma_tot^2 = 1 / sum w). When the scalar part is below
    QUEST_MIN_SCALAR the problem is re-solved with the reference frame rotated 180 degrees about
    x, then y, then z (sequential rotations) and the rotation is undone. The covariance is NaN when
    its information matrix is ill-conditioned (MAX_CONDITION).
    """
    b = np.asarray(b_body, dtype=float)
    r = np.asarray(r_ref_mci, dtype=float)
    w = np.asarray(weights, dtype=float)
    w_sum = w.sum()
    prof = (b * (w / w_sum)[:, None]).T @ r
    q = _quest_solve(prof)
    for flip, (perm, sign) in zip(_FLIPS, _UNDO, strict=True):
        if q is not None:
            break
        q_flipped = _quest_solve(prof * flip[None, :])
        q = None if q_flipped is None else q_flipped[perm] * sign
    info = w_sum * _EYE3 - (b * w[:, None]).T @ b
    cov = inverse_if_well_conditioned(info)
    if q is None or cov is None:
        return np.full(4, np.nan), np.full((3, 3), np.nan)
    return positive_scalar(q), cov


def quest_position_sensitivity(q_mci_from_body: np.ndarray, att_cov_body: np.ndarray,
                               r_mci_m: np.ndarray, c_mci_m: np.ndarray, weights: np.ndarray,
                               los: tuple[np.ndarray, np.ndarray] | None = None
                               ) -> np.ndarray:
    """d dtheta / d r (3, 3) (rad/m) of the Wahba/QUEST attitude when the references are built
    as r_ref_j = (c_j - r) / |c_j - r| from the position r (paper Sec. 4.2).

    First order, with l_j the MCI line of sight: the references move by dl_j = -(I - l_j l_j^T)
    dr / rho_j, and the optimal right perturbation solves sum w_i (I - b_i b_i^T) dtheta =
    sum w_i b_i x R^T dl_i, so d dtheta / d r = -P R^T [sum_j w_j l_j / rho_j]x, with
    P = `att_cov_body` = [sum w (I - b b^T)]^-1 and `weights` w the inverse variances (rad^-2)
    QUEST used. `los`: `line_of_sight(r_mci_m, c_mci_m)` when the caller has it.
    """
    w, rng_m = line_of_sight(r_mci_m, c_mci_m) if los is None else los
    s0, s1, s2 = (w * (np.asarray(weights, dtype=float) / rng_m)[:, None]).sum(axis=0).tolist()
    skew_s = np.array([[0.0, -s2, s1], [s2, 0.0, -s0], [-s1, s0, 0.0]])
    return -att_cov_body @ dcm_from_q(q_mci_from_body).T @ skew_s
