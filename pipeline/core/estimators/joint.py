"""Joint maximum likelihood pose from ranges and bearings: Gauss-Newton on (dr, dtheta) of the
whitened residuals of `measurement` (Eq. 10-11), started from the paper's estimate."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.estimators.base import (
    EPS,
    ROUNDING_FACTOR,
    Estimator,
    PoseEstimate,
    failed,
    inverse_if_well_conditioned,
)
from pipeline.core.estimators.paper import PaperEstimator
from pipeline.core.measurement import whitened_system
from pipeline.core.rotations import positive_scalar, q_exp, q_multiply
from pipeline.core.status import Status


@dataclass(frozen=True)
class JointEstimator(Estimator):
    """Minimises sum (rho_j - h_rho,j)^2 / sigma_range^2 + |u_j - h_b,j|^2 / sigma_bearing^2 by
    Gauss-Newton on (dr, dtheta), R <- R Exp(dtheta), from the paper's estimate (`refine`).
    `cov` = (sum J^T J)^-1 at the solution (the inverse Fisher information there);
    `att_cov_quest` NaN; `iterations` the joint's own."""

    method: ClassVar[str] = "joint"

    def fit(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, use: np.ndarray,
            r_prior_mci_m: np.ndarray | None) -> PoseEstimate:
        initial = PaperEstimator(self.options).fit(c_mci_m, u_body, rho_m, use, r_prior_mci_m)
        return self.refine(c_mci_m, u_body, rho_m, use, initial)

    def refine(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
               use: np.ndarray, initial: PoseEstimate) -> PoseEstimate:
        """Gauss-Newton over the rows `use` from `initial`; a non-ok `initial` gives its status
        (iterations 0). Stops when the position step is at most `step_tol_m` (m) and the attitude
        step moves no predicted crater by more than that (or both are at their rounding floor)."""
        o = self.options
        if initial.status != Status.OK:
            return failed(initial.status, use, 0)
        cs, us, rs = c_mci_m[use], u_body[use], rho_m[use]
        x = initial.r_mci_m.copy()
        q = initial.q_mci_from_body
        for k in range(1, o.max_iterations + 1):
            e, jac, rng_m = whitened_system(x, q, cs, us, rs, sigma_bearing=o.sigma_bearing,
                                            sigma_range_m=o.sigma_range_m)
            jac_rows = jac.reshape(-1, 6)
            h = jac_rows.T @ jac_rows
            try:
                h_inv = np.linalg.inv(h)
            except np.linalg.LinAlgError:
                return failed(Status.DEGENERATE, use, k)
            step = h_inv @ (jac_rows.T @ e.reshape(-1))
            if not np.all(np.isfinite(step)):
                return failed(Status.DEGENERATE, use, k)
            x += step[:3]
            q = q_multiply(q, q_exp(step[3:]))
            q /= math.sqrt(float(q @ q))
            dx, dth = math.sqrt(float(step[:3] @ step[:3])), math.sqrt(float(step[3:] @ step[3:]))
            # whitened rounding level of the residuals, propagated to each block of the step
            rho_max = float(rng_m.max())
            noise = ROUNDING_FACTOR * EPS * max(rho_max / o.sigma_range_m, 1.0 / o.sigma_bearing)
            diag = np.abs(np.diag(h_inv))
            if (dx <= max(o.step_tol_m, noise * math.sqrt(diag[:3].sum()))
                    and dth <= max(o.step_tol_m / rho_max, noise * math.sqrt(diag[3:].sum()))):
                cov = inverse_if_well_conditioned(h)
                if cov is None:
                    return failed(Status.DEGENERATE, use, k)
                return PoseEstimate(Status.OK.value, x, positive_scalar(q), cov,
                                    np.full((3, 3), np.nan), k, use)
        return failed(Status.NOT_CONVERGED, use, o.max_iterations)
