"""Craters seen by their bearings alone (a NaN range): P3P, the joint ML without ranges (exact,
efficient, honest covariance, ambiguity reported), mixed ranges, the paper's method asking for
ranges, the Fisher information and checks counting only the measurements present, and RANSAC
without ranges.

Geometry of the default scenario: a nadir camera 10-250 km above a random point of the
1737.4 km sphere, a square 45 deg field of view, craters where rays through random image points
meet the sphere; bearing noise 1e-4 rad per component, range noise 10 m.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from pipeline.core.estimation import estimators as est
from pipeline.core.estimation import measurement
from pipeline.core.estimation.estimators import bearings
from pipeline.core.estimation.estimators.base import prepare
from pipeline.core.math import frames
from pipeline.core.math.constants import MOON_RADIUS_M

SIGMA_B = 1e-4
SIGMA_R = 10.0
TAN_EDGE = np.tan(np.radians(22.5))
ROBUST = est.RobustOptions(gate_probability=0.9999, max_hypotheses=64, confidence=0.999)


def make_frame(rng: np.random.Generator, n: int, alt_km: tuple[float, float] = (10.0, 250.0)
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True position r (3,), dcm_mci_from_body (3, 3) (nadir, random heading), craters (n, 3)."""
    up = rng.standard_normal(3)
    up /= np.linalg.norm(up)
    r = (MOON_RADIUS_M + 1e3 * rng.uniform(*alt_km)) * up
    dcm = frames.dcm_mci_from_orbit(r, np.cross(up, rng.standard_normal(3)))
    rays = np.concatenate([rng.uniform(-TAN_EDGE, TAN_EDGE, (n, 2)), np.ones((n, 1))], axis=1)
    rays = (rays / np.linalg.norm(rays, axis=1, keepdims=True)) @ dcm.T
    od = rays @ r
    t = -od - np.sqrt(od**2 - (r @ r - MOON_RADIUS_M**2))
    return r, dcm, r + t[:, None] * rays


def observe(rng: np.random.Generator | None, r, dcm, c) -> tuple[np.ndarray, np.ndarray]:
    """Bearings (n, 3) and ranges (n,); noiseless when rng is None."""
    u, rho = measurement.true_bearings(c, r, dcm.T)
    return (u, rho) if rng is None else measurement.measure(rng, u, rho, SIGMA_B, SIGMA_R)


def no_ranges(n: int) -> np.ndarray:
    return np.full(n, np.nan)


def pose(method, c, u, rho, **kw) -> est.PoseEstimate:
    return est.estimate_pose(method, c, u, rho, sigma_bearing=SIGMA_B, sigma_range_m=SIGMA_R,
                             **kw)


def att_error(dcm_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    return (Rotation.from_matrix(dcm_true).inv() * Rotation.from_quat(q_est)).as_rotvec()


def pose_error(r, dcm, e: est.PoseEstimate) -> np.ndarray:
    return np.r_[e.r_mci_m - r, att_error(dcm, e.q_mci_from_body)]


def mean_nees_bounds(n_trials: int, dof: int) -> tuple[float, float]:
    """99 % two-sided bounds of the mean of n_trials chi2(dof) variables."""
    lo, hi = chi2.ppf([0.005, 0.995], n_trials * dof)
    return lo / n_trials, hi / n_trials


# --------------------------------------------------------------------------------------------
# P3P

def test_p3p_finds_the_true_pose_among_its_candidates():
    rng = np.random.default_rng(1)
    k = 300
    r_true, dcm_true, u, c = [], [], [], []
    for _ in range(k):
        r, dcm, cc = make_frame(rng, 3)
        uu, _ = observe(None, r, dcm, cc)
        r_true.append(r), dcm_true.append(dcm), u.append(uu), c.append(cc)
    dcm4, r4 = bearings.p3p(np.array(u), np.array(c))
    assert dcm4.shape == (k, 4, 3, 3) and r4.shape == (k, 4, 3)
    err = np.linalg.norm(r4 - np.array(r_true)[:, None], axis=2)
    best = np.nanargmin(err, axis=1)
    rows = np.arange(k)
    # polished roots: ~1e-9 m at 10-250 km; near a double root (the "danger cylinder")
    # the problem itself loses digits
    assert np.median(err[rows, best]) < 1e-8 and err[rows, best].max() < 1e-3
    dcm_err = dcm4[rows, best] - np.array(dcm_true)
    assert np.median(np.abs(dcm_err).max(axis=(1, 2))) < 1e-13
    # most triples have several poses that reproduce their three bearings exactly: the
    # ambiguity of three craters without ranges
    exact = np.zeros(k, dtype=int)
    for i in range(k):
        for j in np.flatnonzero(np.isfinite(r4[i, :, 0])):
            u_pred, _ = measurement.true_bearings(c[i], r4[i, j], dcm4[i, j].T)
            exact[i] += np.abs(u_pred - u[i]).max() < 1e-9
    assert exact.min() >= 1 and np.mean(exact >= 2) > 0.9


def test_p3p_of_a_degenerate_triple_gives_nan_not_an_exception():
    c = np.array([[[x, 0.0, MOON_RADIUS_M] for x in (0.0, 1e3, 2e3)]])  # on one line
    u = np.array([[[0.0, 0.0, 1.0]] * 3])  # one bearing three times
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dcm, r = bearings.p3p(u, c)
    assert np.isnan(r).all() and np.isnan(dcm).all()


# --------------------------------------------------------------------------------------------
# The joint ML from bearings alone

@pytest.mark.parametrize("n", [5, 10, 30, 100])
def test_bearings_only_joint_returns_the_true_pose_from_a_cold_start(n):
    rng = np.random.default_rng(200 + n)
    for _ in range(10):
        r, dcm, c = make_frame(rng, n)
        u, _ = observe(None, r, dcm, c)
        e = pose("joint", c, u, no_ranges(n))
        assert e.status == "ok"
        assert np.linalg.norm(e.r_mci_m - r) < 1e-6
        assert np.linalg.norm(att_error(dcm, e.q_mci_from_body)) < 1e-10
        assert e.inliers.all()  # a NaN range keeps its crater


def test_four_craters_without_ranges_are_exact_or_reported_ambiguous():
    """4 craters without ranges leave 2 redundant measurements: two distinct minima can fit at
    the noise level (a few % of nadir frames): `ambiguous`; every other frame is exact."""
    rng = np.random.default_rng(4)
    statuses = []
    for _ in range(100):
        r, dcm, c = make_frame(rng, 4)
        u, _ = observe(None, r, dcm, c)
        e = pose("joint", c, u, no_ranges(4))
        statuses.append(e.status)
        if e.status == "ok":
            assert np.linalg.norm(e.r_mci_m - r) < 1e-6
    assert set(statuses) <= {"ok", "ambiguous", "ill_conditioned"}
    assert statuses.count("ok") >= 90


def test_three_craters_without_ranges_need_a_prior():
    """Three bearings fit up to 4 poses exactly: cold, `ambiguous`; with a prior (a previous
    estimate ~2 km off) the fit returns the pose nearest to it, the truth, or `ambiguous` when
    another exact pose is almost as near."""
    rng = np.random.default_rng(3)
    statuses = []
    for _ in range(40):
        r, dcm, c = make_frame(rng, 3)
        u, _ = observe(None, r, dcm, c)
        cold = pose("joint", c, u, no_ranges(3))
        assert cold.status == "ambiguous" and np.isnan(cold.r_mci_m).all()
        warm = pose("joint", c, u, no_ranges(3), r_prior_mci_m=r + rng.normal(0.0, 1.2e3, 3))
        statuses.append(warm.status)
        if warm.status == "ok":
            assert np.linalg.norm(warm.r_mci_m - r) < 1e-6
            assert np.linalg.norm(att_error(dcm, warm.q_mci_from_body)) < 1e-9
    assert set(statuses) <= {"ok", "ambiguous", "ill_conditioned"}
    assert statuses.count("ok") >= 25


def test_a_wrong_warm_start_falls_back_to_the_cold_start():
    rng = np.random.default_rng(5)
    r, dcm, c = make_frame(rng, 12)
    u, _ = observe(None, r, dcm, c)
    for prior in (np.zeros(3), -r, np.full(3, np.nan), r + 1e3):
        e = pose("joint", c, u, no_ranges(12), r_prior_mci_m=prior)
        assert e.status == "ok" and np.linalg.norm(e.r_mci_m - r) < 1e-6


def test_bearings_only_joint_matches_scipy_least_squares():
    rng = np.random.default_rng(6)
    for n in (6, 20):
        r, dcm, c = make_frame(rng, n)
        u, _ = observe(rng, r, dcm, c)
        e = pose("joint", c, u, no_ranges(n))
        assert e.status == "ok"
        rot0 = Rotation.from_quat(e.q_mci_from_body)

        def residuals(p, rot0=rot0, c=c, u=u):
            rot = rot0 * Rotation.from_rotvec(p[3:])
            d = c - p[:3]
            pred = rot.inv().apply(d / np.linalg.norm(d, axis=1, keepdims=True))
            return ((u - pred) / SIGMA_B).ravel()  # chordal error: the tangent one to O(sigma^2)

        ref = least_squares(residuals, np.r_[r, 0.0, 0.0, 0.0] + np.r_[500.0, -300.0, 200.0,
                                                                       0, 0, 0],
                            x_scale=np.r_[1e2, 1e2, 1e2, 1e-4, 1e-4, 1e-4], xtol=1e-15,
                            ftol=1e-15, gtol=1e-15)
        sigma = np.sqrt(np.diag(e.cov))
        assert np.all(np.abs(ref.x[:3] - e.r_mci_m) < 1e-3 * sigma[:3])


def test_bearings_only_covariance_is_honest_and_reaches_the_crlb():
    """Mean NEES over many noisy frames ~ 6 with the estimate's own covariance and with the
    bearings-only Cramer-Rao bound at the truth (joint is efficient)."""
    rng = np.random.default_rng(7)
    trials, own, bound = 400, [], []
    for _ in range(trials):
        n = int(rng.integers(8, 40))
        r, dcm, c = make_frame(rng, n)
        u, _ = observe(rng, r, dcm, c)
        e = pose("joint", c, u, no_ranges(n))
        assert e.status == "ok"
        err = pose_error(r, dcm, e)
        crlb = est.crlb(r, Rotation.from_matrix(dcm).as_quat(), c, sigma_bearing=SIGMA_B,
                        sigma_range_m=SIGMA_R, has_range=np.zeros(n, dtype=bool))
        own.append(err @ np.linalg.solve(e.cov, err))
        bound.append(err @ np.linalg.solve(crlb, err))
    lo, hi = mean_nees_bounds(trials, 6)
    assert lo <= np.mean(own) <= hi
    assert lo <= np.mean(bound) <= hi


def test_the_crlb_without_ranges_is_larger_than_with_them():
    rng = np.random.default_rng(8)
    r, dcm, c = make_frame(rng, 25)
    q = Rotation.from_matrix(dcm).as_quat()
    kw = {"sigma_bearing": SIGMA_B, "sigma_range_m": SIGMA_R}
    with_ranges = est.crlb(r, q, c, **kw)
    without = est.crlb(r, q, c, has_range=np.zeros(25, dtype=bool), **kw)
    half = est.crlb(r, q, c, has_range=np.arange(25) % 2 == 0, **kw)
    assert np.all(np.isfinite(without))
    # Loewner order: fewer measurements, a larger bound (positive semi-definite differences)
    for big, small in ((without, half), (half, with_ranges)):
        assert np.linalg.eigvalsh(big - small).min() > -1e-9 * np.abs(big).max()
    assert np.trace(without[:3, :3]) > 10 * np.trace(with_ranges[:3, :3])
    # the information of the bearings alone: range rows zero, the same as an infinite sigma
    fisher = est.fisher_information(r, q, c, has_range=np.zeros(25, dtype=bool), **kw)
    vague = est.fisher_information(r, q, c, sigma_bearing=SIGMA_B, sigma_range_m=1e30)
    np.testing.assert_allclose(fisher, vague, rtol=1e-12, atol=0)
    assert np.array_equal(est.crlb(r, q, c, has_range=np.ones(25, dtype=bool), **kw),
                          with_ranges)


# --------------------------------------------------------------------------------------------
# Mixed ranges, the paper's method, what a NaN range means

def test_a_nan_range_drops_the_range_only():
    c = np.ones((5, 3))
    u = np.tile([0.0, 0.0, 2.0], (5, 1))
    rho = np.array([1.0, np.nan, np.inf, -1.0, 0.0])
    _, u_n, rho_p, valid = prepare(c, u, rho)
    np.testing.assert_array_equal(valid, [True, True, False, False, False])
    assert np.isnan(rho_p[1]) and np.allclose(u_n, [0.0, 0.0, 1.0])
    c[0, 1] = np.nan
    assert not prepare(c, u, rho)[3][0]


def test_mixed_ranges_give_the_joint_ml():
    """Some ranges missing: joint on all craters (3 or more ranges: from the paper's estimate;
    fewer: from P3P) is the minimum of the bearings-and-present-ranges cost (scipy)."""
    rng = np.random.default_rng(9)
    for ranged in (0.1, 0.5, 0.9):
        n = 20
        r, dcm, c = make_frame(rng, n)
        u, rho = observe(rng, r, dcm, c)
        rho = np.where(rng.random(n) < ranged, rho, np.nan)
        e = pose("joint", c, u, rho)
        assert e.status == "ok" and e.inliers.all()
        has = ~np.isnan(rho)
        rot0 = Rotation.from_quat(e.q_mci_from_body)

        def residuals(p, rot0=rot0, c=c, u=u, rho=rho, has=has):
            rot = rot0 * Rotation.from_rotvec(p[3:])
            d = c - p[:3]
            dist = np.linalg.norm(d, axis=1)
            pred = rot.inv().apply(d / dist[:, None])
            return np.r_[((u - pred) / SIGMA_B).ravel(), (rho[has] - dist[has]) / SIGMA_R]

        ref = least_squares(residuals, np.r_[r + 200.0, 0.0, 0.0, 0.0],
                            x_scale=np.r_[1e1, 1e1, 1e1, 1e-5, 1e-5, 1e-5], xtol=1e-15,
                            ftol=1e-15, gtol=1e-15)
        sigma = np.sqrt(np.diag(e.cov))
        assert np.all(np.abs(ref.x[:3] - e.r_mci_m) < 1e-3 * sigma[:3])
        # the covariance is the inverse information of the craters and ranges present
        q = e.q_mci_from_body
        np.testing.assert_allclose(e.cov, est.crlb(e.r_mci_m, q, c, sigma_bearing=SIGMA_B,
                                                   sigma_range_m=SIGMA_R, has_range=has),
                                   rtol=1e-6, atol=1e-20)


def test_mixed_ranges_are_consistent_over_many_frames():
    rng = np.random.default_rng(10)
    trials, nees = 300, []
    for _ in range(trials):
        n = int(rng.integers(6, 30))
        r, dcm, c = make_frame(rng, n)
        u, rho = observe(rng, r, dcm, c)
        rho[rng.random(n) < 0.6] = np.nan
        e = pose("joint", c, u, rho)
        assert e.status == "ok"
        err = pose_error(r, dcm, e)
        nees.append(err @ np.linalg.solve(e.cov, err))
    lo, hi = mean_nees_bounds(trials, 6)
    assert lo <= np.mean(nees) <= hi


def test_the_paper_method_needs_three_ranges():
    rng = np.random.default_rng(11)
    r, dcm, c = make_frame(rng, 10)
    u, rho = observe(None, r, dcm, c)
    rho_few = np.full(10, np.nan)
    rho_few[[2, 7]] = rho[[2, 7]]
    e = pose("paper", c, u, rho_few)
    assert e.status == "needs_ranges" and np.isnan(e.r_mci_m).all() and e.inliers.all()
    assert pose("joint", c, u, rho_few).status == "ok"
    # with 3 ranges the paper's position comes from them, its attitude from all 10 bearings
    rho_three = rho_few.copy()
    rho_three[4] = rho[4]
    e = pose("paper", c, u, rho_three)
    assert e.status == "ok" and np.linalg.norm(e.r_mci_m - r) < 1e-6
    assert np.linalg.norm(att_error(dcm, e.q_mci_from_body)) < 1e-9
    assert pose("paper", c[:2], u[:2], rho[:2]).status == "too_few_craters"


def test_checks_count_two_measurements_per_bearing_and_one_per_range():
    """Bearings 1.4 times noisier than assumed: 2N = 200 measurements give a cost ~ 190 x 1.96
    = 370, far beyond the chi-square(194) test (~ 300 at 1e-6) but inside a chi-square(294)
    one (~ 420): counting 3 per crater would call the frame consistent."""
    rng = np.random.default_rng(12)
    n, flagged = 100, 0
    for _ in range(5):
        r, dcm, c = make_frame(rng, n)
        u, rho = measurement.true_bearings(c, r, dcm.T)
        u, _ = measurement.measure(rng, u, rho, 1.4 * SIGMA_B, SIGMA_R)
        flagged += pose("joint", c, u, no_ranges(n)).status == "inconsistent"
        u_ok, _ = measurement.measure(rng, *measurement.true_bearings(c, r, dcm.T), SIGMA_B,
                                      SIGMA_R)
        assert pose("joint", c, u_ok, no_ranges(n)).status == "ok"
    assert flagged == 5
    assert measurement.measurement_count(np.array([1.0, np.nan, 2.0])) == 8


def test_normalised_residuals_of_a_missing_range_have_two_dof():
    rng = np.random.default_rng(13)
    r, dcm, c = make_frame(rng, 4000)
    q = Rotation.from_matrix(dcm).as_quat()
    u, rho = observe(rng, r, dcm, c)
    rho[::2] = np.nan
    s = measurement.squared_normalised_residuals(r, q, c, u, rho, sigma_bearing=SIGMA_B,
                                                 sigma_range_m=SIGMA_R)
    e, jac, _ = measurement.whitened_system(r, q, c, u, rho, sigma_bearing=SIGMA_B,
                                            sigma_range_m=SIGMA_R)
    assert np.all(e[::2, 0] == 0.0) and np.all(jac[::2, 0] == 0.0)
    np.testing.assert_allclose(s, np.sum(e**2, axis=1), rtol=1e-12)
    for part, dof in ((s[::2], 2), (s[1::2], 3)):
        lo, hi = chi2.ppf([1e-5, 1 - 1e-5], dof * part.size)
        assert lo <= part.sum() <= hi


# --------------------------------------------------------------------------------------------
# RANSAC without ranges

@pytest.mark.parametrize("ranged_share", [0.0, 0.5])
def test_robust_rejects_false_matches_without_ranges(ranged_share):
    """RANSAC on P3P hypotheses when ranges are missing (all, or about half of them)."""
    rng = np.random.default_rng(14)
    for _ in range(10):
        n = 30
        r, dcm, c = make_frame(rng, n, alt_km=(50.0, 200.0))
        u, rho = observe(rng, r, dcm, c)
        rho[rng.random(n) >= ranged_share] = np.nan
        false = rng.choice(n, 6, replace=False)
        c = c.copy()
        c[false] = c[np.roll(false, 1)] + rng.normal(0.0, 3e3, (6, 3))
        e = pose("joint", c, u, rho, robust=ROBUST, rng=np.random.default_rng(0))
        assert e.status == "ok"
        assert not e.inliers[false].any() and e.inliers.sum() >= n - 6 - 1
        err = pose_error(r, dcm, e)
        assert err @ np.linalg.solve(e.cov, err) < chi2.isf(1e-4, 6)
        clean = np.ones(n, dtype=bool)
        clean[false] = False
        ref = pose("joint", c[clean], u[clean], rho[clean])
        if e.inliers.sum() == clean.sum():
            np.testing.assert_allclose(e.r_mci_m, ref.r_mci_m, atol=1e-6)
