"""Pose estimators (paper Sec. 4 and beyond), one module per topic:

- `base`: `PoseEstimate`, `EstimatorOptions`, the `Estimator` interface and its registry
  `ESTIMATORS` (method name -> class); a new estimator is a new module with a subclass.
- `position`: closed-form start and range Gauss-Newton (Eq. 12-14); `quest`: QUEST, its
  covariance and position sensitivity; `paper`: the paper's method; `joint`: joint ML pose.
- `bearings`: P3P and the cold starts from bearings alone (joint without ranges, RANSAC): the
  craters' plane (`planar_pose`, a homography) and P3P candidates.
- `safeguarded`: the joint's Gauss-Newton from starts far from the minimum (line search, closed-
  form normal equations of `measurement`, LAPACK called directly).
- `robust`: RANSAC and the chi-square refit gate; `information`: Fisher information and CRLB;
  `checks`: the consistency, surface and conditioning checks on every final estimate (on the
  fit's own last system when it has one, `FitSystem`).

Measurement model (paper Eq. 10-11, ERRATA 6) in `pipeline.core.estimation.measurement`: noise one
number
for every crater or one value per crater; a NaN range means the crater was seen by its bearing
only (bearings-only frames: "joint"; "paper" needs 3 ranges). Statuses
(`pipeline.core.scoring.status.Status`): `ok`; `too_few_craters` (fewer than 3 usable rows: finite
c and
u, a non-zero bearing, a positive range or NaN; or, robust, fewer than 3 craters consistent with
any pose); `needs_ranges` (paper: fewer than 3 usable rows with a range); `ambiguous` (joint: 3
craters, bearings only, no prior, several exact poses); `not_converged` (iteration cap);
`degenerate` (singular or ill-conditioned normal matrices, MAX_CONDITION); then the `checks`:
`ill_conditioned`, `below_surface`, `inconsistent`. A non-ok estimate has NaN pose and
covariances. Nothing raises on bad data; an unknown method, a robust request without a
generator or a noise that is not finite and > 0 (or not one per crater) is a contract violation
(ValueError).
"""

from __future__ import annotations

import numpy as np

from pipeline.core.estimation.estimators.base import (
    ESTIMATORS,
    MAX_CONDITION,
    Estimator,
    EstimatorOptions,
    PoseEstimate,
    prepare,
)
from pipeline.core.estimation.estimators.bearings import absolute_orientation, bearings_initial, p3p
from pipeline.core.estimation.estimators.checks import CheckOptions, check_estimate
from pipeline.core.estimation.estimators.information import crlb, fisher_information
from pipeline.core.estimation.estimators.joint import JointEstimator
from pipeline.core.estimation.estimators.paper import PaperEstimator
from pipeline.core.estimation.estimators.position import closed_form_position, gauss_newton_position
from pipeline.core.estimation.estimators.quest import quest, quest_position_sensitivity
from pipeline.core.estimation.estimators.robust import RobustOptions, robust_fit
from pipeline.core.estimation.measurement import Sigma, noise

METHODS: tuple[str, ...] = tuple(ESTIMATORS)
DEFAULT_CHECKS = CheckOptions()


def estimate_pose(method: str, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, *,
                  sigma_bearing: Sigma, sigma_range_m: Sigma,
                  r_prior_mci_m: np.ndarray | None = None, step_tol_m: float = 1e-9,
                  max_iterations: int = 20, robust: RobustOptions | None = None,
                  rng: np.random.Generator | None = None,
                  checks: CheckOptions = DEFAULT_CHECKS) -> PoseEstimate:
    """One frame's pose by `method` (a key of `ESTIMATORS`: "paper", "joint") from craters
    `c_mci_m` (n, 3) (MCI, m), bearings `u_body` (n, 3) (body, renormalised here) and ranges
    `rho_m` (n,) (m; NaN: no range, the crater counts by its bearing) with noise `sigma_bearing`
    (~rad per axis) and `sigma_range_m` (m), each one number or an (n,) array, one per crater (an
    array of equal values is that number). Rows with a non-finite c or u, a zero bearing, or an
    infinite or non-positive range are left out (`inliers` False).

    `r_prior_mci_m`: warm start (the previous estimate; None or NaN for a cold start). With
    `robust`, false matches are removed first (`robust_fit`; the prior is not used) with draws
    from `rng` only. The final estimate always passes `checks` (`check_estimate`) to be `ok`.
    """
    if method not in ESTIMATORS:
        raise ValueError(f"unknown method {method!r}, known {METHODS}")
    if robust is not None and rng is None:
        raise ValueError("robust estimation needs an explicit rng")
    n = int(np.size(rho_m))
    sigma_bearing = _uniform(noise("sigma_bearing", sigma_bearing, n))
    sigma_range_m = _uniform(noise("sigma_range_m", sigma_range_m, n))
    options = EstimatorOptions(sigma_bearing, sigma_range_m, step_tol_m, max_iterations)
    estimator = ESTIMATORS[method](options)
    c, u, rho, valid = prepare(c_mci_m, u_body, rho_m)
    if robust is not None and rng is not None:
        est = robust_fit(estimator, c, u, rho, valid, robust, rng)
    else:
        est = estimator.fit(c, u, rho, valid, r_prior_mci_m)
    return check_estimate(est, c, u, rho, sigma_bearing=sigma_bearing,
                          sigma_range_m=sigma_range_m, options=checks)


def _uniform(sigma: Sigma) -> Sigma:
    """A per-crater noise whose values are all equal as that one number (so that the paper's
    arithmetic, and its bits, are kept); anything else unchanged."""
    if np.ndim(sigma) == 0:
        return sigma
    arr = np.asarray(sigma)
    return float(arr[0]) if arr.size and bool(np.all(arr == arr[0])) else arr


__all__ = [
    "DEFAULT_CHECKS", "ESTIMATORS", "MAX_CONDITION", "METHODS", "CheckOptions", "Estimator",
    "EstimatorOptions", "JointEstimator", "PaperEstimator", "PoseEstimate", "RobustOptions",
    "Sigma", "absolute_orientation", "bearings_initial", "check_estimate", "closed_form_position",
    "crlb", "estimate_pose", "fisher_information", "gauss_newton_position", "p3p", "quest",
    "quest_position_sensitivity",
]
