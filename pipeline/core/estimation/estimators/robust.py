"""Robust estimation against false matches: RANSAC over minimal 3-crater poses (absolute
orientation when every crater has a range, else P3P on the bearings, `bearings.p3p`) scored by
MSAC, then the method refitted until the craters passing a chi-square gate on their normalised
residuals (`measurement`: 3 dof per crater with a range, 2 without) are stable. Noise one number
or one value per row of the frame (`measurement.Sigma`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from pipeline.core.estimation.estimators.base import Estimator, PoseEstimate, failed
from pipeline.core.estimation.estimators.bearings import absolute_orientation, crater_costs, p3p
from pipeline.core.estimation.measurement import Sigma, per_crater, squared_normalised_residuals
from pipeline.core.math import chi_square
from pipeline.core.scoring.status import Status

# RANSAC's consensus gate is the final chi-square gate widened by this factor in sigma: a 3-crater
# pose predicts the other craters several sigma off, while a false match is kilometres off.
RANSAC_LOOSE_FACTOR = 10.0
RANSAC_BATCH = 8  # hypotheses scored per vectorised batch
MAX_GATE_ITERATIONS = 10  # robust refit-and-gate passes
# A consensus whose bearings all lie within this angle of their mean direction is
# `ill_conditioned`: a few craters within a small cone fit a wrong pose as well as the true one
# (false matches agreeing by chance, 0.3-3 km off at ~0.1 deg), whatever its covariance says;
# 0.5 deg is ~1/90 of the 45 deg field of view.
MIN_CONSENSUS_SPREAD_RAD = np.radians(0.5)


@dataclass(frozen=True)
class RobustOptions:
    """RANSAC over minimal 3-crater poses, then refit and chi-square gate (3 dof per crater, 2
    for a crater without a range)."""

    gate_probability: float  # chi-square gate on each crater's normalised residual
    max_hypotheses: int  # cap on the RANSAC hypotheses
    confidence: float  # probability of drawing at least one all-inlier sample


@cache
def _chi2_gate(probability: float, dof: int = 3) -> float:
    """Chi-square quantile with `dof` (1 range + 2 bearing tangent; 2 without a range) at
    `probability`."""
    return float(chi_square.quantile(probability, dof))


def chi2_gates(probability: float, rho_m: np.ndarray) -> float | np.ndarray:
    """The chi-square gate of each crater with ranges `rho_m` (n,) (NaN: none): one number when
    every crater has a range, else (n,)."""
    missing = np.isnan(rho_m)
    if not missing.any():
        return _chi2_gate(probability)
    return np.where(missing, _chi2_gate(probability, 2), _chi2_gate(probability))


def _sample_triples(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """(k, 3) uniformly drawn triples of distinct indices in [0, n), n >= 3."""
    i = rng.integers(0, n, k)
    j = rng.integers(0, n - 1, k)
    j += j >= i
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    m = rng.integers(0, n - 2, k)
    m += m >= lo
    m += m >= hi
    return np.stack([i, j, m], axis=1)


def _hypotheses_needed(inlier_share: float, opts: RobustOptions) -> int:
    """Hypotheses for `confidence` of one all-inlier triple at this inlier share (capped)."""
    miss = 1.0 - inlier_share**3
    if miss <= 0.0:
        return 1
    if miss >= 1.0:
        return opts.max_hypotheses
    return min(opts.max_hypotheses, math.ceil(math.log(1.0 - opts.confidence) / math.log(miss)))


def _ransac(c: np.ndarray, u: np.ndarray, rho: np.ndarray, valid: np.ndarray,
            sigma_bearing: Sigma, sigma_range_m: Sigma, opts: RobustOptions,
            rng: np.random.Generator, loose_gate: float | np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Consensus mask (n,) and position (3,) of the best minimal-set hypothesis (MSAC cost with
    the loose gate, one number or one per valid row); adaptive hypothesis count from the best
    inlier share and `confidence`. Noise: a number or one value per valid row."""
    idx = np.flatnonzero(valid)
    cv = c[idx]
    bearings_only = bool(np.isnan(rho[idx]).any())
    if not bearings_only:
        p = u[idx] * rho[idx, None]  # body-frame relative vectors R^T (c_j - r)
        tangent_var = (rho[idx] * sigma_bearing) ** 2
    needed, drawn = opts.max_hypotheses, 0
    # no hypothesis with a finite cost: an empty consensus (too_few_craters)
    best_cost, best_s, best_x = np.inf, np.full(idx.size, np.inf), np.full(3, np.nan)
    while drawn < min(needed, opts.max_hypotheses):
        k = min(RANSAC_BATCH, opts.max_hypotheses - drawn)
        sample = _sample_triples(rng, idx.size, k)
        if bearings_only:  # up to 4 P3P poses per triple, scored on bearings and any ranges
            dcm4, x4 = p3p(u[idx][sample], cv[sample])
            x = x4.reshape(-1, 3)
            s = crater_costs(x, dcm4.reshape(-1, 3, 3), cv, u[idx], rho[idx], sigma_bearing,
                             sigma_range_m)
        else:
            dcm, x = absolute_orientation(p[sample], cv[sample])
            los = np.einsum("kab,mb->kma", dcm, u[idx])  # measured lines of sight, MCI
            resid = cv[None] - x[:, None, :] - los * rho[idx, None]  # (k, m, 3) metres
            along2 = np.einsum("kma,kma->km", resid, los) ** 2
            s = along2 / sigma_range_m**2 + (np.einsum("kma,kma->km", resid, resid) - along2) \
                / tangent_var
        cost = np.minimum(s, loose_gate).sum(axis=1)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best_s, best_x = cost[j], s[j], x[j]
            needed = _hypotheses_needed(float(np.mean(best_s < loose_gate)), opts)
        drawn += k
    consensus = np.zeros(valid.size, dtype=bool)
    consensus[idx[best_s < loose_gate]] = True
    return consensus, best_x


def robust_fit(estimator: Estimator, c_mci_m: np.ndarray, u_body: np.ndarray, rho_m: np.ndarray,
               valid: np.ndarray, opts: RobustOptions, rng: np.random.Generator) -> PoseEstimate:
    """`estimator` on the rows of `valid` with false matches removed: RANSAC consensus (loose
    gate RANSAC_LOOSE_FACTOR), then fits warm-started at the best hypothesis and refitted until
    the set of craters passing the chi-square gate (`gate_probability`, 3 dof, 2 without a
    range) under the fit is stable (at most MAX_GATE_ITERATIONS fits; the estimate returned is
    the last fit, its `inliers` the rows it used). Random draws come from `rng` only. The
    estimator's noise is a number or one value per row of the frame."""
    c, u, rho = c_mci_m, u_body, rho_m
    if valid.sum() < 3:
        return failed(Status.TOO_FEW_CRATERS, valid, 0)
    o = estimator.options
    gate = chi2_gates(opts.gate_probability, rho[valid])
    sigma_b, sigma_r = per_crater(o.sigma_bearing, valid), per_crater(o.sigma_range_m, valid)
    use, prior = _ransac(c, u, rho, valid, sigma_b, sigma_r, opts, rng,
                         gate * RANSAC_LOOSE_FACTOR**2)
    est = failed(Status.TOO_FEW_CRATERS, use, 0)
    for _ in range(MAX_GATE_ITERATIONS):
        if use.sum() < 3:
            return failed(Status.TOO_FEW_CRATERS, use, 0)
        est = estimator.fit(c, u, rho, use, prior)
        if est.status != Status.OK:
            return est
        kept = np.zeros(valid.size, dtype=bool)
        kept[valid] = squared_normalised_residuals(
            est.r_mci_m, est.q_mci_from_body, c[valid], u[valid], rho[valid],
            sigma_bearing=sigma_b, sigma_range_m=sigma_r) <= gate
        if np.array_equal(kept, use):
            return _spread(est, u)
        use, prior = kept, est.r_mci_m
    return _spread(est, u)


def _spread(est: PoseEstimate, u: np.ndarray) -> PoseEstimate:
    """`est`, or `ill_conditioned` when the bearings (n, 3) of its inliers lie within
    MIN_CONSENSUS_SPREAD_RAD of their mean direction."""
    if est.status != Status.OK:
        return est
    b = u[est.inliers]
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    mean = b.sum(axis=0)
    mean /= np.linalg.norm(mean)
    if float(np.arccos(np.clip((b @ mean).min(), -1.0, 1.0))) < MIN_CONSENSUS_SPREAD_RAD:
        return failed(Status.ILL_CONDITIONED, est.inliers, est.iterations)
    return est
