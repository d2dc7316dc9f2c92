"""The paper's method (Sec. 4): range Gauss-Newton for the position (Eq. 12-14), then QUEST with
references built from that position, and the full covariance with the position error carried
into the attitude."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.core.estimation.estimators.base import Estimator, PoseEstimate, failed, select_rows
from pipeline.core.estimation.estimators.position import closed_form_position, gauss_newton_position
from pipeline.core.estimation.estimators.quest import quest, quest_position_sensitivity
from pipeline.core.estimation.measurement import line_of_sight, per_crater
from pipeline.core.scoring.status import Status


@dataclass(frozen=True)
class PaperEstimator(Estimator):
    """Position: range Gauss-Newton from the prior (the previous successful estimate) or, when
    None or not finite (a failed frame's NaN), from `closed_form_position`, on the craters with a
    range (at least 3, else `needs_ranges`; weights 1/sigma_range^2 when they differ). Attitude:
    QUEST on every used crater's bearing with r_ref_j = unit(c_j - r_est) and weights
    1/sigma_bearing^2 (equal for one number, per crater for an array). `cov`: the Gauss-Newton
    position block; attitude block QUEST's covariance plus G P_rr G^T, with the cross terms
    G P_rr, where G = d dtheta / d r (`quest_position_sensitivity`): the attitude error the
    position error induces through the references (bearing and range noise are independent).
    `att_cov_quest`: QUEST's own covariance."""

    method: ClassVar[str] = "paper"

    def fit(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, use: np.ndarray,
            r_prior_mci_m: np.ndarray | None) -> PoseEstimate:
        o = self.options
        n_use = int(np.count_nonzero(use))
        if n_use < 3:
            return failed(Status.TOO_FEW_CRATERS, use, 0)
        has_range = ~np.isnan(rho_m)
        ranged = use & has_range
        n_ranged = n_use if n_use == use.size and has_range.all() else int(
            np.count_nonzero(ranged))
        if n_ranged < 3:
            return failed(Status.NEEDS_RANGES, use, 0)
        cs, us, rs = select_rows(use, c_mci_m, u_body, rho_m)
        cr, rr, ur = (cs, rs, us) if n_ranged == n_use else select_rows(
            ranged, c_mci_m, rho_m, u_body)
        warm = r_prior_mci_m is not None and bool(np.all(np.isfinite(r_prior_mci_m)))
        r0 = r_prior_mci_m if warm else closed_form_position(cr, rr, ur)
        if r0 is None:
            return failed(Status.DEGENERATE, use, 0)
        x, cov_x, its, status = gauss_newton_position(
            cr, rr, r0, o.step_tol_m, o.max_iterations,
            sigma_range_m=per_crater(o.sigma_range_m, ranged))
        if status != Status.OK:
            return failed(status, use, its)
        los = line_of_sight(x, cs)
        sigma_b = per_crater(o.sigma_bearing, use)
        weights = np.full(rs.size, sigma_b**-2) if np.ndim(sigma_b) == 0 else sigma_b**-2.0
        q, att_cov = quest(us, los[0], weights)
        if math.isnan(att_cov[0, 0]):  # QUEST's covariance is all finite or all NaN
            return failed(Status.DEGENERATE, use, its)
        g = quest_position_sensitivity(q, att_cov, x, cs, weights, los)
        cov = np.empty((6, 6))
        cov[:3, :3] = cov_x
        cov[3:, :3] = g @ cov_x
        cov[:3, 3:] = cov[3:, :3].T
        cov[3:, 3:] = att_cov + g @ cov_x @ g.T
        return PoseEstimate(Status.OK.value, x, q, cov, att_cov, its, use)
