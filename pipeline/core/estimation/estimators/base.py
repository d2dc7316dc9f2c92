"""The estimator interface: the result `PoseEstimate`, the options `EstimatorOptions`, the base
class `Estimator` with its registry (method name -> class), and the numerical guards they share.

Every covariance is over the state [position MCI (m), dtheta body (rad)] (or a block of it), with
right (body-frame) attitude perturbations R_est = R_true Exp([dtheta]x), as `measurement`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import numpy as np
from scipy.linalg import lapack

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


class FitSystem(NamedTuple):
    """What a Gauss-Newton fit of the whole pose leaves for the checks of its estimate
    (`checks.check_estimate`, which then evaluates no model of its own): its last system, at the
    pose one step (below tolerance) before the estimate, over the rows the fit used."""

    info: np.ndarray  # (6, 6) sum J^T J there, of [position MCI (m), dtheta body (rad)]
    condition: float  # Jacobi-scaled condition number of info, or an upper bound of it
    cost: float  # e^T e - g^T step: the cost of the linearised model at the estimate
    shift: float  # step^T info step: the estimate's squared distance from that pose, in sigma
    rho_pred_m: np.ndarray  # (n_used,) predicted ranges (m)
    cos_pred: np.ndarray  # (n_used,) cosine between each measured and predicted bearing


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
    system: FitSystem | None = None  # the fit's last system (joint), else None


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
    # the usual frame, every row good (a finite sum, positive norms and ranges), in few passes
    if (rho.size and math.isfinite(float(c.sum()) + float(norm.sum()))
            and float(norm.min()) > 0.0
            and ((float(rho.min()) > 0.0 and math.isfinite(float(rho.max())))
                 or bool(np.isnan(rho).all()))):
        return c, u / norm[:, None], rho, np.ones(rho.size, dtype=bool)
    valid = np.isfinite(c).all(axis=1) & np.isfinite(norm) & (norm > 0) \
        & ((np.isfinite(rho) & (rho > 0)) | np.isnan(rho))
    with np.errstate(invalid="ignore", divide="ignore"):
        u = u / norm[:, None]
    return c, u, rho, valid


def select_rows(use: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The rows `use` (n,) bool of each array: a[use], or the arrays themselves when every row is
    used (the same values, without the copies)."""
    if use.all():
        return arrays
    return tuple(a[use] for a in arrays)


def failed(status: str, inliers: np.ndarray, iterations: int) -> PoseEstimate:
    """A non-ok estimate (`status` a `Status`, stored as its plain string): NaN pose and
    covariances."""
    return PoseEstimate(str(status), np.full(3, np.nan), np.full(4, np.nan),
                        np.full((6, 6), np.nan), np.full((3, 3), np.nan), iterations, inliers)


def inverse_if_well_conditioned(h: np.ndarray, max_condition: float = MAX_CONDITION
                                ) -> np.ndarray | None:
    """Inverse of a symmetric positive definite normal matrix, or None when its Jacobi-scaled
    condition number exceeds `max_condition` (or it is singular or not finite)."""
    inverse, _ = scaled_inverse(h, max_condition)
    return inverse


def scaled_inverse(h: np.ndarray, max_condition: float = MAX_CONDITION, *,
                   direct: bool = False) -> tuple[np.ndarray | None, tuple[float, float]]:
    """`inverse_if_well_conditioned` and the smallest and largest eigenvalue of h Jacobi-scaled
    (unit diagonal; NaN when h is not finite or its diagonal not positive), from one symmetric
    eigendecomposition: numpy's (the estimates' arithmetic), or with `direct` LAPACK's dsyevd
    called through scipy without numpy's wrapper (for decisions: equal to rounding)."""
    diag = h.diagonal()
    if not (np.isfinite(h).all() and (diag > 0).all()):
        return None, (math.nan, math.nan)
    s = 1.0 / np.sqrt(diag)
    outer = s[:, None] * s[None, :]
    if direct:
        ev, vec, info = lapack.dsyevd(h * outer)
        if info != 0:
            return None, (math.nan, math.nan)
    else:
        ev, vec = np.linalg.eigh(h * outer)
    extremes = (float(ev[0]), float(ev[-1]))
    if not ev[0] > ev[-1] / max_condition:
        return None, extremes
    return (vec / ev) @ vec.T * outer, extremes


def scaled_condition(h: np.ndarray) -> float:
    """The condition number of a symmetric matrix h Jacobi-scaled (unit diagonal), from its
    eigenvalues (LAPACK dsyevd, called directly); inf when h is not finite, its diagonal not
    positive or the scaled matrix not positive definite."""
    d = h.diagonal()
    if not (np.isfinite(h).all() and (d > 0).all()):
        return math.inf
    s = 1.0 / np.sqrt(d)
    ev, _, info = lapack.dsyevd(h * (s[:, None] * s[None, :]), compute_v=0)
    return float(ev[-1] / ev[0]) if info == 0 and ev[0] > 0 else math.inf
