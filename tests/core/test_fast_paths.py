"""The estimators' fast paths against their references: the compiled normal equations against
the whitened Jacobian, the craters' plane start against the ML pose, the safeguarded
Gauss-Newton against scipy's least squares, the checks on a fit's own system against the checks
on the normal equations at the estimate, and the condition-number bound against the eigenvalues.

Geometry as `test_bearings_only` (a nadir camera 10-250 km up, a square 45 deg field of view).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from test_bearings_only import SIGMA_B, SIGMA_R, att_error, make_frame, no_ranges, observe

from pipeline.core.estimation import estimators as est
from pipeline.core.estimation import measurement
from pipeline.core.estimation.estimators import bearings, checks, safeguarded
from pipeline.core.estimation.estimators.base import scaled_condition, scaled_inverse
from pipeline.core.math.rotations import dcm_from_q


def _system(r, q, c, u, rho, sb, sr):
    e, jac, _ = measurement.whitened_system(r, q, c, u, rho, sigma_bearing=sb, sigma_range_m=sr)
    rows = jac.reshape(-1, 6)
    return rows.T @ rows, rows.T @ e.ravel(), float(e.ravel() @ e.ravel())


@pytest.mark.parametrize("case", ["ranges", "none", "mixed", "per_crater"])
def test_normal_equations_equal_the_jacobians(case):
    """J^T J, J^T e and e^T e summed crater by crater equal those of the (N, 4, 6) Jacobian
    to rounding, off the minimum (residuals of ~30 sigma) and with every kind of noise and
    missing range."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        n = int(rng.integers(3, 40))
        r, dcm, c = make_frame(rng, n)
        u, rho = observe(rng, r, dcm, c)
        rho = rho + rng.normal(0.0, 300.0, n)
        u = u + rng.normal(0.0, 3e-3, (n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        sb, sr = (rng.uniform(5e-5, 5e-4, n), rng.uniform(1.0, 100.0, n)) \
            if case == "per_crater" else (SIGMA_B, SIGMA_R)
        if case == "none":
            rho = no_ranges(n)
        elif case in ("mixed", "per_crater"):
            rho[rng.random(n) < 0.4] = np.nan
        q = Rotation.from_matrix(dcm).as_quat()
        info, gradient, cost = _system(r, q, c, u, rho, sb, sr)
        ne = measurement.normal_equations(r, dcm_from_q(q), measurement.frame(c, u, rho, sb, sr))
        scale = np.sqrt(np.diag(info))
        np.testing.assert_allclose(ne.info / np.outer(scale, scale),
                                   info / np.outer(scale, scale), rtol=0, atol=1e-13)
        np.testing.assert_allclose(ne.gradient / scale, gradient / scale, rtol=0,
                                   atol=1e-12 * np.sqrt(cost))
        assert ne.cost == pytest.approx(cost, rel=1e-12)
        u_pred, rho_pred = measurement.predict(r, q, c)
        np.testing.assert_allclose(ne.rho_pred_m, rho_pred, rtol=1e-15)
        np.testing.assert_allclose(ne.cos_pred, np.einsum("ij,ij->i", u_pred, u), atol=1e-15)


def test_the_plane_start_is_near_the_ml_pose():
    """Noiseless craters: the plane's pose to metres from 50-200 km (its second pass takes the
    ~200 m of the patch's curvature away); with noise, within a few
    standard deviations of the ML pose (the curvature of the patch corrected by the second
    pass), and None for craters on a line."""
    rng = np.random.default_rng(12)
    r, dcm, c = make_frame(rng, 20, (50.0, 200.0))
    u, _ = observe(None, r, dcm, c)
    r0, q0 = bearings.planar_pose(c, u)
    assert np.linalg.norm(r0 - r) < 5.0
    assert np.linalg.norm(att_error(dcm, q0)) < 5e-5
    distances = []
    for _ in range(40):
        r, dcm, c = make_frame(rng, 20, (50.0, 200.0))
        u, _ = observe(rng, r, dcm, c)
        ml = est.estimate_pose("joint", c, u, no_ranges(20), sigma_bearing=SIGMA_B,
                               sigma_range_m=SIGMA_R)
        assert ml.status == "ok"
        r0, q0 = bearings.planar_pose(c, u)
        delta = np.r_[r0 - ml.r_mci_m, Rotation.from_matrix(
            dcm_from_q(ml.q_mci_from_body).T @ dcm_from_q(q0)).as_rotvec()]
        distances.append(float(np.sqrt(delta @ np.linalg.solve(ml.cov, delta))))
    assert np.median(distances) < 1.5 and max(distances) < 10.0
    line = np.linspace(0.0, 1.0, 6)[:, None] * np.array([1e4, 2e4, 0.0]) + r * 0.99
    assert bearings.planar_pose(line, observe(None, r, dcm, line)[0]) is None


def test_the_safeguarded_fit_is_the_ml_and_stops_early():
    """From the plane, bearings only: the minimum of scipy's least squares to 1e-3 sigma, in at
    most 3 iterations (the plane is within ~1 sigma), with the covariance the inverse
    information at the estimate to 1e-4 (it is that of the pose one step back, the step below
    1e-4 sigma)."""
    rng = np.random.default_rng(13)
    for _ in range(8):
        n = 20
        r, dcm, c = make_frame(rng, n, (50.0, 200.0))
        u, _ = observe(rng, r, dcm, c)
        e = est.estimate_pose("joint", c, u, no_ranges(n), sigma_bearing=SIGMA_B,
                              sigma_range_m=SIGMA_R)
        assert e.status == "ok" and e.iterations <= 3
        rot0 = Rotation.from_quat(e.q_mci_from_body)

        def residuals(p, rot0=rot0, c=c, u=u):
            d = c - p[:3]
            pred = (rot0 * Rotation.from_rotvec(p[3:])).inv().apply(
                d / np.linalg.norm(d, axis=1)[:, None])
            return ((u - pred) / SIGMA_B).ravel()

        ref = least_squares(residuals, np.r_[e.r_mci_m + 100.0, 0.0, 0.0, 0.0],
                            x_scale=np.r_[1e1, 1e1, 1e1, 1e-5, 1e-5, 1e-5], xtol=1e-15,
                            ftol=1e-15, gtol=1e-15)
        sigma = np.sqrt(np.diag(e.cov))
        assert np.all(np.abs(ref.x[:3] - e.r_mci_m) < 1e-3 * sigma[:3])
        np.testing.assert_allclose(e.cov, est.crlb(e.r_mci_m, e.q_mci_from_body, c,
                                                   sigma_bearing=SIGMA_B, sigma_range_m=SIGMA_R,
                                                   has_range=np.zeros(n, bool)),
                                   rtol=1e-4, atol=1e-20)


@pytest.mark.parametrize("ranges", [True, False])
def test_checks_on_the_fit_system_decide_as_at_the_estimate(ranges):
    """The checks of a joint estimate on its fit's last system give the status of the checks on
    the normal equations at the estimate itself, also for frames made inconsistent (a crater
    moved by 2 km)."""
    rng = np.random.default_rng(14)
    options = checks.CheckOptions(moon_radius_m=1737.4e3)
    statuses = set()
    for trial in range(30):
        n = 12
        r, dcm, c = make_frame(rng, n)
        u, rho = observe(rng, r, dcm, c)
        rho = rho if ranges else no_ranges(n)
        if trial % 3 == 1:
            c = c.copy()
            c[0] += 2e3
        fit = est.JointEstimator(est.EstimatorOptions(SIGMA_B, SIGMA_R)).fit(
            c, u, rho, np.ones(n, bool), r + 500.0)
        if fit.status != "ok":
            continue
        assert fit.system is not None
        reused = checks.check_estimate(fit, c, u, rho, sigma_bearing=SIGMA_B,
                                       sigma_range_m=SIGMA_R, options=options)
        at_estimate = checks.check_estimate(replace(fit, system=None), c, u, rho,
                                            sigma_bearing=SIGMA_B,
                                            sigma_range_m=SIGMA_R, options=options)
        assert reused.status == at_estimate.status
        statuses.add(reused.status)
    assert {"ok", "inconsistent"} <= statuses


def test_the_condition_bound_bounds_the_condition_number():
    """6 tr((S I S)^-1) is at least the Jacobi-scaled condition number (eigenvalues), and the
    exact number replaces it past MAX_CONDITION."""
    rng = np.random.default_rng(15)
    for k in range(200):
        a = rng.normal(size=(20, 6)) * 10.0 ** rng.uniform(-4, 4, 6)
        if k % 4 == 0:
            a[:, 5] = a[:, 4] * (1 + 1e-7 * rng.normal(size=20))  # nearly dependent
        h = a.T @ a
        exact = scaled_condition(h)
        bound = safeguarded.condition_bound(h, np.linalg.inv(h))
        assert bound >= exact * (1 - 1e-9)
        if bound > est.MAX_CONDITION:
            assert bound == exact
        _, (low, high) = scaled_inverse(h, direct=True)
        if exact < 1e12:  # both eigensolvers accurate
            assert high / low == pytest.approx(exact, rel=1e-6)


def test_the_compiled_cholesky_solve_matches_numpy_and_refuses_what_is_not_positive_definite():
    """The compiled Gauss-Newton's 6 x 6 solve: I^-1 g and I^-1 equal numpy's on well- and
    ill-scaled SPD matrices; an indefinite, a singular or a NaN matrix is not ok."""
    from pipeline.core.estimation import pose_kernels

    rng = np.random.default_rng(16)
    for _ in range(50):
        a = rng.normal(size=(12, 6)) * 10.0 ** rng.uniform(-3, 3, 6)
        h, g = a.T @ a, rng.normal(size=6)
        ok, step, inv = pose_kernels._cholesky_solve(h, g)
        assert ok
        np.testing.assert_allclose(step, np.linalg.solve(h, g), rtol=1e-6,
                                   atol=1e-12 * np.abs(np.linalg.solve(h, g)).max())
        np.testing.assert_allclose(inv, np.linalg.inv(h), rtol=1e-6,
                                   atol=1e-9 * np.abs(np.linalg.inv(h)).max())
    bad = [np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -1.0]), np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 1.0]),
           np.full((6, 6), np.nan)]
    for h in bad:
        assert not pose_kernels._cholesky_solve(h, np.ones(6))[0]


def test_the_compiled_eigen_and_lu_solvers_match_numpy():
    """The planar start's 9 x 9 (and 4 x 4) symmetric eigen-decomposition and its LU solve
    against numpy's LAPACK: eigenvalues, the null vector of a nearly singular PSD matrix (the
    homography's: smallest eigenvalue 1e-10 of the largest), solutions; a singular matrix is
    not solved."""
    from pipeline.core.estimation import pose_kernels

    rng = np.random.default_rng(17)
    for n in (4, 9):
        for _ in range(30):
            a = rng.normal(size=(n, n))
            sym = a + a.T
            ev, vec = pose_kernels._symmetric_eigen(sym)
            np.testing.assert_allclose(ev, np.linalg.eigvalsh(sym), rtol=0,
                                       atol=1e-12 * np.abs(ev).max())
            np.testing.assert_allclose(vec.T @ vec, np.eye(n), atol=1e-12)
            np.testing.assert_allclose(sym @ vec, vec * ev, atol=1e-11 * np.abs(ev).max())
            null = rng.normal(size=n)
            null /= np.linalg.norm(null)
            basis = np.linalg.qr(np.column_stack([null, rng.normal(size=(n, n - 1))]))[0]
            psd = basis @ np.diag(np.r_[1e-10, rng.uniform(0.5, 2.0, n - 1)]) @ basis.T
            ev, vec = pose_kernels._symmetric_eigen(psd)
            assert ev[0] == pytest.approx(1e-10, rel=1e-4)
            assert abs(vec[:, 0] @ null) == pytest.approx(1.0, abs=1e-12)
            b = rng.normal(size=n)
            ok, x = pose_kernels._lu_solve(sym, b)
            assert ok
            np.testing.assert_allclose(x, np.linalg.solve(sym, b), rtol=1e-8)
    singular = np.ones((9, 9))
    assert not pose_kernels._lu_solve(singular, np.ones(9))[0]
