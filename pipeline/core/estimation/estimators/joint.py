"""Joint maximum likelihood pose from ranges and bearings, or bearings alone: Gauss-Newton on
(dr, dtheta) of the whitened residuals of `measurement` (Eq. 10-11), started from the paper's
estimate when at least 3 craters have ranges, else from the prior or a P3P pose (`bearings`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import ClassVar

import numpy as np

from pipeline.core.estimation.estimators.base import (
    EPS,
    ROUNDING_FACTOR,
    Estimator,
    FitSystem,
    PoseEstimate,
    failed,
    scaled_inverse,
    select_rows,
)
from pipeline.core.estimation.estimators.bearings import bearings_candidates, planar_pose
from pipeline.core.estimation.estimators.paper import PaperEstimator
from pipeline.core.estimation.estimators.quest import quest
from pipeline.core.estimation.estimators.safeguarded import refine as safeguarded_refine
from pipeline.core.estimation.measurement import (
    frame,
    line_of_sight,
    measurement_count,
    per_crater,
    rounding_level,
    squared_normalised_residuals,
    whitened_system_from_los,
)
from pipeline.core.math import chi_square
from pipeline.core.math.rotations import (
    dcm_from_q,
    positive_scalar,
    q_exp,
    q_from_dcm,
    q_multiply,
)
from pipeline.core.scoring.status import Status

# Cold start without the paper's estimate (`JointEstimator._cold`): P3P candidates refined at
# most; measurement count up to which other minima are searched (4 craters with bearings only);
# the chi-square tail bounding the candidates worth refining there; and the cost difference
# (2 ln 1000: a likelihood ratio under 1000) within which two distinct minima are ambiguous.
MAX_STARTS = 8
PRIOR_MARGIN = 3.0  # 3 craters without ranges: the prior must be this much nearer one pose
RIVAL_SEARCH_MEASUREMENTS = 8
RIVAL_CHECK_MEASUREMENTS = 9  # 3 craters with ranges: is the fit from the paper's start unique?
AMBIGUITY_TAIL = 1e-6
AMBIGUITY_COST = 2.0 * math.log(1000.0)


@dataclass(frozen=True)
class JointEstimator(Estimator):
    """Minimises sum (rho_j - h_rho,j)^2 / sigma_range_j^2 + |u_j - h_b,j|^2 / sigma_bearing_j^2
    (range terms only for the craters with a range) by Gauss-Newton on (dr, dtheta),
    R <- R Exp(dtheta) (`refine`), from:
    - the paper's estimate when at least 3 used craters have a range (always so in the paper's
      scenario); with some ranges missing and the paper's estimate failing, as without ranges:
    - without ranges (fewer than 3): the prior when finite (warm start: QUEST attitude with
      references from the prior position), and when that fit fails, a cold start from P3P
      poses (`bearings`; `_cold`): every pose the craters allow is found, then refined in
      order of cost. Three craters without ranges fit up to 4 poses exactly: `ambiguous`
      unless a prior is PRIOR_MARGIN times nearer one of them than any other; and with 4
      craters two distinct minima can fit about equally well (~2 % of nadir frames; cold,
      `ambiguous` too).
    These starts use the safeguarded Gauss-Newton (`refine(..., safeguarded=True)`).
    `cov` = (sum J^T J)^-1 at the solution (the inverse Fisher information there);
    `att_cov_quest` NaN; `iterations` the joint's own (of the fit returned)."""

    method: ClassVar[str] = "joint"

    def fit(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray, use: np.ndarray,
            r_prior_mci_m: np.ndarray | None) -> PoseEstimate:
        if use.sum() < 3:
            return failed(Status.TOO_FEW_CRATERS, use, 0)
        ranged = int(np.count_nonzero(use & ~np.isnan(rho_m)))
        if ranged >= 3:
            initial = PaperEstimator(self.options).fit(c_mci_m, u_body, rho_m, use,
                                                       r_prior_mci_m)
            if initial.status == Status.OK or ranged == use.sum():
                est = self.refine(c_mci_m, u_body, rho_m, use, initial)
                if (est.status == Status.OK
                        and measurement_count(rho_m[use]) <= RIVAL_CHECK_MEASUREMENTS
                        and self._has_rival(c_mci_m, u_body, rho_m, use, est)):
                    return failed(Status.AMBIGUOUS, use, est.iterations)
                return est
        return self._from_bearings(c_mci_m, u_body, rho_m, use, r_prior_mci_m)

    def _has_rival(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
                   use: np.ndarray, est: PoseEstimate) -> bool:
        """Whether a distinct minimum fits within AMBIGUITY_COST of `est` (3 craters with
        ranges: the P3P poses the bearings allow, refined, may fit as well when the ranges are
        coarse, e.g. from the craters' apparent sizes)."""
        o = self.options
        cs, us, rs = c_mci_m[use], u_body[use], rho_m[use]
        sigma_b, sigma_r = per_crater(o.sigma_bearing, use), per_crater(o.sigma_range_m, use)
        best = float(np.sum(squared_normalised_residuals(
            est.r_mci_m, est.q_mci_from_body, cs, us, rs, sigma_bearing=sigma_b,
            sigma_range_m=sigma_r)))
        costs, r0, dcm0 = bearings_candidates(cs, us, rs, sigma_b, sigma_r)
        bound = best + _chi2_isf(AMBIGUITY_TAIL, measurement_count(rs))
        for i in range(min(costs.size, MAX_STARTS)):
            if costs[i] > bound:
                break
            rival = self.refine(c_mci_m, u_body, rho_m, use,
                                _start(r0[i], q_from_dcm(dcm0[i]), use), safeguarded=True)
            if rival.status != Status.OK or _same_minimum(rival, est):
                continue
            cost = float(np.sum(squared_normalised_residuals(
                rival.r_mci_m, rival.q_mci_from_body, cs, us, rs, sigma_bearing=sigma_b,
                sigma_range_m=sigma_r)))
            if cost - best < AMBIGUITY_COST:
                return True
        return False

    def _from_bearings(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
                       use: np.ndarray, r_prior_mci_m: np.ndarray | None) -> PoseEstimate:
        """The fit started without the paper's estimate: warm from the prior, else cold. With
        exactly 6 measurements (3 craters, no range) the prior selects among the exact P3P
        poses, and only when the nearest is PRIOR_MARGIN times nearer than the next."""
        if r_prior_mci_m is None or not bool(np.all(np.isfinite(r_prior_mci_m))):
            return self._cold(c_mci_m, u_body, rho_m, use)
        prior = np.asarray(r_prior_mci_m, dtype=float)
        cs, us, rs = c_mci_m[use], u_body[use], rho_m[use]
        sigma_b = per_crater(self.options.sigma_bearing, use)
        if measurement_count(rs) <= 6:
            _, r0, dcm0 = bearings_candidates(cs, us, rs, sigma_b,
                                              per_crater(self.options.sigma_range_m, use))
            if r0.shape[0] == 0:
                return failed(Status.DEGENERATE, use, 0)
            dist = np.linalg.norm(r0 - prior, axis=1)
            order = np.argsort(dist)
            nearest = int(order[0])
            if dist.size > 1 and dist[order[1]] < PRIOR_MARGIN * dist[nearest]:
                return failed(Status.AMBIGUOUS, use, 0)
            return self.refine(c_mci_m, u_body, rho_m, use,
                               _start(r0[nearest], q_from_dcm(dcm0[nearest]), use),
                               safeguarded=True)
        ref, _ = line_of_sight(prior, cs)
        q, _ = quest(us, ref, np.broadcast_to(np.asarray(sigma_b, dtype=float) ** -2.0,
                                              (rs.size,)))
        if np.all(np.isfinite(q)):
            est = self.refine(c_mci_m, u_body, rho_m, use, _start(prior, q, use),
                              safeguarded=True)
            if est.status == Status.OK:
                return est
        return self._cold(c_mci_m, u_body, rho_m, use)

    def _cold(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
              use: np.ndarray) -> PoseEstimate:
        """The cold start: with 5 craters or more (more than RIVAL_SEARCH_MEASUREMENTS), first
        from the craters' plane (`bearings.planar_pose`), kept when it converges to a cost
        within the chi-square bound of all measurements (AMBIGUITY_TAIL); else from P3P
        candidates (`bearings.bearings_candidates`), lowest cost first. The first is refined,
        and the next ones while no fit has succeeded (at most MAX_STARTS). With few
        measurements (at most RIVAL_SEARCH_MEASUREMENTS: 4 craters without
        ranges) every candidate whose cost is below the chi-square bound of all measurements
        (AMBIGUITY_TAIL) is refined too, and the fit with the lowest cost is kept, unless a
        distinct minimum comes within AMBIGUITY_COST of it: `ambiguous`. Three craters without
        ranges (6 measurements for 6 unknowns) are `ambiguous` outright."""
        o = self.options
        cs, us, rs = select_rows(use, c_mci_m, u_body, rho_m)
        measurements = measurement_count(rs)
        search = measurements <= RIVAL_SEARCH_MEASUREMENTS
        bound = _chi2_isf(AMBIGUITY_TAIL, measurements)
        if not search:  # 5 craters or more: the plane's closed form first
            start = planar_pose(cs, us)
            if start is not None:
                est = self.refine(c_mci_m, u_body, rho_m, use, _start(*start, use),
                                  safeguarded=True)
                if est.status == Status.OK and est.system is not None \
                        and est.system.cost <= bound:
                    return est
        sigma_b, sigma_r = per_crater(o.sigma_bearing, use), per_crater(o.sigma_range_m, use)
        costs, r0, dcm0 = bearings_candidates(cs, us, rs, sigma_b, sigma_r)
        if costs.size == 0:
            return failed(Status.DEGENERATE, use, 0)
        if measurements <= 6:
            return failed(Status.AMBIGUOUS, use, 0)
        fits: list[tuple[float, PoseEstimate]] = []
        first_failure: PoseEstimate | None = None
        for i in range(min(costs.size, MAX_STARTS)):
            if fits and not (search and costs[i] <= bound):
                break
            est = self.refine(c_mci_m, u_body, rho_m, use,
                              _start(r0[i], q_from_dcm(dcm0[i]), use), safeguarded=True)
            if est.status != Status.OK:
                first_failure = first_failure or est
                continue
            if not search:
                return est
            cost = float(np.sum(squared_normalised_residuals(
                est.r_mci_m, est.q_mci_from_body, cs, us, rs, sigma_bearing=sigma_b,
                sigma_range_m=sigma_r)))
            if not any(_same_minimum(est, other) for _, other in fits):
                fits.append((cost, est))
        if not fits:
            return first_failure if first_failure is not None else failed(
                Status.DEGENERATE, use, 0)
        fits.sort(key=lambda f: f[0])
        best_cost, best = fits[0]
        if any(cost - best_cost < AMBIGUITY_COST for cost, _ in fits[1:]):
            return failed(Status.AMBIGUOUS, use, best.iterations)
        return best

    def refine(self, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
               use: np.ndarray, initial: PoseEstimate, *, safeguarded: bool = False
               ) -> PoseEstimate:
        """Gauss-Newton over the rows `use` from `initial`; a non-ok `initial` gives its status
        (iterations 0). Stops when the position step is at most `step_tol_m` (m) and the attitude
        step moves no predicted crater by more than that (or both are at their rounding floor).
        The estimate carries its last system (`FitSystem`) for the checks.

        `safeguarded` (for starts that may be far from the minimum: P3P, the craters' plane or
        a prior, not the paper's estimate): `safeguarded.refine`, with a line search and a stop
        on the step in its own standard deviations. Without it the iteration is exactly the
        original one, on the whitened Jacobian (the paper's scenario keeps its bits)."""
        o = self.options
        if initial.status != Status.OK:
            return failed(initial.status, use, 0)
        cs, us, rs = select_rows(use, c_mci_m, u_body, rho_m)
        sigma_b, sigma_r = per_crater(o.sigma_bearing, use), per_crater(o.sigma_range_m, use)
        f = frame(cs, us, rs, sigma_b, sigma_r)
        if safeguarded:
            return safeguarded_refine(f, use, initial.r_mci_m, initial.q_mci_from_body,
                                      step_tol_m=o.step_tol_m, max_iterations=o.max_iterations)
        # the paper's scenario (one sigma each, every range) keeps its original arithmetic
        simple = np.ndim(sigma_b) == 0 and np.ndim(sigma_r) == 0 and not np.isnan(rs).any()
        x = initial.r_mci_m.copy()
        q = initial.q_mci_from_body
        missing = np.isnan(rs)
        missing_rows = missing if missing.any() else None
        for k in range(1, o.max_iterations + 1):
            w, rng_m = line_of_sight(x, cs)
            e, jac, u_pred = whitened_system_from_los(w, rng_m, dcm_from_q(q), us, rs, sigma_b,
                                                      sigma_r, missing_rows)
            jac_rows = jac.reshape(-1, 6)
            h = jac_rows.T @ jac_rows
            try:
                h_inv = np.linalg.inv(h)
            except np.linalg.LinAlgError:
                return failed(Status.DEGENERATE, use, k)
            gradient = jac_rows.T @ e.reshape(-1)
            step = h_inv @ gradient
            s0, s1, s2, s3, s4, s5 = step.tolist()
            dx2, dth2 = s0 * s0 + s1 * s1 + s2 * s2, s3 * s3 + s4 * s4 + s5 * s5
            if not math.isfinite(dx2 + dth2):
                return failed(Status.DEGENERATE, use, k)
            x_full = x + step[:3]
            q_full = q_multiply(q, q_exp(step[3:]))
            q_full /= math.sqrt(float(q_full @ q_full))
            dx, dth = math.sqrt(dx2), math.sqrt(dth2)
            # whitened rounding level of the residuals, propagated to each block of the step
            rho_max = float(rng_m.max())
            if simple:
                level = max(rho_max / o.sigma_range_m, 1.0 / o.sigma_bearing)
            else:
                level = rounding_level(f, rng_m)
            noise = ROUNDING_FACTOR * EPS * level
            d0, d1, d2, d3, d4, d5 = h_inv.diagonal().tolist()
            if (dx <= max(o.step_tol_m, noise * math.sqrt(abs(d0) + abs(d1) + abs(d2)))
                    and dth <= max(o.step_tol_m / rho_max,
                                   noise * math.sqrt(abs(d3) + abs(d4) + abs(d5)))):
                cov, (low, high) = scaled_inverse(h)
                if cov is None:
                    return failed(Status.DEGENERATE, use, k)
                flat = e.reshape(-1)
                shs = float(gradient @ step)  # step^T h step
                fit = FitSystem(h, high / low, float(flat @ flat) - shs, shs, rng_m,
                                np.einsum("ij,ij->i", u_pred, us))
                return PoseEstimate(Status.OK.value, x_full, positive_scalar(q_full), cov,
                                    np.full((3, 3), np.nan), k, use, fit)
            x, q = x_full, q_full
        return failed(Status.NOT_CONVERGED, use, o.max_iterations)


@cache
def _chi2_isf(tail: float, dof: int) -> float:
    return float(chi_square.upper_quantile(tail, dof))


def _same_minimum(a: PoseEstimate, b: PoseEstimate) -> bool:
    """Whether two converged fits are the same minimum: positions within one standard deviation
    of each other (under either's position covariance); distinct minima are many apart."""
    d = a.r_mci_m - b.r_mci_m
    return min(float(d @ np.linalg.solve(a.cov[:3, :3], d)),
               float(d @ np.linalg.solve(b.cov[:3, :3], d))) <= 1.0


_NO_COV, _NO_ATT_COV = np.full((6, 6), np.nan), np.full((3, 3), np.nan)
_NO_COV.flags.writeable = _NO_ATT_COV.flags.writeable = False


def _start(r_mci_m: np.ndarray, q_mci_from_body: np.ndarray, use: np.ndarray) -> PoseEstimate:
    """An initial pose for `JointEstimator.refine` (no covariance)."""
    return PoseEstimate(Status.OK.value, np.array(r_mci_m, dtype=float),
                        np.asarray(q_mci_from_body, dtype=float), _NO_COV, _NO_ATT_COV, 0, use)
