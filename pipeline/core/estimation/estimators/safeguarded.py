"""The safeguarded Gauss-Newton of the joint ML pose (`JointEstimator.refine(...,
safeguarded=True)`), for starts that may be far from the minimum (P3P, the craters' plane, a
prior): the normal equations summed crater by crater (`measurement.normal_equations`), a line
search on the cost, and a stop on the step's size in its own standard deviations; the loop is
compiled (`pose_kernels.gauss_newton`: in Python its glue cost ~150 us a fit, 2-3x the
arithmetic).

Each iteration solves I step = g and forms I^-1 (for the rounding floor and, at the end, the
covariance) from one Cholesky factor. The line search: along the step the linearised cost is
c(t) = cost - 2 t shs + t^2 shs (shs = step^T I step); with the cost c(1) at the full step in
place of the model's, the parabola through c(0), c'(0) and c(1) has its minimum at
t = shs / (c(1) - cost + 2 shs). A full step is taken when t >= LINE_SEARCH_BELOW (the model
holds), else t (at least MIN_FRACTION), halved while the cost is above c(0) (at most
MAX_HALVINGS times). The Jacobi-scaled condition number is bounded by 6 tr((S I S)^-1)
(S = diag(I)^-1/2: the scaled matrix has trace 6, so its largest eigenvalue is at most 6, and its
smallest at least 1 / tr of its inverse); the eigenvalues are computed only when that bound
exceeds MAX_CONDITION.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.estimation.estimators.base import (
    EPS,
    MAX_CONDITION,
    ROUNDING_FACTOR,
    FitSystem,
    PoseEstimate,
    failed,
    scaled_condition,
)
from pipeline.core.estimation.measurement import Frame
from pipeline.core.math.rotations import positive_scalar
from pipeline.core.scoring.status import Status

# A step is shortened to the minimum of the parabola through the costs (the line search) when
# that is below LINE_SEARCH_BELOW of it, but not below MIN_FRACTION, then halved at most
# MAX_HALVINGS times while the cost still rises; and the fit has converged once a step is below
# SMALL_STEP_SIGMA standard deviations of the estimate.
LINE_SEARCH_BELOW = 0.9
MIN_FRACTION = 0.1
MAX_HALVINGS = 10
SMALL_STEP_SIGMA = 1e-4


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
    from pipeline.core.estimation import pose_kernels as kernels  # lazy: Numba costs ~1 s

    sigma_range_m = np.full(f.rho_m.size, np.inf) if f.sigma_range_m is None else f.sigma_range_m
    (outcome, k, x, q, h, cov, cost, shs, rho_pred, cos_pred) = kernels.gauss_newton(
        np.array(r0_mci_m, dtype=float), np.array(q0_mci_from_body, dtype=float), f.c_mci_m,
        f.u_body, f.inv_sigma_bearing, f.rho_m, f.inv_sigma_range,
        np.ascontiguousarray(sigma_range_m, dtype=float), f.max_inv_sigma_bearing, step_tol_m,
        max_iterations, SMALL_STEP_SIGMA, ROUNDING_FACTOR * EPS, LINE_SEARCH_BELOW,
        MIN_FRACTION, MAX_HALVINGS)
    if outcome == kernels.NOT_CONVERGED:
        return failed(Status.NOT_CONVERGED, use, k)
    if outcome != kernels.CONVERGED:
        return failed(Status.DEGENERATE, use, k)
    condition = condition_bound(h, cov)
    if not condition <= MAX_CONDITION:
        return failed(Status.DEGENERATE, use, k)
    fit = FitSystem(h, condition, cost - shs, shs, rho_pred, cos_pred)
    return PoseEstimate(Status.OK.value, x, positive_scalar(q), cov, np.full((3, 3), np.nan), k,
                        use, fit)


def condition_bound(h: np.ndarray, h_inv: np.ndarray) -> float:
    """The Jacobi-scaled condition number of an SPD matrix h with inverse h_inv, or an upper
    bound of it: 6 tr((S h S)^-1) = 6 sum h_ii (h^-1)_ii when that is at most MAX_CONDITION,
    else exactly (`scaled_condition`)."""
    bound = 6.0 * float(h.diagonal() @ h_inv.diagonal())
    return bound if bound <= MAX_CONDITION else scaled_condition(h)
