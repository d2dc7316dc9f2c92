"""Measurement model (paper Eq. 10-11, ERRATA 6): unit bearings in body axes with sigma 1e-4 per
component (renormalised) and ranges with sigma 10 m.

Noise statistics are checked with chi-square and normal bounds at a false-alarm rate of 1e-4 per
test (split evenly over its simultaneous checks). Renormalisation changes the tangential
components only at relative order sigma^2 (1e-8), far inside these bounds.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from pipeline.core.estimation import measurement
from pipeline.core.math import frames

ALPHA = 1e-4
SIGMA_BEARING = 1e-4
SIGMA_RANGE_M = 10.0
R_M = 1_737_400.0


def chi2_bounds(dof: int, alpha: float) -> tuple[float, float]:
    return stats.chi2.ppf(alpha / 2, dof), stats.chi2.isf(alpha / 2, dof)


def tangent_basis(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3) completing each unit vector u (N, 3) to an orthonormal basis."""
    helper = np.where(np.abs(u[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(u, e1)


def random_units(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_measured_bearings_are_unit_vectors():
    rng = np.random.default_rng(1)
    u = random_units(rng, 10_000)
    for sigma in (0.0, 1e-4, 0.3):
        u_meas, _ = measurement.measure(rng, u, np.full(u.shape[0], 1e5), sigma, SIGMA_RANGE_M)
        np.testing.assert_allclose(np.linalg.norm(u_meas, axis=1), 1.0, rtol=1e-15)


def test_zero_noise_returns_the_truth():
    rng = np.random.default_rng(2)
    u = random_units(rng, 100)
    rho = rng.uniform(1e4, 1e6, 100)
    u_meas, rho_meas = measurement.measure(rng, u, rho, 0.0, 0.0)
    np.testing.assert_allclose(u_meas, u, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(rho_meas, rho)


def test_bearing_noise_statistics():
    rng = np.random.default_rng(3)
    n = 200_000
    u = random_units(rng, n)
    u_meas, _ = measurement.measure(rng, u, np.full(n, 1e5), SIGMA_BEARING, SIGMA_RANGE_M)
    e1, e2 = tangent_basis(u)
    x1 = np.sum(u_meas * e1, axis=1) / SIGMA_BEARING
    x2 = np.sum(u_meas * e2, axis=1) / SIGMA_BEARING
    alpha = ALPHA / 7  # seven checks below
    z = stats.norm.isf(alpha / 2)
    # Tangential components: mean 0, standard deviation sigma per axis, uncorrelated.
    for x in (x1, x2):
        assert abs(x.mean()) <= z / np.sqrt(n)
        lo, hi = chi2_bounds(n, alpha)
        assert lo <= np.sum(x**2) <= hi
    assert abs(np.mean(x1 * x2)) <= z / np.sqrt(n)  # the product of two N(0,1) has variance 1
    # Radial: the angular error theta ~ sigma * sqrt(chi2(2)); the bias 1 - u.u_meas = theta^2/2
    # is second order, mean sigma^2.
    theta = np.arctan2(np.linalg.norm(np.cross(u, u_meas), axis=1), np.sum(u * u_meas, axis=1))
    lo, hi = chi2_bounds(2 * n, alpha)
    assert lo <= np.sum((theta / SIGMA_BEARING) ** 2) <= hi
    radial_bias = 1.0 - np.sum(u * u_meas, axis=1)
    assert lo <= np.sum(2 * radial_bias / SIGMA_BEARING**2) <= hi


def test_range_noise_statistics():
    rng = np.random.default_rng(4)
    n = 200_000
    rho = rng.uniform(1e4, 4e5, n)
    _, rho_meas = measurement.measure(rng, random_units(rng, n), rho, SIGMA_BEARING,
                                      SIGMA_RANGE_M)
    x = (rho_meas - rho) / SIGMA_RANGE_M
    alpha = ALPHA / 2
    assert abs(x.mean()) <= stats.norm.isf(alpha / 2) / np.sqrt(n)
    lo, hi = chi2_bounds(n, alpha)
    assert lo <= np.sum(x**2) <= hi


def test_bearing_and_range_noise_are_independent():
    rng = np.random.default_rng(5)
    n = 200_000
    u = np.tile([0.0, 0.0, 1.0], (n, 1))  # boresight: body x, y are the tangential axes
    u_meas, rho_meas = measurement.measure(rng, u, np.full(n, 2e5), SIGMA_BEARING, SIGMA_RANGE_M)
    x = u_meas[:, 0] / SIGMA_BEARING
    y = (rho_meas - 2e5) / SIGMA_RANGE_M
    assert abs(np.mean(x * y)) <= stats.norm.isf(ALPHA / 2) / np.sqrt(n)


def test_true_bearings_are_the_same_in_mci_and_mcmf():
    rng = np.random.default_rng(6)
    theta = 0.7  # Moon rotation angle
    r_mci = np.array([1.2e6, -1.1e6, 0.9e6])
    c_mcmf = random_units(rng, 50) * R_M
    dcm_body_from_mci = Rotation.random(random_state=7).as_matrix()
    dcm_mci_from_mcmf = frames.dcm_mci_from_mcmf(theta)
    c_mci = c_mcmf @ dcm_mci_from_mcmf.T
    r_mcmf = dcm_mci_from_mcmf.T @ r_mci

    u_mci, rho_mci = measurement.true_bearings(c_mci, r_mci, dcm_body_from_mci)
    u_mcmf, rho_mcmf = measurement.true_bearings(c_mcmf, r_mcmf,
                                                 dcm_body_from_mci @ dcm_mci_from_mcmf)
    np.testing.assert_allclose(u_mcmf, u_mci, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rho_mcmf, rho_mci, rtol=1e-14)
    # And against the definition, one crater at a time, with the rotation applied as scipy does.
    rot = Rotation.from_matrix(dcm_body_from_mci)
    for i in range(5):
        d = c_mci[i] - r_mci
        assert rho_mci[i] == pytest.approx(np.sqrt(d @ d), rel=1e-15)
        np.testing.assert_allclose(u_mci[i], rot.apply(d / np.sqrt(d @ d)), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(u_mci, axis=1), 1.0, rtol=1e-15)


# --------------------------------------------------------------------------------------------
# The navigator's model: h(x), the whitened Jacobian against central differences, residuals

def _pose_and_craters(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """A position 80 km above the sphere, a random attitude, craters on the sphere below."""
    up = random_units(rng, 1)[0]
    r = (R_M + 80e3) * up
    c = (up + 0.05 * rng.normal(size=(n, 3))) * R_M
    c *= R_M / np.linalg.norm(c, axis=1, keepdims=True)
    return r, Rotation.random(random_state=rng).as_quat(), c


def test_predict_is_the_simulators_truth():
    rng = np.random.default_rng(7)
    r, q, c = _pose_and_craters(rng, 40)
    u, rho = measurement.predict(r, q, c)
    u_true, rho_true = measurement.true_bearings(c, r, Rotation.from_quat(q).as_matrix().T)
    np.testing.assert_allclose(u, u_true, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rho, rho_true, rtol=1e-15)


def _whitened_residuals(r, rot: Rotation, c, u_meas, rho_meas):
    """Independent whitened residuals: range, and the bearing error in a fixed tangent basis of
    the measured bearing (its tangent part to first order; what the whitened Jacobian predicts
    after projecting it into the same basis)."""
    d = c - r
    rho = np.linalg.norm(d, axis=1)
    u = rot.inv().apply(d / rho[:, None])
    return (rho_meas - rho) / SIGMA_RANGE_M, (u_meas - u) / SIGMA_BEARING


def test_whitened_jacobian_matches_central_differences():
    rng = np.random.default_rng(8)
    r, q, c = _pose_and_craters(rng, 25)
    rot = Rotation.from_quat(q)
    u_meas, rho_meas = measurement.predict(r, q, c)
    e, jac, rho_pred = measurement.whitened_system(r, q, c, u_meas, rho_meas,
                                                   sigma_bearing=SIGMA_BEARING,
                                                   sigma_range_m=SIGMA_RANGE_M)
    np.testing.assert_allclose(e, 0.0, atol=1e-9)
    np.testing.assert_array_equal(rho_pred, rho_meas)
    # d e / d x = -J; steps: 1 m in position, 1e-6 rad in attitude (truncation ~h^2/rho^2)
    for k in range(6):
        h = 1.0 if k < 3 else 1e-6
        step = np.eye(3)[k % 3] * h
        if k < 3:
            plus = _whitened_residuals(r + step, rot, c, u_meas, rho_meas)
            minus = _whitened_residuals(r - step, rot, c, u_meas, rho_meas)
        else:
            plus = _whitened_residuals(r, rot * Rotation.from_rotvec(step), c, u_meas, rho_meas)
            minus = _whitened_residuals(r, rot * Rotation.from_rotvec(-step), c, u_meas, rho_meas)
        np.testing.assert_allclose(-jac[:, 0, k], (plus[0] - minus[0]) / (2 * h), rtol=1e-7,
                                   atol=1e-9)
        np.testing.assert_allclose(-jac[:, 1:, k], (plus[1] - minus[1]) / (2 * h), rtol=1e-7,
                                   atol=1e-8 if k < 3 else 1e-5)  # rounding ~eps / h / sigma
    # bearing rows are tangent to the predicted bearing (rank 2)
    np.testing.assert_allclose(np.einsum("na,nak->nk", u_meas, jac[:, 1:, :]), 0.0, atol=1e-9)


def test_normalised_residuals_are_chi_square_with_3_dof_at_the_truth():
    rng = np.random.default_rng(9)
    n = 100_000
    r, q, c = _pose_and_craters(rng, n)
    u, rho = measurement.predict(r, q, c)
    u_meas, rho_meas = measurement.measure(rng, u, rho, SIGMA_BEARING, SIGMA_RANGE_M)
    s = measurement.squared_normalised_residuals(r, q, c, u_meas, rho_meas,
                                                 sigma_bearing=SIGMA_BEARING,
                                                 sigma_range_m=SIGMA_RANGE_M)
    e, _, _ = measurement.whitened_system(r, q, c, u_meas, rho_meas, sigma_bearing=SIGMA_BEARING,
                                          sigma_range_m=SIGMA_RANGE_M)
    np.testing.assert_allclose(s, np.sum(e**2, axis=1), rtol=1e-12)
    lo, hi = chi2_bounds(3 * n, ALPHA)
    assert lo <= s.sum() <= hi
