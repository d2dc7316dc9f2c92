"""Pose estimators: the paper's Gauss-Newton position + QUEST attitude (Sec. 4), the joint maximum
likelihood pose, its Fisher information, and a RANSAC + chi-square front end against false matches.

Measurement model (paper Eq. 10-11, ERRATA 6): crater j at `c_mci_m[j]` (MCI, m) is seen along the
unit bearing `u_body[j] = R^T (c_j - r) / |c_j - r|` plus about `sigma_bearing` rad of tangential
noise per axis, at the range `rho_m[j] = |c_j - r|` plus `sigma_range_m` (m) of noise, where
`R = dcm_mci_from_body` and `r = r_mci_m` is the spacecraft position.

Attitude errors are right (body-frame) perturbations: `R_est = R_true @ Exp([dtheta]x)`. Every
covariance here is over the state `[position MCI (m), dtheta body (rad)]`, or a block of it.

Statuses: `ok`; `too_few_craters` (fewer than 3 usable rows: finite c, u and rho, a non-zero
bearing, a positive range; or, in the robust mode, fewer than 3 craters consistent with any pose);
`not_converged` (iteration cap reached); `degenerate` (collinear or duplicated craters, or any
normal matrix whose Jacobi-scaled condition number exceeds `MAX_CONDITION`). A non-ok estimate has
NaN pose and covariances. Nothing raises on bad data; an unknown method or a robust request
without a generator is a contract violation (ValueError).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy.stats import chi2

STATUSES = ("ok", "too_few_craters", "not_converged", "degenerate")
METHODS = ("paper", "joint")

# Largest accepted condition number of a normal matrix after Jacobi (unit-diagonal) scaling. For
# the unit line-of-sight Gram matrix of the range fit, 1e10 means a weakest direction 1e5 times
# worse determined than the best: with 10 m ranges and n craters the position sigma there exceeds
# 1e6/sqrt(n) m, far outside the linearisation, so the fix is called degenerate, not reported.
# Collinear or duplicated craters give 1e15 or more in double precision.
MAX_CONDITION = 1e10
# QUEST falls back to sequential rotations when |scalar part| of its quaternion is below this. At
# least one of the four frames (as is, rotated 180 deg about x, y or z) then has |q4| >= 0.57.
QUEST_MIN_SCALAR = 0.1
# RANSAC's consensus gate is the final chi-square gate widened by this factor in sigma: a 3-crater
# pose predicts the other craters several sigma off, while a false match is kilometres off.
RANSAC_LOOSE_FACTOR = 10.0
RANSAC_BATCH = 8  # hypotheses scored per vectorised batch
MAX_GATE_ITERATIONS = 10  # robust refit-and-gate passes
# Gauss-Newton also stops when its step is below this many times the step that the rounding error
# of the residuals (eps * range for ranges, eps for unit bearings) alone produces through the
# normal equations: in weak geometries (3 craters nearly coplanar with the spacecraft) that floor
# exceeds a 1e-9 m `step_tol_m`, and further steps are only rounding noise.
ROUNDING_FACTOR = 10.0
_EPS = float(np.finfo(float).eps)


@dataclass(frozen=True)
class PoseEstimate:
    """One frame's pose estimate; NaN pose and covariances unless `status == "ok"`."""

    status: str
    r_mci_m: np.ndarray  # (3,) position, MCI (m)
    q_mci_from_body: np.ndarray  # (4,) scalar-last, w >= 0
    cov: np.ndarray  # (6, 6) of [position MCI (m), dtheta body (rad)]
    att_cov_quest: np.ndarray  # (3, 3) QUEST's own dtheta covariance (paper method), rad^2
    iterations: int  # Gauss-Newton iterations of the method itself
    inliers: np.ndarray  # (n,) bool: rows used by the final fit (or the failed attempt)


@dataclass(frozen=True)
class RobustOptions:
    """RANSAC over minimal 3-crater poses, then refit and chi-square gate (3 dof per crater)."""

    gate_probability: float  # chi-square gate on each crater's normalised residual
    max_hypotheses: int  # cap on the RANSAC hypotheses
    confidence: float  # probability of drawing at least one all-inlier sample


# ---------------------------------------------------------------------------------------------
# Rotation helpers (scalar-last Hamilton quaternions, as scipy; written out because a scipy
# Rotation costs ~20 us per call inside the Gauss-Newton loops)

def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x of a (3,) vector: skew(v) @ a == cross(v, a)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def dcm_from_q(q: np.ndarray) -> np.ndarray:
    """DCM (3, 3) of a unit scalar-last quaternion, as scipy: q_a_from_b -> dcm_a_from_b."""
    x, y, z, w = q.tolist()
    return np.array([
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def q_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q of scalar-last quaternions: dcm(p * q) = dcm(p) @ dcm(q)."""
    x1, y1, z1, w1 = p.tolist()
    x2, y2, z2, w2 = q.tolist()
    return np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])


def q_exp(theta_rad: np.ndarray) -> np.ndarray:
    """Unit scalar-last quaternion of the rotation vector theta (rad): dcm = Exp([theta]x)."""
    angle = math.sqrt(float(theta_rad @ theta_rad))
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 - a^2/48 below 1e-4 rad (error < 1e-19)
    k = math.sin(half) / angle if angle > 1e-4 else 0.5 - angle * angle / 48.0
    return np.array([k * theta_rad[0], k * theta_rad[1], k * theta_rad[2], math.cos(half)])


def _positive_scalar(q: np.ndarray) -> np.ndarray:
    return -q if q[3] < 0 else q


def _inverse_if_well_conditioned(h: np.ndarray) -> np.ndarray | None:
    """Inverse of a symmetric positive definite normal matrix, or None when its Jacobi-scaled
    condition number exceeds MAX_CONDITION (or it is singular or not finite)."""
    diag = np.diag(h)
    if not (np.all(np.isfinite(h)) and np.all(diag > 0)):
        return None
    s = 1.0 / np.sqrt(diag)
    outer = s[:, None] * s[None, :]
    ev, vec = np.linalg.eigh(h * outer)
    if not ev[0] > ev[-1] / MAX_CONDITION:
        return None
    return (vec / ev) @ vec.T * outer


def _sym3_inverse(h: np.ndarray) -> np.ndarray | None:
    """Inverse of a symmetric 3x3 matrix by its adjugate; None unless its determinant is > 0."""
    (a, b, c), (_, d, e), (_, _, f) = h.tolist()
    m00, m01, m02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * m00 + b * m01 + c * m02
    if not det > 0.0:
        return None
    m11, m12, m22 = a * f - c * c, b * c - a * e, a * d - b * b
    return np.array([[m00, m01, m02], [m01, m11, m12], [m02, m12, m22]]) / det


def _failed(status: str, inliers: np.ndarray, iterations: int) -> PoseEstimate:
    return PoseEstimate(status, np.full(3, np.nan), np.full(4, np.nan), np.full((6, 6), np.nan),
                        np.full((3, 3), np.nan), iterations, inliers)


# ---------------------------------------------------------------------------------------------
# Position from ranges (paper Sec. 4.1, ERRATA 3)

def closed_form_position(c_mci_m: np.ndarray, rho_m: np.ndarray, u_body: np.ndarray | None = None
                         ) -> np.ndarray | None:
    """Position (3,) (MCI, m) from ranges alone, without any prior; None when impossible.

    With x' = r - mean(c) and d_j = c_j - mean(c), subtracting the mean of |x' - d_j|^2 = rho_j^2
    leaves the linear equations d_j . x' = (|d_j|^2 - mean|d|^2 - rho_j^2 + mean rho^2) / 2 and
    the quadratic |x'|^2 = mean(rho^2) - mean(|d|^2). Craters on a small spherical patch make the
    linear system nearly blind along the patch normal, so only its two in-plane components are
    solved from it (the leading eigenvectors of sum d d^T), and the normal component comes from
    the quadratic (a negative discriminant from noise is clamped to zero). Exact for noiseless
    data. Of the two roots, mirror images across the craters' best-fit plane, take the one farther
    from the Moon's centre (above the surface) or, when the bearings `u_body` (n, 3) are given, the
    one whose crater vectors c_j - r match rho_j u_j by a proper rotation (the best orthogonal
    Procrustes fit): when the craters lie near a great circle, their plane passes near the Moon's
    centre and both roots are equally high. None for fewer than 3 craters, non-finite input, or
    craters on one line (in-plane eigenvalue ratio below 1/MAX_CONDITION).
    """
    c = np.asarray(c_mci_m, dtype=float)
    rho = np.asarray(rho_m, dtype=float)
    if c.shape[0] < 3 or not (np.all(np.isfinite(c)) and np.all(np.isfinite(rho))):
        return None
    c_mean = c.mean(axis=0)
    d = c - c_mean
    d2 = np.einsum("ij,ij->i", d, d)
    rho2 = rho * rho
    y = 0.5 * (d2 - d2.mean() - rho2 + rho2.mean())
    ev, vec = np.linalg.eigh(d.T @ d)
    if not ev[1] > ev[2] / MAX_CONDITION:
        return None
    in_plane = vec[:, 1:] @ ((vec[:, 1:].T @ (d.T @ y)) / ev[1:])
    t = math.sqrt(max(rho2.mean() - d2.mean() - float(in_plane @ in_plane), 0.0))
    roots = c_mean + in_plane + np.outer([t, -t], vec[:, 0])
    if u_body is None:
        score = np.einsum("ij,ij->i", roots, roots)
    else:
        # max over rotations of sum (c_j - r) . R rho_j u_j: s1 + s2 + sign(det A) s3
        a = np.einsum("ja,kjb->kab", np.asarray(u_body, dtype=float) * rho[:, None],
                      c[None] - roots[:, None, :])
        sv = np.linalg.svd(a, compute_uv=False)
        score = sv[:, 0] + sv[:, 1] + np.sign(np.linalg.det(a)) * sv[:, 2]
    return roots[int(np.argmax(score))]


def gauss_newton_position(c_mci_m: np.ndarray, rho_m: np.ndarray, r0_mci_m: np.ndarray,
                          step_tol_m: float, max_iterations: int, *, sigma_range_m: float = 1.0
                          ) -> tuple[np.ndarray, np.ndarray, int, str]:
    """Gauss-Newton on the range residuals f_j = |r - c_j| - rho_j (paper Eq. 12-14, ERRATA 3).

    Returns the position (3,) (MCI, m), its covariance sigma_range^2 (J^T J)^-1 (m^2; the default
    sigma 1 gives (J^T J)^-1), the number of steps and a status: `ok` once a step is at most
    `step_tol_m` (m) or its rounding floor (ROUNDING_FACTOR), `not_converged` at the cap,
    `degenerate` for an ill-conditioned J^T J (MAX_CONDITION). Position and covariance are NaN
    unless ok.
    """
    c = np.asarray(c_mci_m, dtype=float)
    rho = np.asarray(rho_m, dtype=float)
    x = np.array(r0_mci_m, dtype=float)
    nan_x, nan_cov = np.full(3, np.nan), np.full((3, 3), np.nan)
    for k in range(1, max_iterations + 1):
        d = c - x
        rng_m = np.sqrt(np.einsum("ij,ij->i", d, d))
        w = d / rng_m[:, None]  # unit line of sight, MCI; the Jacobian is -w
        h = w.T @ w
        h_inv = _sym3_inverse(h)
        if h_inv is None:
            return nan_x, nan_cov, k, "degenerate"
        step = h_inv @ ((rng_m - rho) @ w)
        x += step
        step_m = math.sqrt(float(step @ step))
        if not math.isfinite(step_m):
            return nan_x, nan_cov, k, "degenerate"
        floor = ROUNDING_FACTOR * _EPS * float(rng_m.max()) * math.sqrt(h_inv.trace())
        if step_m <= max(step_tol_m, floor):
            h_inv = _inverse_if_well_conditioned(h)
            if h_inv is None:
                return nan_x, nan_cov, k, "degenerate"
            return x, sigma_range_m**2 * h_inv, k, "ok"
    return nan_x, nan_cov, max_iterations, "not_converged"


# ---------------------------------------------------------------------------------------------
# Attitude (paper Sec. 4.2): Shuster's QUEST

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
    sigma = float(b[0, 0] + b[1, 1] + b[2, 2])
    z = np.array([b[1, 2] - b[2, 1], b[2, 0] - b[0, 2], b[0, 1] - b[1, 0]])
    sz = s @ z
    kappa = float(s[0, 0] * s[1, 1] - s[0, 1] * s[1, 0] + s[0, 0] * s[2, 2] - s[0, 2] * s[2, 0]
                  + s[1, 1] * s[2, 2] - s[1, 2] * s[2, 1])
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
    return np.concatenate([x, [gamma]]) / norm


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
    prof = (b * (w / w.sum())[:, None]).T @ r
    q = _quest_solve(prof)
    for flip, (perm, sign) in zip(_FLIPS, _UNDO, strict=True):
        if q is not None:
            break
        q_flipped = _quest_solve(prof * flip[None, :])
        q = None if q_flipped is None else q_flipped[perm] * sign
    info = w.sum() * np.eye(3) - (b * w[:, None]).T @ b
    cov = _inverse_if_well_conditioned(info)
    if q is None or cov is None:
        return np.full(4, np.nan), np.full((3, 3), np.nan)
    return _positive_scalar(q), cov


def quest_position_sensitivity(q_mci_from_body: np.ndarray, att_cov_body: np.ndarray,
                               r_mci_m: np.ndarray, c_mci_m: np.ndarray, weights: np.ndarray
                               ) -> np.ndarray:
    """d dtheta / d r (3, 3) (rad/m) of the Wahba/QUEST attitude when the references are built
    as r_ref_j = (c_j - r) / |c_j - r| from the position r (paper Sec. 4.2).

    First order, with l_j the MCI line of sight: the references move by dl_j = -(I - l_j l_j^T)
    dr / rho_j, and the optimal right perturbation solves sum w_i (I - b_i b_i^T) dtheta =
    sum w_i b_i x R^T dl_i, so d dtheta / d r = -P R^T [sum_j w_j l_j / rho_j]x, with
    P = `att_cov_body` = [sum w (I - b b^T)]^-1 and `weights` w the inverse variances (rad^-2)
    QUEST used.
    """
    d = np.asarray(c_mci_m, dtype=float) - r_mci_m
    rng_m = np.sqrt(np.einsum("ij,ij->i", d, d))
    s = (d * (np.asarray(weights, dtype=float) / (rng_m * rng_m))[:, None]).sum(axis=0)
    return -att_cov_body @ dcm_from_q(q_mci_from_body).T @ _skew(s)


# ---------------------------------------------------------------------------------------------
# Joint model: Jacobians, information

def measurement_jacobians(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Predicted ranges (n,) (m) and bearings (n, 3) (body) with their Jacobians wrt the position
    (MCI, m) and the right attitude perturbation dtheta (body, rad):
    d rho / d r = -w^T (n, 3), d u / d r = -R^T (I - w w^T) / rho (n, 3, 3),
    d u / d dtheta = [u]x (n, 3, 3), with w the MCI line of sight."""
    d = np.asarray(c_mci_m, dtype=float) - r_mci_m
    rng_m = np.sqrt(np.einsum("ij,ij->i", d, d))
    w = d / rng_m[:, None]
    dcm = dcm_from_q(q_mci_from_body)
    u = w @ dcm
    proj = np.eye(3) - w[:, :, None] * w[:, None, :]
    du_dr = -np.einsum("ba,nbc->nac", dcm, proj) / rng_m[:, None, None]
    zero = np.zeros_like(rng_m)
    du_dtheta = np.stack([np.stack([zero, -u[:, 2], u[:, 1]], -1),
                          np.stack([u[:, 2], zero, -u[:, 0]], -1),
                          np.stack([-u[:, 1], u[:, 0], zero], -1)], -2)
    return rng_m, u, -w, du_dr, du_dtheta


def fisher_information(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray, *,
                       sigma_bearing: float, sigma_range_m: float) -> np.ndarray:
    """Fisher information (6, 6) of [position MCI (m), dtheta body (rad)] of one frame's ranges
    and bearings at the true pose: sum_j H_j^T W_j H_j with range weight 1/sigma_range^2 and the
    tangent-plane bearing weight (I - u u^T)/sigma_bearing^2 (built from the explicit Jacobians)."""
    _, u, drho_dr, du_dr, du_dtheta = measurement_jacobians(r_mci_m, q_mci_from_body, c_mci_m)
    hb = np.concatenate([du_dr, du_dtheta], axis=2)  # (n, 3, 6)
    hb_tangent = hb - u[:, :, None] * np.einsum("na,nab->nb", u, hb)[:, None, :]
    info = np.zeros((6, 6))
    info[:3, :3] = drho_dr.T @ drho_dr / sigma_range_m**2
    info += np.einsum("nai,naj->ij", hb_tangent, hb_tangent) / sigma_bearing**2
    return info


def crlb(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, c_mci_m: np.ndarray, *,
         sigma_bearing: float, sigma_range_m: float) -> np.ndarray:
    """Cramer-Rao bound (6, 6): the inverse of `fisher_information` (same state and units); NaN
    when the information is singular or ill-conditioned (MAX_CONDITION), e.g. under 3 craters."""
    bound = _inverse_if_well_conditioned(
        fisher_information(r_mci_m, q_mci_from_body, c_mci_m, sigma_bearing=sigma_bearing,
                           sigma_range_m=sigma_range_m))
    return np.full((6, 6), np.nan) if bound is None else bound


# ---------------------------------------------------------------------------------------------
# Estimators

def _prepare(c_mci_m, u_body, rho_m) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Float arrays, bearings renormalised, and the mask of usable rows: finite c, u and rho, a
    non-zero bearing and a positive range."""
    c = np.asarray(c_mci_m, dtype=float).reshape(-1, 3)
    u = np.asarray(u_body, dtype=float).reshape(-1, 3)
    rho = np.asarray(rho_m, dtype=float).reshape(-1)
    norm = np.sqrt(np.einsum("ij,ij->i", u, u))
    valid = np.isfinite(c).all(axis=1) & np.isfinite(norm) & (norm > 0) & np.isfinite(rho) \
        & (rho > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = u / norm[:, None]
    return c, u, rho, valid


def _paper(c, u, rho, use, sigma_bearing, sigma_range_m, r_prior, step_tol_m, max_iterations
           ) -> PoseEstimate:
    """The paper's method on the rows `use`: range Gauss-Newton, then QUEST with r_ref built from
    the estimated position, and the full covariance with the position error propagated."""
    if use.sum() < 3:
        return _failed("too_few_craters", use, 0)
    cs, us, rs = c[use], u[use], rho[use]
    warm = r_prior is not None and bool(np.all(np.isfinite(r_prior)))
    r0 = r_prior if warm else closed_form_position(cs, rs, us)
    if r0 is None:
        return _failed("degenerate", use, 0)
    x, cov_x, its, status = gauss_newton_position(cs, rs, r0, step_tol_m, max_iterations,
                                                  sigma_range_m=sigma_range_m)
    if status != "ok":
        return _failed(status, use, its)
    d = cs - x
    ref = d / np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
    weights = np.full(rs.size, sigma_bearing**-2)
    q, att_cov = quest(us, ref, weights)
    if not np.all(np.isfinite(att_cov)):
        return _failed("degenerate", use, its)
    g = quest_position_sensitivity(q, att_cov, x, cs, weights)
    cov = np.empty((6, 6))
    cov[:3, :3] = cov_x
    cov[3:, :3] = g @ cov_x
    cov[:3, 3:] = cov[3:, :3].T
    cov[3:, 3:] = att_cov + g @ cov_x @ g.T
    return PoseEstimate("ok", x, q, cov, att_cov, its, use)


def _joint_normal_equations(c, u, rho, x, dcm, sigma_bearing, sigma_range_m
                            ) -> tuple[np.ndarray, np.ndarray, float]:
    """Information matrix H (6, 6), gradient J^T W e (6,) of the joint cost at (x, R), and the
    largest predicted range (m). Closed-form sums of the `measurement_jacobians` blocks."""
    d = c - x
    rng_m = np.sqrt(np.einsum("ij,ij->i", d, d))
    inv_rng = 1.0 / rng_m
    w = d * inv_rng[:, None]
    beta = w @ dcm  # predicted bearings, body
    e_rho = rho - rng_m
    e_u = u - beta
    wb, wr = sigma_bearing**-2, sigma_range_m**-2
    w_over = w * inv_rng[:, None]
    ww = w.T @ w
    h = np.empty((6, 6))
    h[:3, :3] = wr * ww + wb * (float(inv_rng @ inv_rng) * np.eye(3) - w_over.T @ w_over)
    h[3:, 3:] = wb * (rng_m.size * np.eye(3) - dcm.T @ ww @ dcm)
    h[:3, 3:] = -wb * _skew(w_over.sum(axis=0)) @ dcm
    h[3:, :3] = h[:3, 3:].T
    v = e_u @ dcm.T  # bearing residuals in MCI
    v_t = v - w * np.einsum("ij,ij->i", w, v)[:, None]
    cross = e_u.T @ beta  # sum e_u beta^T: its antisymmetric part is sum e_u x beta
    g = np.empty(6)
    g[:3] = -wr * (w.T @ e_rho) - wb * (inv_rng @ v_t)
    g[3:] = wb * np.array([cross[1, 2] - cross[2, 1], cross[2, 0] - cross[0, 2],
                           cross[0, 1] - cross[1, 0]])
    return h, g, float(rng_m.max())


def _joint(c, u, rho, use, sigma_bearing, sigma_range_m, initial: PoseEstimate, step_tol_m,
           max_iterations) -> PoseEstimate:
    """Gauss-Newton on (dr, dtheta) of the joint ML cost over the rows `use`, from `initial`."""
    if initial.status != "ok":
        return _failed(initial.status, use, 0)
    cs, us, rs = c[use], u[use], rho[use]
    x = initial.r_mci_m.copy()
    q = initial.q_mci_from_body
    for k in range(1, max_iterations + 1):
        h, g, rho_max = _joint_normal_equations(cs, us, rs, x, dcm_from_q(q), sigma_bearing,
                                                sigma_range_m)
        try:
            h_inv = np.linalg.inv(h)
        except np.linalg.LinAlgError:
            return _failed("degenerate", use, k)
        step = h_inv @ g
        if not np.all(np.isfinite(step)):
            return _failed("degenerate", use, k)
        x += step[:3]
        q = q_multiply(q, q_exp(step[3:]))
        q /= math.sqrt(float(q @ q))
        dx, dth = math.sqrt(float(step[:3] @ step[:3])), math.sqrt(float(step[3:] @ step[3:]))
        # whitened rounding level of the residuals, propagated to each block of the step
        noise = ROUNDING_FACTOR * _EPS * max(rho_max / sigma_range_m, 1.0 / sigma_bearing)
        diag = np.abs(np.diag(h_inv))
        # attitude step "tiny": it moves no predicted crater by more than step_tol_m
        if (dx <= max(step_tol_m, noise * math.sqrt(diag[:3].sum()))
                and dth <= max(step_tol_m / rho_max, noise * math.sqrt(diag[3:].sum()))):
            cov = _inverse_if_well_conditioned(h)
            if cov is None:
                return _failed("degenerate", use, k)
            return PoseEstimate("ok", x, _positive_scalar(q), cov, np.full((3, 3), np.nan), k,
                                use)
    return _failed("not_converged", use, max_iterations)


def estimate_paper(c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                   sigma_bearing: float, sigma_range_m: float,
                   r_prior_mci_m: np.ndarray | None = None, step_tol_m: float = 1e-9,
                   max_iterations: int = 20) -> PoseEstimate:
    """The paper's method (Sec. 4) on craters `c_mci_m` (n, 3) (MCI, m), bearings `u_body` (n, 3)
    and ranges `rho_m` (n,) (m); rows with a non-finite value, a zero bearing or a range <= 0
    are left out (`inliers` False).

    Position: range Gauss-Newton from `r_prior_mci_m` (the previous successful estimate) or, when
    None or not finite (a failed frame's NaN), from `closed_form_position`. Attitude: QUEST with
    r_ref_j = unit(c_j - r_est) and equal weights 1/sigma_bearing^2. `cov`: the Gauss-Newton
    position block; attitude block QUEST's covariance plus G P_rr G^T, with the cross terms
    G P_rr, where G = d dtheta / d r (`quest_position_sensitivity`): the attitude error the
    position error induces through the references (bearing and range noise are independent).
    `att_cov_quest`: QUEST's own covariance.
    """
    c, u, rho, valid = _prepare(c_mci_m, u_body, rho_m)
    return _paper(c, u, rho, valid, sigma_bearing, sigma_range_m, r_prior_mci_m, step_tol_m,
                  max_iterations)


def estimate_joint(c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                   sigma_bearing: float, sigma_range_m: float, initial: PoseEstimate,
                   step_tol_m: float = 1e-9, max_iterations: int = 20) -> PoseEstimate:
    """Joint maximum likelihood pose from ranges and bearings, on the rows `initial.inliers`.

    Minimises sum (rho_j - |r - c_j|)^2 / sigma_range^2 + |u_j - R^T unit(c_j - r)|^2 /
    sigma_bearing^2 by Gauss-Newton on (dr, dtheta), R <- R Exp(dtheta), from `initial` (the
    paper's estimate). Stops when the position step is at most `step_tol_m` (m) and the attitude
    step moves no predicted crater by more than that. `cov` = (H^T W H)^-1 at the solution;
    `att_cov_quest` NaN. A non-ok `initial` gives its status (iterations 0).
    """
    c, u, rho, valid = _prepare(c_mci_m, u_body, rho_m)
    return _joint(c, u, rho, valid & initial.inliers, sigma_bearing, sigma_range_m, initial,
                  step_tol_m, max_iterations)


def _fit(method, c, u, rho, use, sigma_bearing, sigma_range_m, r_prior, step_tol_m,
         max_iterations) -> PoseEstimate:
    paper = _paper(c, u, rho, use, sigma_bearing, sigma_range_m, r_prior, step_tol_m,
                   max_iterations)
    if method == "paper":
        return paper
    return _joint(c, u, rho, use, sigma_bearing, sigma_range_m, paper, step_tol_m,
                  max_iterations)


# ---------------------------------------------------------------------------------------------
# Robust estimation

@cache
def _chi2_gate(probability: float) -> float:
    """Chi-square quantile with 3 dof (1 range + 2 bearing tangent) at `probability`."""
    return float(chi2.ppf(probability, 3))


def _normalised_residuals(c, u, rho, x, dcm, sigma_bearing, sigma_range_m) -> np.ndarray:
    """Per-crater squared normalised residual (range and bearing tangent part) under (x, R)."""
    d = c - x
    rng_m = np.sqrt(np.einsum("ij,ij->i", d, d))
    beta = (d / rng_m[:, None]) @ dcm
    e_u = u - beta
    e_t = e_u - beta * np.einsum("ij,ij->i", e_u, beta)[:, None]
    return ((rho - rng_m) / sigma_range_m) ** 2 + np.einsum("ij,ij->i", e_t, e_t) / sigma_bearing**2


def _sample_triples(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """(k, 3) uniformly drawn triples of distinct indices in [0, n), n >= 3."""
    i = rng.integers(0, n, k)
    j = rng.integers(0, n - 1, k)
    j += j >= i
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    m = rng.integers(0, n - 2, k)
    m += m >= lo
    m += m >= hi
    return np.stack([i, j, m], axis=1)


def absolute_orientation(p_body_m: np.ndarray, c_mci_m: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Batched least-squares c_j = R p_j + r (Kabsch): (..., m, 3) body-frame relative vectors
    p_j = rho_j u_j and MCI points -> dcm_mci_from_body (..., 3, 3) and r_mci_m (..., 3)."""
    p_mean = p_body_m.mean(axis=-2)
    c_mean = c_mci_m.mean(axis=-2)
    a = np.einsum("...ja,...jb->...ab", p_body_m - p_mean[..., None, :],
                  c_mci_m - c_mean[..., None, :])
    uu, _, vt = np.linalg.svd(a)
    v = np.swapaxes(vt, -1, -2)
    v[..., :, 2] *= np.sign(np.linalg.det(v @ np.swapaxes(uu, -1, -2)))[..., None]
    dcm = v @ np.swapaxes(uu, -1, -2)
    return dcm, c_mean - np.einsum("...ab,...b->...a", dcm, p_mean)


def _hypotheses_needed(inlier_share: float, opts: RobustOptions) -> int:
    """Hypotheses for `confidence` of one all-inlier triple at this inlier share (capped)."""
    miss = 1.0 - inlier_share**3
    if miss <= 0.0:
        return 1
    if miss >= 1.0:
        return opts.max_hypotheses
    return min(opts.max_hypotheses, math.ceil(math.log(1.0 - opts.confidence) / math.log(miss)))


def _ransac(c, u, rho, valid, sigma_bearing, sigma_range_m, opts: RobustOptions,
            rng: np.random.Generator, loose_gate: float) -> tuple[np.ndarray, np.ndarray]:
    """Consensus mask (n,) and position (3,) of the best minimal-set hypothesis (MSAC cost with
    the loose gate); adaptive hypothesis count from the best inlier share and `confidence`."""
    idx = np.flatnonzero(valid)
    cv = c[idx]
    p = u[idx] * rho[idx, None]  # body-frame relative vectors R^T (c_j - r)
    tangent_var = (rho[idx] * sigma_bearing) ** 2
    needed, drawn = opts.max_hypotheses, 0
    best_cost, best_s, best_x = np.inf, None, None
    while drawn < min(needed, opts.max_hypotheses):
        k = min(RANSAC_BATCH, opts.max_hypotheses - drawn)
        sample = _sample_triples(rng, idx.size, k)
        dcm, x = absolute_orientation(p[sample], cv[sample])
        los = np.einsum("kab,mb->kma", dcm, u[idx])  # measured lines of sight, MCI
        resid = cv[None] - x[:, None, :] - los * rho[idx, None]  # (k, m, 3) metres
        along2 = np.einsum("kma,kma->km", resid, los) ** 2
        s = along2 / sigma_range_m**2 + (np.einsum("kma,kma->km", resid, resid) - along2) \
            / tangent_var
        cost = np.minimum(s, loose_gate).sum(axis=1)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best_s, best_x = cost[j], s[j], x[j]
            needed = _hypotheses_needed(float(np.mean(best_s < loose_gate)), opts)
        drawn += k
    consensus = np.zeros(valid.size, dtype=bool)
    consensus[idx[best_s < loose_gate]] = True
    return consensus, best_x


def _robust(method, c, u, rho, valid, sigma_bearing, sigma_range_m, step_tol_m, max_iterations,
            opts: RobustOptions, rng: np.random.Generator) -> PoseEstimate:
    if valid.sum() < 3:
        return _failed("too_few_craters", valid, 0)
    gate = _chi2_gate(opts.gate_probability)
    use, prior = _ransac(c, u, rho, valid, sigma_bearing, sigma_range_m, opts, rng,
                         gate * RANSAC_LOOSE_FACTOR**2)
    for _ in range(MAX_GATE_ITERATIONS):
        if use.sum() < 3:
            return _failed("too_few_craters", use, 0)
        est = _fit(method, c, u, rho, use, sigma_bearing, sigma_range_m, prior, step_tol_m,
                   max_iterations)
        if est.status != "ok":
            return est
        s = np.full(valid.size, np.inf)
        s[valid] = _normalised_residuals(c[valid], u[valid], rho[valid], est.r_mci_m,
                                         dcm_from_q(est.q_mci_from_body), sigma_bearing,
                                         sigma_range_m)
        kept = s <= gate
        if np.array_equal(kept, use):
            return est
        use, prior = kept, est.r_mci_m
    return est


def estimate_pose(method: str, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                  sigma_bearing: float, sigma_range_m: float,
                  r_prior_mci_m: np.ndarray | None = None, step_tol_m: float = 1e-9,
                  max_iterations: int = 20, robust: RobustOptions | None = None,
                  rng: np.random.Generator | None = None) -> PoseEstimate:
    """One frame's pose by `method` "paper" or "joint" (the joint starts from the paper's
    estimate; `iterations` is then the joint's own). Inputs as `estimate_paper`.

    With `robust`, false matches are removed first: RANSAC over 3-crater absolute-orientation
    poses scored by MSAC with a loose gate (RANSAC_LOOSE_FACTOR), then the method is fitted on the
    consensus (warm-started at the best hypothesis; `r_prior_mci_m` is not used) and refitted
    until the set of craters passing the chi-square gate (`gate_probability`, 3 dof) under the
    fit is stable (at most MAX_GATE_ITERATIONS fits; the estimate returned is the last fit, its
    `inliers` the rows it used). Random draws come from `rng` only.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}, known {METHODS}")
    c, u, rho, valid = _prepare(c_mci_m, u_body, rho_m)
    if robust is not None:
        if rng is None:
            raise ValueError("robust estimation needs an explicit rng")
        return _robust(method, c, u, rho, valid, sigma_bearing, sigma_range_m, step_tol_m,
                       max_iterations, robust, rng)
    return _fit(method, c, u, rho, valid, sigma_bearing, sigma_range_m, r_prior_mci_m,
                step_tol_m, max_iterations)
