"""Per-crater noise: `sigma_bearing` and `sigma_range_m` as (n,) arrays, one per crater.

An array of equal values is the scalar, bit for bit; varying sigmas weight each crater by
1/sigma^2 everywhere (estimators against scipy's weighted least squares, the CRLB, the robust
gate, the checks); a crater with a huge sigma is as good as absent; the covariances stay honest
when the simulated noise varies per crater as the navigator assumes; bad arrays are a clear
contract error naming the argument.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2
from test_bearings_only import make_frame

from pipeline.core.estimation import estimators as est
from pipeline.core.estimation import measurement

SIGMA_B = 1e-4
SIGMA_R = 10.0
TAN_EDGE = np.tan(np.radians(22.5))
ROBUST = est.RobustOptions(gate_probability=0.9999, max_hypotheses=64, confidence=0.999)


def physical_sigmas(u_body: np.ndarray, rho_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pixel camera's bearing noise (a constant pixel noise is a larger angle near the image
    centre: sigma ~ cos^2 of the off-axis angle) and a range from the apparent size (0.2 % of
    it: 20-500 m)."""
    return SIGMA_B * u_body[:, 2] ** 2, 0.002 * rho_m


def att_error(dcm_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    return (Rotation.from_matrix(dcm_true).inv() * Rotation.from_quat(q_est)).as_rotvec()


def assert_same(a: est.PoseEstimate, b: est.PoseEstimate) -> None:
    assert a.status == b.status and a.iterations == b.iterations
    for field in ("r_mci_m", "q_mci_from_body", "cov", "att_cov_quest", "inliers"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


# --------------------------------------------------------------------------------------------
# Equal arrays are the scalar

@pytest.mark.parametrize("method", est.METHODS)
def test_arrays_of_equal_sigmas_give_the_scalar_results_bit_for_bit(method):
    rng = np.random.default_rng(1)
    for n in (3, 4, 12, 60):
        for missing in (False, True):
            r, dcm, c = make_frame(rng, n)
            u, rho = measurement.measure(rng, *measurement.true_bearings(c, r, dcm.T), SIGMA_B,
                                         SIGMA_R)
            if missing:
                rho[rng.random(n) < 0.4] = np.nan
            prior = None if n % 2 else r + rng.normal(0.0, 1e3, 3)
            scalar = {"sigma_bearing": SIGMA_B, "sigma_range_m": SIGMA_R}
            arrays = {"sigma_bearing": np.full(n, SIGMA_B), "sigma_range_m": np.full(n, SIGMA_R)}
            for robust in (False, True):
                def kw(robust=robust, n=n, prior=prior):  # a fresh generator per call
                    return ({"robust": ROBUST, "rng": np.random.default_rng(n)} if robust
                            else {"r_prior_mci_m": prior})
                assert_same(est.estimate_pose(method, c, u, rho, **scalar, **kw()),
                            est.estimate_pose(method, c, u, rho, **arrays, **kw()))
            # the measurement model divides element by element: also the same bits
            q = Rotation.from_matrix(dcm).as_quat()
            for x, y in zip(measurement.whitened_system(r, q, c, u, rho, **scalar),
                            measurement.whitened_system(r, q, c, u, rho, **arrays), strict=True):
                np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(
                measurement.squared_normalised_residuals(r, q, c, u, rho, **scalar),
                measurement.squared_normalised_residuals(r, q, c, u, rho, **arrays))
            np.testing.assert_array_equal(est.crlb(r, q, c, **scalar), est.crlb(r, q, c, **arrays))


def test_nearly_equal_sigmas_take_the_weighted_path_to_the_same_result():
    """Sigmas differing by 1e-12 relative are not collapsed to a number: the per-crater code
    (weighted range fit, per-crater QUEST weights and rounding levels) gives the scalar result
    to ~1e-9 of its sigma."""
    rng = np.random.default_rng(2)
    for n in (5, 30):
        r, dcm, c = make_frame(rng, n)
        u, rho = measurement.measure(rng, *measurement.true_bearings(c, r, dcm.T), SIGMA_B,
                                     SIGMA_R)
        wiggle = 1.0 + 1e-12 * np.arange(n)
        for method in est.METHODS:
            a = est.estimate_pose(method, c, u, rho, sigma_bearing=SIGMA_B, sigma_range_m=SIGMA_R)
            b = est.estimate_pose(method, c, u, rho, sigma_bearing=SIGMA_B * wiggle,
                                  sigma_range_m=SIGMA_R * wiggle)
            assert a.status == b.status == "ok"
            sigma = np.sqrt(np.diag(a.cov))
            assert np.all(np.abs(a.r_mci_m - b.r_mci_m) < 1e-6 * sigma[:3])
            np.testing.assert_allclose(b.cov, a.cov, rtol=1e-8)


# --------------------------------------------------------------------------------------------
# Weights as they should be

def test_joint_with_per_crater_sigmas_matches_weighted_least_squares():
    rng = np.random.default_rng(3)
    for n, missing in ((8, 0.0), (30, 0.5)):
        r, dcm, c = make_frame(rng, n)
        u_true, rho_true = measurement.true_bearings(c, r, dcm.T)
        s_b, s_r = physical_sigmas(u_true, rho_true)
        s_b *= rng.uniform(0.5, 3.0, n)
        u, rho = measurement.measure(rng, u_true, rho_true, s_b, s_r)
        rho[rng.random(n) < missing] = np.nan
        e = est.estimate_pose("joint", c, u, rho, sigma_bearing=s_b, sigma_range_m=s_r)
        assert e.status == "ok"
        has = ~np.isnan(rho)
        rot0 = Rotation.from_quat(e.q_mci_from_body)

        def residuals(p, rot0=rot0, c=c, u=u, rho=rho, has=has, s_b=s_b, s_r=s_r):
            rot = rot0 * Rotation.from_rotvec(p[3:])
            d = c - p[:3]
            dist = np.linalg.norm(d, axis=1)
            pred = rot.inv().apply(d / dist[:, None])
            return np.r_[((u - pred) / s_b[:, None]).ravel(), (rho - dist)[has] / s_r[has]]

        ref = least_squares(residuals, np.r_[r + 300.0, 0.0, 0.0, 0.0],
                            x_scale=np.r_[1e1, 1e1, 1e1, 1e-5, 1e-5, 1e-5], xtol=1e-15,
                            ftol=1e-15, gtol=1e-15)
        sigma = np.sqrt(np.diag(e.cov))
        assert np.all(np.abs(ref.x[:3] - e.r_mci_m) < 1e-3 * sigma[:3])
        np.testing.assert_allclose(
            e.cov, est.crlb(e.r_mci_m, e.q_mci_from_body, c, sigma_bearing=s_b, sigma_range_m=s_r,
                            has_range=has), rtol=1e-6)


def test_range_fit_with_per_crater_sigmas_matches_weighted_least_squares():
    rng = np.random.default_rng(4)
    r, dcm, c = make_frame(rng, 15)
    _, rho = measurement.true_bearings(c, r, dcm.T)
    s_r = rng.uniform(5.0, 500.0, 15)
    rho = rho + s_r * rng.standard_normal(15)
    x, cov, _, status = est.gauss_newton_position(c, rho, r + 3e3, 1e-9, 20, sigma_range_m=s_r)
    assert status == "ok"
    ref = least_squares(lambda p: (np.linalg.norm(c - p, axis=1) - rho) / s_r, r + 3e3,
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(x, ref.x, atol=1e-6)
    jac = (x - c) / np.linalg.norm(c - x, axis=1)[:, None] / s_r[:, None]
    np.testing.assert_allclose(cov, np.linalg.inv(jac.T @ jac), rtol=1e-9)


@pytest.mark.parametrize("method", est.METHODS)
def test_a_crater_with_a_huge_sigma_is_ignored(method):
    """A false match (5 km off) with sigmas 1e9 times the others' changes nothing that matters;
    with the common sigma it ruins the fix."""
    rng = np.random.default_rng(5)
    n = 20
    r, dcm, c = make_frame(rng, n)
    u, rho = measurement.measure(rng, *measurement.true_bearings(c, r, dcm.T), SIGMA_B, SIGMA_R)
    c_bad = c.copy()
    c_bad[7] += [5e3, -4e3, 1e3]
    s_b, s_r = np.full(n, SIGMA_B), np.full(n, SIGMA_R)
    s_b[7], s_r[7] = 1e9 * SIGMA_B, 1e9 * SIGMA_R
    keep = np.arange(n) != 7
    without = est.estimate_pose(method, c[keep], u[keep], rho[keep], sigma_bearing=SIGMA_B,
                                sigma_range_m=SIGMA_R)
    ignored = est.estimate_pose(method, c_bad, u, rho, sigma_bearing=s_b, sigma_range_m=s_r)
    assert without.status == ignored.status == "ok" and ignored.inliers.all()
    sigma = np.sqrt(np.diag(without.cov))
    assert np.all(np.abs(ignored.r_mci_m - without.r_mci_m) < 1e-6 * sigma[:3])
    assert np.linalg.norm(att_error(Rotation.from_quat(without.q_mci_from_body).as_matrix(),
                                    ignored.q_mci_from_body)) < 1e-6 * sigma[3:].min()
    np.testing.assert_allclose(ignored.cov, without.cov, rtol=1e-6)
    assert est.estimate_pose(method, c_bad, u, rho, sigma_bearing=SIGMA_B,
                             sigma_range_m=SIGMA_R).status == "inconsistent"


def test_the_crlb_weights_each_crater_by_its_sigma():
    rng = np.random.default_rng(6)
    r, dcm, c = make_frame(rng, 10)
    q = Rotation.from_matrix(dcm).as_quat()
    s_b, s_r = rng.uniform(1e-5, 1e-3, 10), rng.uniform(1.0, 100.0, 10)
    fisher = est.fisher_information(r, q, c, sigma_bearing=s_b, sigma_range_m=s_r)
    one_by_one = sum(est.fisher_information(r, q, c[[j]], sigma_bearing=s_b[j],
                                            sigma_range_m=s_r[j]) for j in range(10))
    np.testing.assert_allclose(fisher, one_by_one, rtol=1e-12)
    # doubling a crater's sigmas quarters its information
    s_b2, s_r2 = s_b.copy(), s_r.copy()
    s_b2[3] *= 2.0
    s_r2[3] *= 2.0
    f3 = est.fisher_information(r, q, c[[3]], sigma_bearing=s_b[3], sigma_range_m=s_r[3])
    np.testing.assert_allclose(est.fisher_information(r, q, c, sigma_bearing=s_b2,
                                                      sigma_range_m=s_r2),
                               fisher - 0.75 * f3, rtol=1e-9, atol=1e-12 * np.abs(fisher).max())


@pytest.mark.parametrize("method", est.METHODS)
def test_covariances_stay_honest_with_per_crater_noise(method):
    """Simulated with a pixel camera's bearing noise and ranges 0.2 % of the distance, estimated
    with the same per-crater sigmas: mean NEES ~ 6 against the estimate's own covariance (joint,
    and the paper's full covariance) and the joint against the CRLB."""
    rng = np.random.default_rng(7)
    trials, own, bound = 300, [], []
    for _ in range(trials):
        n = int(rng.integers(6, 40))
        r, dcm, c = make_frame(rng, n)
        u_true, rho_true = measurement.true_bearings(c, r, dcm.T)
        s_b, s_r = physical_sigmas(u_true, rho_true)
        u, rho = measurement.measure(rng, u_true, rho_true, s_b, s_r)
        e = est.estimate_pose(method, c, u, rho, sigma_bearing=s_b, sigma_range_m=s_r)
        assert e.status == "ok"
        err = np.r_[e.r_mci_m - r, att_error(dcm, e.q_mci_from_body)]
        own.append(err @ np.linalg.solve(e.cov, err))
        crlb = est.crlb(r, Rotation.from_matrix(dcm).as_quat(), c, sigma_bearing=s_b,
                        sigma_range_m=s_r)
        bound.append(err @ np.linalg.solve(crlb, err))
    lo, hi = chi2.ppf([0.005, 0.995], trials * 6) / trials
    assert lo <= np.mean(own) <= hi
    if method == "joint":
        assert lo <= np.mean(bound) <= hi


def test_the_robust_gate_uses_each_craters_sigma():
    """A range 400 m off: rejected under a 10 m sigma, kept when that crater's sigma is 300 m."""
    rng = np.random.default_rng(8)
    n = 25
    r, dcm, c = make_frame(rng, n)
    u, rho = measurement.measure(rng, *measurement.true_bearings(c, r, dcm.T), SIGMA_B, SIGMA_R)
    rho[4] += 400.0
    s_r = np.full(n, SIGMA_R)
    kw = {"robust": ROBUST, "rng": np.random.default_rng(0), "sigma_bearing": SIGMA_B}
    for method in est.METHODS:
        tight = est.estimate_pose(method, c, u, rho, sigma_range_m=SIGMA_R, **kw)
        assert tight.status == "ok" and not tight.inliers[4] and tight.inliers.sum() == n - 1
        s_r[4] = 300.0
        loose = est.estimate_pose(method, c, u, rho, sigma_range_m=s_r, **kw)
        assert loose.status == "ok" and loose.inliers.all()
        s_r[4] = SIGMA_R


def test_checks_use_each_craters_sigma():
    """Bearings of half the craters 5 times noisier: inconsistent under one small sigma, ok
    when those craters' sigmas say so."""
    rng = np.random.default_rng(9)
    n = 60
    r, dcm, c = make_frame(rng, n)
    s_b = np.where(np.arange(n) < 30, 5.0 * SIGMA_B, SIGMA_B)
    u, rho = measurement.measure(rng, *measurement.true_bearings(c, r, dcm.T), s_b, SIGMA_R)
    for method in est.METHODS:
        assert est.estimate_pose(method, c, u, rho, sigma_bearing=SIGMA_B,
                                 sigma_range_m=SIGMA_R).status == "inconsistent"
        assert est.estimate_pose(method, c, u, rho, sigma_bearing=s_b,
                                 sigma_range_m=SIGMA_R).status == "ok"


def test_simulated_per_crater_noise_has_the_given_sigmas():
    rng = np.random.default_rng(10)
    n = 200_000
    u = np.tile([0.0, 0.0, 1.0], (n, 1))
    s_b = np.where(np.arange(n) % 2 == 0, 1e-4, 3e-4)
    s_r = np.where(np.arange(n) % 2 == 0, 1.0, 50.0)
    u_m, rho_m = measurement.measure(rng, u, np.full(n, 1e5), s_b, s_r)
    for k in (0, 1):
        rows = slice(k, None, 2)
        np.testing.assert_allclose(np.std(u_m[rows, :2]), s_b[k], rtol=0.01)
        np.testing.assert_allclose(np.std(rho_m[rows] - 1e5), s_r[k], rtol=0.01)


# --------------------------------------------------------------------------------------------
# Contract violations

@pytest.mark.parametrize(("name", "value", "match"), [
    ("sigma_bearing", np.full(9, 1e-4), r"sigma_bearing .*shape \(10,\)"),
    ("sigma_range_m", np.full((10, 1), 10.0), r"sigma_range_m .*shape \(10,\)"),
    ("sigma_bearing", np.r_[np.full(9, 1e-4), np.nan], r"sigma_bearing .*index 9"),
    ("sigma_range_m", np.r_[0.0, np.full(9, 10.0)], r"sigma_range_m .*> 0.*index 0"),
    ("sigma_range_m", np.r_[np.full(9, 10.0), -1.0], r"sigma_range_m"),
    ("sigma_bearing", np.r_[np.full(9, 1e-4), np.inf], r"sigma_bearing"),
])
def test_bad_per_crater_sigmas_are_a_clear_contract_error(name, value, match):
    rng = np.random.default_rng(11)
    r, dcm, c = make_frame(rng, 10)
    u, rho = measurement.true_bearings(c, r, dcm.T)
    q = Rotation.from_matrix(dcm).as_quat()
    kw = {"sigma_bearing": SIGMA_B, "sigma_range_m": SIGMA_R, name: value}
    for call in (lambda: est.estimate_pose("joint", c, u, rho, **kw),
                 lambda: est.fisher_information(r, q, c, **kw),
                 lambda: est.crlb(r, q, c, **kw),
                 lambda: measurement.whitened_system(r, q, c, u, rho, **kw),
                 lambda: measurement.squared_normalised_residuals(r, q, c, u, rho, **kw)):
        with pytest.raises(ValueError, match=match):
            call()
