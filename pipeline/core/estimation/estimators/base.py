"""The estimator interface: the result `PoseEstimate`, the options `EstimatorOptions`, the base
class `Estimator` with its registry (method name -> class), and the numerical guards they share.

Every covariance is over the state [position MCI (m), dtheta body (rad)] (or a block of it), with
right (body-frame) attitude perturbations R_est = R_true Exp([dtheta]x), as `measurement`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.estimation.measurement import Sigma

# Largest accepted condition number of a normal matrix after Jacobi (unit-diagonal) scaling. For
# the unit line-of-sight Gram matrix of the range fit, 1e10 means a weakest direction 1e5 times
# worse determined than the best: with 10 m ranges and n craters the position sigma there exceeds
# 1e6/sqrt(n) m, far outside the linearisation, so the fix is called degenerate, not reported.
# Collinear or duplicated craters give 1e15 or more in double precision.
MAX_CONDITION = 1e10
# Gauss-Newton also stops when its step is below this many times the step that the rounding error
# of the residuals (eps * range for ranges, eps for unit bearings) alone produces through the
# normal equations: in weak geometries (3 craters nearly coplanar with the spacecraft) that floor
# exceeds a 1e-9 m `step_tol_m`, and further steps are only rounding noise.
ROUNDING_FACTOR = 10.0
EPS = float(np.finfo(float).eps)


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
class EstimatorOptions:
    """What every estimator needs: the measurement noise it assumes (Eq. 10-11: `sigma_bearing`
    ~rad per tangent axis, `sigma_range_m` m; each a number, or an (n,) array with one value per
    row of the frame's prepared inputs, `measurement.Sigma`) and its Gauss-Newton stop
    (`step_tol_m` m, at most `max_iterations` steps)."""

    sigma_bearing: Sigma
    sigma_range_m: Sigma
    step_tol_m: float = 1e-9
    max_iterations: int = 20


@dataclass(frozen=True)
class Estimator(ABC):
    """A single-frame pose estimator: a frozen options object and one `fit`. A subclass names
    itself with `method` and registers under that name (`ESTIMATORS`) by being defined."""

    options: EstimatorOptions
    method: ClassVar[str]

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        ESTIMATORS[cls.method] = cls

    @abstractmethod
    def fit(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, use: np.ndarray,
            r_prior_mci_m: np.ndarray | None) -> PoseEstimate:
        """The pose from the rows `use` (n,) bool of prepared inputs (`prepare`): craters (n, 3)
        (MCI, m), unit bearings (n, 3) (body), ranges (n,) (m; NaN: that crater has a bearing
        and no range); `r_prior_mci_m` a warm start (the previous estimate) or None. Never
        raises on bad data: a status instead."""


ESTIMATORS: dict[str, type[Estimator]] = {}


def prepare(c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Float arrays, bearings renormalised, and the mask of usable rows: finite c and u, a
    non-zero bearing, and a range that is positive and finite or NaN (no range: the crater
    counts by its bearing alone). An infinite or non-positive range is bad data: row left out."""
    c = np.asarray(c_mci_m, dtype=float).reshape(-1, 3)
    u = np.asarray(u_body, dtype=float).reshape(-1, 3)
    rho = np.asarray(rho_m, dtype=float).reshape(-1)
    norm = np.sqrt(np.einsum("ij,ij->i", u, u))
    valid = np.isfinite(c).all(axis=1) & np.isfinite(norm) & (norm > 0) \
        & ((np.isfinite(rho) & (rho > 0)) | np.isnan(rho))
    with np.errstate(invalid="ignore", divide="ignore"):
        u = u / norm[:, None]
    return c, u, rho, valid


def failed(status: str, inliers: np.ndarray, iterations: int) -> PoseEstimate:
    """A non-ok estimate (`status` a `Status`, stored as its plain string): NaN pose and
    covariances."""
    return PoseEstimate(str(status), np.full(3, np.nan), np.full(4, np.nan),
                        np.full((6, 6), np.nan), np.full((3, 3), np.nan), iterations, inliers)


def inverse_if_well_conditioned(h: np.ndarray, max_condition: float = MAX_CONDITION
                                ) -> np.ndarray | None:
    """Inverse of a symmetric positive definite normal matrix, or None when its Jacobi-scaled
    condition number exceeds `max_condition` (or it is singular or not finite)."""
    diag = np.diag(h)
    if not (np.all(np.isfinite(h)) and np.all(diag > 0)):
        return None
    s = 1.0 / np.sqrt(diag)
    outer = s[:, None] * s[None, :]
    ev, vec = np.linalg.eigh(h * outer)
    if not ev[0] > ev[-1] / max_condition:
        return None
    return (vec / ev) @ vec.T * outer

