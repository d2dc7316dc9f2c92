"""The safeguarded Gauss-Newton of the joint ML pose (`JointEstimator.refine(...,
safeguarded=True)`), for starts that may be far from the minimum (P3P, the craters' plane, a
prior): the normal equations in closed form (`measurement.normal_equations`), a line search on
the cost, and a stop on the step's size in its own standard deviations.

Each iteration solves I step = g and forms I^-1 (for the rounding floor and, at the end, the
covariance) in one Cholesky solve (LAPACK dposv, called directly: numpy's linalg wrappers cost
more than the 6x6 solve itself). The Jacobi-scaled condition number is bounded by
6 tr((S I S)^-1) (S = diag(I)^-1/2: the scaled matrix has trace 6, so its largest eigenvalue is
at most 6, and its smallest at least 1 / tr of its inverse); the eigenvalues are computed only
when that bound exceeds MAX_CONDITION.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import lapack

from pipeline.core.estimation.estimators.base import (
    EPS,
    MAX_CONDITION,
    ROUNDING_FACTOR,
    FitSystem,
    PoseEstimate,
    failed,
    scaled_condition,
)
from pipeline.core.estimation.measurement import (
    Frame,
    NormalEquations,
    normal_equations,
    rounding_level,
)
from pipeline.core.math.rotations import dcm_from_q, positive_scalar, q_exp, q_multiply
from pipeline.core.scoring.status import Status

# A step is shortened to the minimum of the parabola through the costs (`_line_search`) when
# that is below LINE_SEARCH_BELOW of it, but not below MIN_FRACTION, then halved at most
# MAX_HALVINGS times while the cost still rises; and the fit has converged once a step is below
# SMALL_STEP_SIGMA standard deviations of the estimate.
LINE_SEARCH_BELOW = 0.9
MIN_FRACTION = 0.1
MAX_HALVINGS = 10
SMALL_STEP_SIGMA = 1e-4
_RHS = np.concatenate([np.zeros((6, 1)), np.eye(6)], axis=1)  # [g, I]: step and I^-1 at once


def refine(f: Frame, use: np.ndarray, r0_mci_m: np.ndarray, q0_mci_from_body: np.ndarray, *,
           step_tol_m: float, max_iterations: int) -> PoseEstimate:
    """Gauss-Newton on the frame `f` (the rows `use` of the estimator's inputs) from the pose
    (r0, q0): steps I^-1 g on (dr, dtheta), R <- R Exp(dtheta), each shortened by a line search
    where the cost departs from the linear model's. Stops when (a) the step is below
    SMALL_STEP_SIGMA of its own standard deviation (sqrt(step^T I step)): weak bearings-only
    geometries (4-5 craters) converge only linearly; or (b) the position step is at most
    `step_tol_m` (m) and the attitude step moves no crater by more than that, or both are at
    their rounding floor (ROUNDING_FACTOR, `measurement.rounding_level`).
    `cov` = I^-1 at the last pose (one step before the estimate, the step below tolerance);
    the estimate carries that system (`FitSystem`) for the checks."""
    x = np.array(r0_mci_m, dtype=float)
    q = np.asarray(q0_mci_from_body, dtype=float)
    ne = normal_equations(x, dcm_from_q(q), f)
    rhs = _RHS.copy()
    for k in range(1, max_iterations + 1):
        h = ne.info
        rhs[:, 0] = ne.gradient
        _, sol, info = lapack.dposv(h, rhs)
        if info != 0:  # not positive definite: singular, or not finite
            return failed(Status.DEGENERATE, use, k)
        step = sol[:, 0]
        s0, s1, s2, s3, s4, s5 = step.tolist()
        dx, dth = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2), math.sqrt(s3 * s3 + s4 * s4 + s5 * s5)
        if not math.isfinite(dx + dth):
            return failed(Status.DEGENERATE, use, k)
        x_full = x + step[:3]
        q_full = q_multiply(q, q_exp(step[3:]))
        q_full /= math.sqrt(float(q_full @ q_full))
        shs = float(step @ ne.gradient)  # step^T I step, I step = g
        done = shs <= SMALL_STEP_SIGMA**2
        if not done:
            d = sol[:, 1:].diagonal().tolist()
            rho_max = float(ne.rho_pred_m.max())
            noise = ROUNDING_FACTOR * EPS * rounding_level(f, ne.rho_pred_m)
            done = (dx <= max(step_tol_m, noise * math.sqrt(abs(d[0]) + abs(d[1]) + abs(d[2])))
                    and dth <= max(step_tol_m / rho_max,
                                   noise * math.sqrt(abs(d[3]) + abs(d[4]) + abs(d[5]))))
        if done:
            cov = sol[:, 1:]
            cov = 0.5 * (cov + cov.T)
            condition = condition_bound(h, cov)
            if not condition <= MAX_CONDITION:
                return failed(Status.DEGENERATE, use, k)
            fit = FitSystem(h, condition, ne.cost - shs, shs, ne.rho_pred_m, ne.cos_pred)
            return PoseEstimate(Status.OK.value, x_full, positive_scalar(q_full), cov,
                                np.full((3, 3), np.nan), k, use, fit)
        x, q, ne = _line_search(f, x, q, step, ne.cost, shs, x_full, q_full)
    return failed(Status.NOT_CONVERGED, use, max_iterations)


def condition_bound(h: np.ndarray, h_inv: np.ndarray) -> float:
    """The Jacobi-scaled condition number of an SPD matrix h with inverse h_inv, or an upper
    bound of it: 6 tr((S h S)^-1) = 6 sum h_ii (h^-1)_ii when that is at most MAX_CONDITION,
    else exactly (`scaled_condition`)."""
    bound = 6.0 * float(h.diagonal() @ h_inv.diagonal())
    return bound if bound <= MAX_CONDITION else scaled_condition(h)


def _line_search(f: Frame, x: np.ndarray, q: np.ndarray, step: np.ndarray, cost: float,
                 shs: float, x_full: np.ndarray, q_full: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, NormalEquations]:
    """The pose a fraction t of the Gauss-Newton `step` (6,) from (x, q) and its system.

    Along the step the linearised cost is c(t) = cost - 2 t shs + t^2 shs (shs = step^T I step);
    with the cost c(1) at the full step (x_full, q_full) in place of the model's, the parabola
    through c(0), c'(0) and c(1) has its minimum at t = shs / (c(1) - cost + 2 shs). A full
    step is taken when t >= LINE_SEARCH_BELOW (the model holds), else t (at least MIN_FRACTION),
    halved while the cost is above `cost` (at most MAX_HALVINGS times)."""
    ahead = normal_equations(x_full, dcm_from_q(q_full), f)
    curvature = ahead.cost - cost + 2.0 * shs
    t = shs / curvature if curvature * MIN_FRACTION < shs else MIN_FRACTION
    if t >= LINE_SEARCH_BELOW:
        return x_full, q_full, ahead
    t = max(t, MIN_FRACTION)
    for _ in range(MAX_HALVINGS + 1):
        x_t = x + t * step[:3]
        q_t = q_multiply(q, q_exp(t * step[3:]))
        q_t /= math.sqrt(float(q_t @ q_t))
        ahead = normal_equations(x_t, dcm_from_q(q_t), f)
        if ahead.cost <= cost:
            break
        t *= 0.5
    return x_t, q_t, ahead
