"""Pose estimators (paper Sec. 4 and beyond), one module per topic:

- `base`: `PoseEstimate`, `EstimatorOptions`, the `Estimator` interface and its registry
  `ESTIMATORS` (method name -> class); a new estimator is a new module with a subclass.
- `position`: closed-form start and range Gauss-Newton (Eq. 12-14); `quest`: QUEST, its
  covariance and position sensitivity; `paper`: the paper's method; `joint`: joint ML pose.
- `robust`: RANSAC and the chi-square refit gate; `information`: Fisher information and CRLB;
  `checks`: the consistency, surface and conditioning checks on every final estimate.

Measurement model (paper Eq. 10-11, ERRATA 6) in `pipeline.core.measurement`. Statuses
(`pipeline.core.status.Status`): `ok`; `too_few_craters` (fewer than 3 usable rows: finite c, u
and rho, a non-zero bearing, a positive range; or, robust, fewer than 3 craters consistent with
any pose); `not_converged` (iteration cap); `degenerate` (singular or ill-conditioned normal
matrices, MAX_CONDITION); then the `checks`: `ill_conditioned`, `below_surface`, `inconsistent`.
A non-ok estimate has NaN pose and covariances. Nothing raises on bad data; an unknown method or a
robust request without a generator is a contract violation (ValueError).
"""

from __future__ import annotations

import numpy as np

from pipeline.core.estimators.base import (
    ESTIMATORS,
    MAX_CONDITION,
    Estimator,
    EstimatorOptions,
    PoseEstimate,
    prepare,
)
from pipeline.core.estimators.checks import CheckOptions, check_estimate
from pipeline.core.estimators.information import crlb, fisher_information
from pipeline.core.estimators.joint import JointEstimator
from pipeline.core.estimators.paper import PaperEstimator
from pipeline.core.estimators.position import closed_form_position, gauss_newton_position
from pipeline.core.estimators.quest import quest, quest_position_sensitivity
from pipeline.core.estimators.robust import RobustOptions, absolute_orientation, robust_fit

METHODS: tuple[str, ...] = tuple(ESTIMATORS)
DEFAULT_CHECKS = CheckOptions()


def estimate_pose(method: str, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                  sigma_bearing: float, sigma_range_m: float,
                  r_prior_mci_m: np.ndarray | None = None, step_tol_m: float = 1e-9,
                  max_iterations: int = 20, robust: RobustOptions | None = None,
                  rng: np.random.Generator | None = None,
                  checks: CheckOptions = DEFAULT_CHECKS) -> PoseEstimate:
    """One frame's pose by `method` (a key of `ESTIMATORS`: "paper", "joint") from craters
    `c_mci_m` (n, 3) (MCI, m), bearings `u_body` (n, 3) (body, renormalised here) and ranges
    `rho_m` (n,) (m) with noise `sigma_bearing` (~rad per axis) and `sigma_range_m` (m). Rows
    with a non-finite value, a zero bearing or a range <= 0 are left out (`inliers` False).

    `r_prior_mci_m`: warm start (the previous estimate; None or NaN for a cold start). With
    `robust`, false matches are removed first (`robust_fit`; the prior is not used) with draws
    from `rng` only. The final estimate always passes `checks` (`check_estimate`) to be `ok`.
    """
    if method not in ESTIMATORS:
        raise ValueError(f"unknown method {method!r}, known {METHODS}")
    if robust is not None and rng is None:
        raise ValueError("robust estimation needs an explicit rng")
    for name, sigma in (("sigma_bearing", sigma_bearing), ("sigma_range_m", sigma_range_m)):
        if not (np.isfinite(sigma) and sigma > 0):  # the weights are 1 / sigma^2
            raise ValueError(f"{name} must be finite and > 0, got {sigma!r}")
    options = EstimatorOptions(sigma_bearing, sigma_range_m, step_tol_m, max_iterations)
    estimator = ESTIMATORS[method](options)
    c, u, rho, valid = prepare(c_mci_m, u_body, rho_m)
    if robust is not None and rng is not None:
        est = robust_fit(estimator, c, u, rho, valid, robust, rng)
    else:
        est = estimator.fit(c, u, rho, valid, r_prior_mci_m)
    return check_estimate(est, c, u, rho, sigma_bearing=sigma_bearing,
                          sigma_range_m=sigma_range_m, options=checks)


__all__ = [
    "DEFAULT_CHECKS", "ESTIMATORS", "MAX_CONDITION", "METHODS", "CheckOptions", "Estimator",
    "EstimatorOptions", "JointEstimator", "PaperEstimator", "PoseEstimate", "RobustOptions",
    "absolute_orientation", "check_estimate", "closed_form_position", "crlb", "estimate_pose",
    "fisher_information", "gauss_newton_position", "quest", "quest_position_sensitivity",
]
