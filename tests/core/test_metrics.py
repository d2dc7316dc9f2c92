"""Scoring metrics: the 3-2-1 Euler angles of the attitude error against analytic rotations, an
independent DCM extraction and scipy; their small-angle link to the rotation vector; the same angles
about MCI axes; NEES and the window statistics against direct numpy computations.

Rotations are built here from explicit elementary matrices, so the analytic cases do not go through
the code under test's own conversion; scipy only turns a matrix into a quaternion.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.core.scoring import metrics

# A DCM entry after a quaternion round trip and a few products is exact to a few ulp (2.2e-16);
# 1e-14 (45 ulp) bounds it (observed: 2e-15). An angle read off such entries inherits that error,
# amplified near gimbal lock by 1/cos(theta) (the arcsin's slope for the pitch).
ROUNDING = 1e-14


def angle_tol_deg(max_abs_pitch_deg: float) -> float:
    return float(np.degrees(ROUNDING / np.cos(np.radians(max_abs_pitch_deg))))


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def dcm_321(phi_deg: float, theta_deg: float, psi_deg: float) -> np.ndarray:
    """z-y'-x'' (3-2-1) rotation: yaw psi about z, then pitch theta, then roll phi."""
    return rz(np.radians(psi_deg)) @ ry(np.radians(theta_deg)) @ rx(np.radians(phi_deg))


def angles_321_deg(dcm: np.ndarray) -> np.ndarray:
    """(phi, theta, psi) in degrees of R = Rz(psi) Ry(theta) Rx(phi), read off the matrix (N, 3, 3)
    (independent of scipy's Euler code)."""
    phi = np.arctan2(dcm[..., 2, 1], dcm[..., 2, 2])
    theta = -np.arcsin(np.clip(dcm[..., 2, 0], -1.0, 1.0))
    psi = np.arctan2(dcm[..., 1, 0], dcm[..., 0, 0])
    return np.degrees(np.stack([phi, theta, psi], axis=-1))


def q_of(dcm: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(dcm).as_quat()


def dcm_of(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(q).as_matrix()


def random_q(rng: np.random.Generator, n: int) -> np.ndarray:
    return Rotation.random(n, random_state=rng).as_quat()


# --- Euler angles of the body-frame error R_true^T R_est --------------------------------------


PURE = [(axis, a) for axis in (0, 2) for a in (-170.0, -30.0, 1e-3, 45.0, 179.0)] + [
    (1, a) for a in (-89.0, -30.0, 1e-3, 45.0, 89.0)]  # pitch lies in [-90, 90] deg


@pytest.mark.parametrize(("axis", "angle_deg"), PURE)
def test_a_pure_error_about_one_body_axis_gives_that_angle_only(axis, angle_deg):
    """R_est = R_true Rx(a) (resp. Ry, Rz): the error is a pure roll (pitch, yaw) of a, whatever
    the true attitude."""
    rng = np.random.default_rng(axis)
    elementary = (rx, ry, rz)[axis](np.radians(angle_deg))
    dcm_true = dcm_of(random_q(rng, 4))
    q_est = q_of(dcm_true @ elementary)
    expected = np.zeros((4, 3))
    expected[:, axis] = angle_deg
    got = metrics.euler321_deg(q_of(dcm_true), q_est)
    pitch = angle_deg if axis == 1 else 0.0
    np.testing.assert_allclose(got, expected, rtol=0, atol=angle_tol_deg(pitch))


@pytest.mark.parametrize("angles_deg", [(10.0, -20.0, 30.0), (-120.0, 80.0, 170.0),
                                        (0.3, -0.02, -179.0), (45.0, -80.0, -45.0)])
def test_a_composed_z_y_x_rotation_gives_back_its_angles(angles_deg):
    rng = np.random.default_rng(1)
    dcm_true = dcm_of(random_q(rng, 3))
    q_est = q_of(dcm_true @ dcm_321(*angles_deg))
    got = metrics.euler321_deg(q_of(dcm_true), q_est)
    np.testing.assert_allclose(got, np.tile(angles_deg, (3, 1)), rtol=0,
                               atol=angle_tol_deg(angles_deg[1]))


def test_random_errors_match_the_matrix_and_rebuild_the_error_rotation():
    """For random attitudes: the angles equal those read off R_true^T R_est, and scipy's
    intrinsic ZYX rotation of (psi, theta, phi) rebuilds that matrix."""
    rng = np.random.default_rng(2)
    q_true, q_est = random_q(rng, 500), random_q(rng, 500)
    err = np.swapaxes(dcm_of(q_true), 1, 2) @ dcm_of(q_est)
    got = metrics.euler321_deg(q_true, q_est)
    assert np.all(np.abs(got[:, 1]) <= 90.0)
    assert np.all(np.abs(got[:, [0, 2]]) <= 180.0)
    # away from gimbal lock the extraction is well conditioned (|theta| < 85 deg here)
    regular = np.abs(got[:, 1]) < 85.0
    assert regular.sum() > 450
    np.testing.assert_allclose(got[regular], angles_321_deg(err)[regular], rtol=0,
                               atol=angle_tol_deg(85.0))
    rebuilt = Rotation.from_euler("ZYX", got[:, ::-1], degrees=True).as_matrix()
    np.testing.assert_allclose(rebuilt, err, rtol=0, atol=ROUNDING)


def test_small_errors_agree_with_the_rotation_vector_to_second_order():
    """For R_err = Rz(psi) Ry(theta) Rx(phi) = Exp(v), Baker-Campbell-Hausdorff gives
    v = (phi - psi theta / 2, theta + psi phi / 2, psi - theta phi / 2) + O(|a|^3): the Euler
    angles (rad) equal the rotation vector to first order, and the second-order terms fix the
    3-2-1 order (another sequence has other signs)."""
    rng = np.random.default_rng(3)
    q_true = random_q(rng, 200)
    for size_rad in (1e-3, 1e-5):
        v = rng.normal(0.0, size_rad, (200, 3))
        q_est = (Rotation.from_quat(q_true) * Rotation.from_rotvec(v)).as_quat()
        a = np.radians(metrics.euler321_deg(q_true, q_est))
        rotvec = metrics.rotation_vector_error(q_true, q_est)
        np.testing.assert_allclose(rotvec, v, rtol=0, atol=ROUNDING)
        norm2 = np.sum(a**2, axis=1, keepdims=True)
        assert np.all(np.abs(rotvec - a) <= norm2)  # first order
        phi, theta, psi = a.T
        bch2 = 0.5 * np.stack([-psi * theta, psi * phi, -theta * phi], axis=1)
        # third-order BCH terms are 1/12 of double commutators: below |a|^3 (+ rounding)
        assert np.all(np.abs(rotvec - a - bch2) <= norm2**1.5 + ROUNDING)


@pytest.mark.parametrize("function", [metrics.euler321_deg, metrics.euler321_mci_deg,
                                      metrics.rotation_vector_error])
def test_missing_estimates_give_nan_rows_and_leave_the_others_alone(function):
    rng = np.random.default_rng(4)
    q_true, q_est = random_q(rng, 6), random_q(rng, 6)
    gaps = q_est.copy()
    gaps[1] = np.nan
    gaps[4, 2] = np.nan  # one non-finite component is enough
    got = function(q_true, gaps)
    assert got.shape == (6, 3)
    assert np.isnan(got[[1, 4]]).all()
    keep = [0, 2, 3, 5]
    np.testing.assert_array_equal(got[keep], function(q_true[keep], q_est[keep]))
    assert np.isnan(function(q_true[:2], np.full((2, 4), np.nan))).all()


# --- the same angles about MCI axes (the paper's apparent convention) -------------------------


def test_mci_angles_are_those_of_r_est_r_true_transposed():
    rng = np.random.default_rng(5)
    q_true, q_est = random_q(rng, 300), random_q(rng, 300)
    dcm_true, dcm_est = dcm_of(q_true), dcm_of(q_est)
    got = metrics.euler321_mci_deg(q_true, q_est)
    regular = np.abs(got[:, 1]) < 85.0
    np.testing.assert_allclose(got[regular],
                               angles_321_deg(dcm_est @ np.swapaxes(dcm_true, 1, 2))[regular],
                               rtol=0, atol=angle_tol_deg(85.0))
    # R_est R_true^T = R_true (R_true^T R_est) R_true^T: the body error seen about MCI axes
    body = Rotation.from_euler("ZYX", metrics.euler321_deg(q_true, q_est)[:, ::-1],
                               degrees=True).as_matrix()
    mci = Rotation.from_euler("ZYX", got[:, ::-1], degrees=True).as_matrix()
    np.testing.assert_allclose(mci, dcm_true @ body @ np.swapaxes(dcm_true, 1, 2), rtol=0,
                               atol=ROUNDING)


def test_a_body_roll_seen_from_mci_after_a_quarter_yaw_is_a_pitch():
    """R_true = Rz(90 deg): the body x axis is MCI +y, so a body roll of a is, about MCI axes, a
    rotation of a about +y (pitch); with R_true = I both conventions agree."""
    roll = rx(np.radians(0.01))
    q_true = q_of(rz(np.pi / 2))[None]
    q_est = q_of(rz(np.pi / 2) @ roll)[None]
    np.testing.assert_allclose(metrics.euler321_deg(q_true, q_est), [[0.01, 0, 0]], rtol=0,
                               atol=angle_tol_deg(0.0))
    np.testing.assert_allclose(metrics.euler321_mci_deg(q_true, q_est), [[0, 0.01, 0]], rtol=0,
                               atol=angle_tol_deg(0.0))
    identity = np.array([[0.0, 0.0, 0.0, 1.0]])
    q = q_of(dcm_321(3.0, -2.0, 1.0))[None]
    np.testing.assert_allclose(metrics.euler321_mci_deg(identity, q),
                               metrics.euler321_deg(identity, q), rtol=0, atol=angle_tol_deg(0.0))


# --- NEES -------------------------------------------------------------------------------------


def random_covariances(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """SPD (n, k, k): random axes, sigmas from 1e-3 to 1 (condition numbers up to 1e6)."""
    axes, _ = np.linalg.qr(rng.standard_normal((n, k, k)))
    sigma = 10.0 ** rng.uniform(-3, 0, (n, k))
    return np.einsum("nij,nj,nkj->nik", axes, sigma**2, axes)


@pytest.mark.parametrize("k", [3, 6])
def test_nees_is_e_transpose_p_inverse_e(k):
    rng = np.random.default_rng(6)
    cov = random_covariances(rng, 50, k)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((50, k)))
    direct = np.array([x @ np.linalg.inv(p) @ x for x, p in zip(e, cov, strict=True)])
    # a solve and an inverse each lose up to ~cond(P) ulp; allow 10 x that
    rtol = 10 * np.finfo(float).eps * np.linalg.cond(cov).max()
    assert rtol < 1e-7
    np.testing.assert_allclose(metrics.nees(e, cov), direct, rtol=rtol)
    # an error of 3 sigma along an eigenvector of P gives 9
    w, v = np.linalg.eigh(cov)
    along = 3.0 * np.sqrt(w[:, 0])[:, None] * v[:, :, 0]
    np.testing.assert_allclose(metrics.nees(along, cov), 9.0, rtol=rtol)


def test_nees_is_nan_for_non_finite_errors_or_covariances():
    rng = np.random.default_rng(7)
    cov = random_covariances(rng, 4, 3)
    e = rng.standard_normal((4, 3))
    e[1, 0] = np.nan
    cov[2, 1, 1] = np.inf
    got = metrics.nees(e, cov)
    assert np.isnan(got[[1, 2]]).all()
    np.testing.assert_allclose(got[[0, 3]], metrics.nees(e[[0, 3]], cov[[0, 3]]), rtol=0, atol=0)


def test_nees_is_nan_for_a_singular_covariance_and_finite_elsewhere():
    cov = np.stack([np.eye(3), np.diag([1.0, 1.0, 0.0]), np.zeros((3, 3))])
    got = metrics.nees(np.ones((3, 3)), cov)
    assert got[0] == 3.0
    assert np.isnan(got[1:]).all()


# --- window statistics ------------------------------------------------------------------------


def test_window_stats_match_numpy_on_the_finite_rows():
    rng = np.random.default_rng(8)
    values = rng.standard_normal((400, 3)) * [1.0, 5.0, 1e-3] + [0.5, 0.0, -2e-3]
    values[rng.choice(400, 37, replace=False), rng.integers(0, 3, 37)] = np.nan
    values[5] = np.inf  # not finite either
    finite = values[np.all(np.isfinite(values), axis=1)]
    assert 300 < finite.shape[0] < 365  # a row with any NaN is dropped whole
    got = metrics.window_stats(values)
    assert got.n == finite.shape[0]
    np.testing.assert_allclose(got.rmse, np.sqrt((finite**2).mean(axis=0)), rtol=1e-13)
    np.testing.assert_array_equal(got.max_abs, np.abs(finite).max(axis=0))
    np.testing.assert_allclose(got.p95_abs, np.percentile(np.abs(finite), 95, axis=0),
                               rtol=1e-13)
    assert np.all(got.p95_abs < got.max_abs)


@pytest.mark.parametrize("values", [np.empty((0, 3)), np.full((4, 3), np.nan)],
                         ids=["no rows", "no finite row"])
def test_window_stats_of_nothing_are_nan(values):
    got = metrics.window_stats(values)
    assert got.n == 0
    for key in ("rmse", "max_abs", "p95_abs"):
        assert getattr(got, key).shape == (3,) and np.isnan(getattr(got, key)).all()
