"""Position from ranges alone (paper Sec. 4.1, Eq. 12-14, ERRATA 3): a closed-form start and the
Gauss-Newton fit of the range residuals, both on the range model of `measurement`."""

from __future__ import annotations

import math

import numpy as np

from pipeline.core.estimation.estimators.base import (
    EPS,
    MAX_CONDITION,
    ROUNDING_FACTOR,
    inverse_if_well_conditioned,
)
from pipeline.core.estimation.measurement import Sigma, line_of_sight
from pipeline.core.scoring.status import Status


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


def _sym3_inverse(h: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Inverse of a symmetric 3x3 matrix by its adjugate, and its trace; None unless the
    determinant and the three diagonal 2x2 minors are > 0 (so the inverse has a positive
    diagonal even when rounding makes a singular matrix look definite)."""
    (a, b, c), (_, d, e), (_, _, f) = h.tolist()
    m00, m01, m02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * m00 + b * m01 + c * m02
    m11, m12, m22 = a * f - c * c, b * c - a * e, a * d - b * b
    if not (det > 0.0 and m00 > 0.0 and m11 > 0.0 and m22 > 0.0):
        return None
    i00, i01, i02, i11, i12, i22 = m00 / det, m01 / det, m02 / det, m11 / det, m12 / det, \
        m22 / det
    return np.array([[i00, i01, i02], [i01, i11, i12], [i02, i12, i22]]), i00 + i11 + i22


def gauss_newton_position(c_mci_m: np.ndarray, rho_m: np.ndarray, r0_mci_m: np.ndarray,
                          step_tol_m: float, max_iterations: int, *, sigma_range_m: Sigma = 1.0
                          ) -> tuple[np.ndarray, np.ndarray, int, str]:
    """Gauss-Newton on the range residuals f_j = h_rho,j(r) - rho_j (paper Eq. 12-14, ERRATA 3).

    Returns the position (3,) (MCI, m), its covariance sigma_range^2 (J^T J)^-1 (m^2; the default
    sigma 1 gives (J^T J)^-1), the number of steps and a status: `ok` once a step is at most
    `step_tol_m` (m) or its rounding floor (ROUNDING_FACTOR), `not_converged` at the cap,
    `degenerate` for an ill-conditioned J^T J (MAX_CONDITION). Position and covariance are NaN
    unless ok. With `sigma_range_m` an (n,) array (one per crater) the fit is weighted: residual j
    by 1 / sigma_j^2, covariance (J^T W J)^-1.
    """
    c = np.asarray(c_mci_m, dtype=float)
    rho = np.asarray(rho_m, dtype=float)
    x = np.array(r0_mci_m, dtype=float)
    sigma = np.asarray(sigma_range_m, dtype=float)
    if sigma.ndim == 0:  # every residual of weight 1 (exact: the scale is 1.0)
        return _weighted_gauss_newton(c, rho, x, step_tol_m, max_iterations, None, float(sigma))
    return _weighted_gauss_newton(c, rho, x, step_tol_m, max_iterations,
                                  float(sigma.min()) / sigma, float(sigma.min()))


def _weighted_gauss_newton(c: np.ndarray, rho: np.ndarray, x: np.ndarray, step_tol_m: float,
                           max_iterations: int, s: np.ndarray | None, scale: float
                           ) -> tuple[np.ndarray, np.ndarray, int, str]:
    """`gauss_newton_position`'s iteration on the residuals scaled by s (n,) (s_j = min(sigma) /
    sigma_j, so the best range keeps weight 1 and the rounding floor its meaning; None: one
    sigma), covariance scale^2 (J^T S^2 J)^-1 with scale = min(sigma) (m)."""
    nan_x, nan_cov = np.full(3, np.nan), np.full((3, 3), np.nan)
    for k in range(1, max_iterations + 1):
        w, rng_m = line_of_sight(x, c)
        # one sigma: w itself, so w^T w is the symmetric product numpy computes for it (a
        # weighted copy would round differently)
        ws = w if s is None else w * (s * s)[:, None]
        h = w.T @ ws
        inverse = _sym3_inverse(h)
        if inverse is None:
            return nan_x, nan_cov, k, Status.DEGENERATE.value
        h_inv, trace = inverse
        step = h_inv @ ((rng_m - rho) @ ws)
        x += step
        s0, s1, s2 = step.tolist()
        step_m = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        if not math.isfinite(step_m):
            return nan_x, nan_cov, k, Status.DEGENERATE.value
        if step_m <= step_tol_m or step_m <= ROUNDING_FACTOR * EPS * float(
                (rng_m if s is None else rng_m * s).max()) * math.sqrt(trace):
            cov = inverse_if_well_conditioned(h)
            if cov is None:
                return nan_x, nan_cov, k, Status.DEGENERATE.value
            return x, scale**2 * cov, k, Status.OK.value
    return nan_x, nan_cov, max_iterations, Status.NOT_CONVERGED.value
