"""The checks a navigator applies to every final estimate before it calls it `ok`: a wrong fix
says so (a status, NaN pose) instead of reporting a covariance it does not have.

In order, on the rows the estimate used, at the estimated pose:
1. `ill_conditioned`: the Cramer-Rao bound of the geometry (`information`) at the estimate is
   numerically singular (Jacobi-scaled condition number of the Fisher information above
   `max_condition`) or too wide for the linearised model it rests on: a position 1-sigma above
   `max_relative_sigma` times the nearest range, or an attitude 1-sigma above
   `max_relative_sigma` rad; or (the paper's) the estimate's own attitude covariance too
   anisotropic for its linearisation (`_attitude_linear`). Craters within 10 m of each other
   or within ~20 m of a line give 0.07-2 (position sigma over range); well-posed frames of 10
   or more craters stay below 1e-3, and random 3-crater frames exceed 0.05 in about 0.2 % of
   draws.
2. `below_surface`: a crater behind the camera (a measured bearing outside the hemisphere of
   `boresight_body`, or pointing away from its crater under the estimate: (c_j - r) . R u_j <= 0)
   or, when `moon_radius_m` is given, the position under the surface: |r| < moon_radius_m -
   surface_margin_m. The ranges alone have a mirror solution across the craters' plane, below
   the surface; with bearings negated it is also consistent with the bearings (a reflection
   times -I is a rotation), so only these tests catch it.
3. `inconsistent`: the normalised residuals (`measurement`: 2 bearing components per crater and
   1 per range, M = 2N + N_ranges in all; 3N with every range) fail a chi-square test at
   `consistency_probability` (`_consistent`): their linearised minimum against M - 6 dof (6 pose
   parameters fitted; none to test when M = 6, 3 craters with bearings only), and the distance
   of the estimate from that minimum against its own covariance (6 dof). For an estimate that
   is not the ML (the paper's), the minimum is reached by Gauss-Newton steps from it when one
   linearised step does not reach it (`_iterated`).
The noise is one number or one value per crater (`measurement.Sigma`) for the rows given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy.linalg import lapack

from pipeline.core.estimation.estimators.base import (
    MAX_CONDITION,
    PoseEstimate,
    failed,
    scaled_condition,
    scaled_inverse,
    select_rows,
)
from pipeline.core.estimation.measurement import (
    Frame,
    NormalEquations,
    Sigma,
    frame,
    normal_equations,
    per_crater,
)
from pipeline.core.math import chi_square
from pipeline.core.math.rotations import dcm_from_q, q_exp, q_log, q_multiply
from pipeline.core.scoring.status import Status

# Gauss-Newton steps from a non-ML estimate (the paper's) towards the ML pose for the residual
# tests (`_iterated`, CheckOptions.ml_steps), and the squared step in the estimate's covariance
# metric below which a step is negligible (a tenth of a sigma)
ML_STEPS = 10
ML_STEP_TOL = 1e-2
# the largest second-order attitude term of an estimate, in its narrowest 1-sigmas
# (`_attitude_linear`)
SECOND_ORDER_SIGMAS = 2.0


@dataclass(frozen=True)
class CheckOptions:
    """Thresholds of the checks on a final estimate."""

    # chi-square probability of the residual test: a consistent frame is flagged with
    # probability 1 - consistency_probability (1e-6)
    consistency_probability: float = 1.0 - 1e-6
    # largest Jacobi-scaled condition number of the Fisher information at the estimate
    max_condition: float = MAX_CONDITION
    # largest 1-sigma of the bound at the estimate: position over the nearest range, attitude
    # (rad); at 0.05 the model's second-order terms are 5 % of its first-order ones; inf: no
    # linearity test at all (neither this one nor the paper estimate's, `_attitude_linear`)
    max_relative_sigma: float = 0.05
    # mean Moon radius (m) for the surface test; None skips it (core takes no constants)
    moon_radius_m: float | None = None
    # depth below moon_radius_m still accepted (m): the lunar relief spans about -9 to +11 km
    surface_margin_m: float = 20e3
    # the camera's boresight in body axes (camera frame = body frame, boresight +z): every
    # measured bearing must lie in its hemisphere; None skips the test
    boresight_body: tuple[float, float, float] | None = (0.0, 0.0, 1.0)
    # further Gauss-Newton steps towards the ML pose when one does not reach it (`_iterated`;
    # 0: the one linearised step, which passed a 3-crater paper fix of the sweep 8.5 km up,
    # NEES 94.7 for 6: test_check_iterated)
    ml_steps: int = ML_STEPS


@cache
def _chi2_threshold(probability: float, dof: int) -> float:
    return float(chi_square.upper_quantile(1.0 - probability, dof))


def check_estimate(est: PoseEstimate, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
                   *, sigma_bearing: Sigma, sigma_range_m: Sigma, options: CheckOptions
                   ) -> PoseEstimate:
    """`est` unchanged when it is not `ok` or passes every check; otherwise a failed estimate
    (NaN pose and covariances, same `inliers` and `iterations`) with the first failing status.
    Inputs as the estimator saw them: craters (n, 3) (MCI, m), unit bearings (n, 3) (body) and
    ranges (n,) (m, NaN: no range), noise a number or (n,) per row; only the rows `est.inliers`
    are used.

    An estimate with the `system` of its fit (the joint's Gauss-Newton) is checked on that
    system, at the pose one step (below tolerance) before it: its information and the scaled
    eigenvalues already computed, its covariance the bound, its linearised cost and step the
    residual tests. Any other (the paper's) is checked on the normal equations at the estimate
    (`measurement.normal_equations`)."""
    if est.status != Status.OK:
        return est
    use = est.inliers
    c, u, rho = select_rows(use, c_mci_m, u_body, rho_m)
    r = est.r_mci_m
    fit = est.system
    if fit is None:
        f = frame(c, u, rho, per_crater(sigma_bearing, use), per_crater(sigma_range_m, use))
        with np.errstate(all="ignore"):
            ne = normal_equations(r, dcm_from_q(est.q_mci_from_body), f)
        bound, _ = scaled_inverse(ne.info, options.max_condition, direct=True)
        rho_pred, cos_pred = ne.rho_pred_m, ne.cos_pred
    else:
        well = fit.condition <= options.max_condition \
            or scaled_condition(fit.info) <= options.max_condition
        bound = est.cov if well else None
        rho_pred, cos_pred = fit.rho_pred_m, fit.cos_pred
    missing = np.isnan(rho)
    n_missing = int(np.count_nonzero(missing))
    if n_missing == 0:
        nearest = float(rho.min())
    else:  # the predicted range of a crater without one
        nearest = float((rho_pred if n_missing == rho.size
                         else np.where(missing, rho_pred, rho)).min())
    if (bound is None or not _linear(bound, nearest, options.max_relative_sigma)
            or (fit is None and math.isfinite(options.max_relative_sigma)
                and not _attitude_linear(est.cov))):
        return failed(Status.ILL_CONDITIONED, use, est.iterations)
    radius = options.moon_radius_m
    ahead = options.boresight_body is None \
        or float((u @ options.boresight_body).min()) > 0.0
    if not (ahead and float(cos_pred.min()) > 0.0
            and (radius is None or float(r @ r) >= (radius - options.surface_margin_m)**2)):
        return failed(Status.BELOW_SURFACE, use, est.iterations)
    if fit is None:
        with np.errstate(all="ignore"):
            cost, shift = _linearised(ne.info, ne.gradient, ne.cost, bound, est.cov)
            if options.ml_steps:
                cost, shift = _iterated(est, f, ne, bound, options, cost, shift)
    else:
        cost, shift = fit.cost, fit.shift
    if not _consistent(cost, shift, options.consistency_probability,
                       3 * rho.size - n_missing):
        return failed(Status.INCONSISTENT, use, est.iterations)
    return est


def _linear(bound: np.ndarray, nearest_m: float, max_relative_sigma: float) -> bool:
    """Whether the bound (6, 6) is small enough for the model to be linear over it: largest
    position 1-sigma over the smallest range `nearest_m` (m), and largest attitude 1-sigma
    (rad), both at most `max_relative_sigma` (the second-order terms of h are that fraction of
    the first-order). A block's largest eigenvalue is at most its trace, so a trace below the
    limit decides without the eigenvalues."""
    limit_r = max_relative_sigma * nearest_m
    d = bound.diagonal().tolist()
    if (d[0] + d[1] + d[2] <= limit_r**2 * (1.0 - 1e-9)
            and d[3] + d[4] + d[5] <= max_relative_sigma**2 * (1.0 - 1e-9)):
        return True
    sig_r = float(np.sqrt(np.linalg.eigvalsh(bound[:3, :3])[-1]))
    sig_theta = float(np.sqrt(np.linalg.eigvalsh(bound[3:, 3:])[-1]))
    return sig_r <= limit_r and sig_theta <= max_relative_sigma


def _attitude_linear(cov: np.ndarray) -> bool:
    """Whether the estimate's own attitude covariance (the (6, 6) `cov`'s last block, rad^2) is
    linear over its spread: the second-order term of its widest axis, sigma_max^2 / 2 (rad), at
    most SECOND_ORDER_SIGMAS of its narrowest 1-sigma. That term, k narrow sigmas, adds ~k^2 to
    the NEES (6 expected): at most ~4. The bound's test (`_linear`) does not see an estimate
    much wider than the bound: a paper fix of 3 craters a few km up (the position fitted
    exactly by its 3 ranges, the attitude spread 2-3 deg about two axes and 0.02 deg about the
    third, k ~ 5) had a NEES of ~100 for 6. Applied to estimates without a fit system of their
    own (the paper's: QUEST's covariance with the position's propagated into it): the joint's
    covariance is its Fisher information's inverse at the estimate, and its 3-crater exact fits
    that fail this test measured consistent (mean NEES 2.4-6.1 over 9 such geometries). Fast
    path: sigma_min^2 >= 4 det / tr^2 (the two larger eigenvalues' product is at most
    (tr / 2)^2) and sigma_max^2 <= tr."""
    a = cov[3:, 3:]
    tr = float(a[0, 0] + a[1, 1] + a[2, 2])
    det = float(np.linalg.det(a))
    k = SECOND_ORDER_SIGMAS
    if tr * tr <= 4.0 * k * math.sqrt(max(det, 0.0)) * (1.0 - 1e-9):
        return True
    ev = np.linalg.eigvalsh(a)
    return bool(ev[-1] / 2.0 <= k * math.sqrt(max(float(ev[0]), 0.0)))


def _linearised(info: np.ndarray, gradient: np.ndarray, cost: float, bound: np.ndarray,
                cov: np.ndarray) -> tuple[float, float]:
    """The residual tests' quantities at a pose estimate from its normal equations (information
    I (6, 6), gradient g = sum J^T e (6,), cost e^T e), I^-1 (`bound`) and the estimate's
    covariance (6, 6): the linearised best pose is one Gauss-Newton step delta = I^-1 g away,
    with the cost e^T e - g^T delta, at the distance delta^T cov^-1 delta (NaN when cov is
    singular)."""
    delta = bound @ gradient
    _, _, solved, info = lapack.dgesv(cov, delta)  # LU, as np.linalg.solve, without its wrapper
    shift = float(delta @ solved) if info == 0 else math.nan
    return cost - float(gradient @ delta), shift


def _iterated(est: PoseEstimate, f: Frame, ne: NormalEquations, bound: np.ndarray,
              options: CheckOptions, cost: float, shift: float) -> tuple[float, float]:
    """`_linearised`'s cost and shift, or, when one Gauss-Newton step from the estimate does not
    reach the ML pose, those of the ML pose reached by further steps (`ml_steps` at most): an
    estimate whose own covariance spans a few % of the range (the paper's method on
    apparent-size ranges: position from ranges of 5 % noise) is so far from the ML that one
    linearised step misses it, and its distance from the ML would be underestimated by orders
    of magnitude (NEES 4,800 read as 12). The step is negligible, and the one-step values kept,
    when the second step moves the estimate by less than ML_STEP_TOL (squared, in its own
    covariance's metric)."""
    delta = bound @ ne.gradient
    r, q = est.r_mci_m + delta[:3], q_multiply(est.q_mci_from_body, q_exp(delta[3:]))
    moved = False
    for _ in range(options.ml_steps):
        step_ne = normal_equations(r, dcm_from_q(q), f)
        step_bound, _ = scaled_inverse(step_ne.info, options.max_condition,
                                        direct=True)
        if step_bound is None:
            return cost, math.inf  # the geometry is singular on the way: no ML to compare
        step = step_bound @ step_ne.gradient
        _, _, solved, info = lapack.dgesv(est.cov, step)
        if info != 0:
            return cost, math.nan
        if float(step @ solved) <= ML_STEP_TOL:
            if not moved:
                return cost, shift
            break
        moved = True
        cost = step_ne.cost - float(step_ne.gradient @ step)
        r, q = r + step[:3], q_multiply(q, q_exp(step[3:]))
    q_est = est.q_mci_from_body
    total = np.concatenate([r - est.r_mci_m, q_log(q_multiply(
        np.array([-q_est[0], -q_est[1], -q_est[2], q_est[3]]), q))])
    _, _, solved, info = lapack.dgesv(est.cov, total)
    return cost, (float(total @ solved) if info == 0 else math.nan)


def _consistent(cost: float, shift: float, probability: float, measurements: int) -> bool:
    """The residual tests at a pose estimate, from the cost of the linearised best pose and the
    estimate's distance from it (`_linearised`, or a fit's `FitSystem`), with M scalar
    measurements present (`measurement_count`).

    The cost is chi-square with M - 6 dof (the measurements fit some pose); the distance is at
    most chi-square with 6 dof (the estimate is as close to that pose as its covariance claims:
    cov(x_est - x_ML) = cov - I^-1 for an efficient ML). An estimate that is not the ML (the
    paper's method) is judged by both: its own cost can exceed the M - 6 quantile on good frames
    while both tests hold."""
    dof = measurements - 6  # none when the measurements determine the pose exactly
    return ((dof <= 0 or cost <= _chi2_threshold(probability, dof))
            and shift <= _chi2_threshold(probability, 6))
