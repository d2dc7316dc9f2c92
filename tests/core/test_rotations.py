"""Rotation helpers: scalar-last quaternions, DCMs and rotation vectors against scipy."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.core.math import rotations


def test_quaternion_dcm_consistent_with_scipy() -> None:
    rng = np.random.default_rng(5)
    rot = Rotation.random(300, rng=rng)
    dcm = rot.as_matrix()
    q = rotations.q_from_dcm(dcm)
    assert q.shape == (300, 4)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=1e-15)
    scipy_q = rot.as_quat()
    same_sign = np.where(scipy_q[:, 3:] < 0, -scipy_q, scipy_q)
    np.testing.assert_allclose(q, same_sign, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rotations.dcm_from_q(q), dcm, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rotations.dcm_from_q(-q), dcm, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rotations.dcm_from_q(3.0 * q), dcm, rtol=0, atol=1e-14)  # normalised
    # v_a = dcm_a_from_b @ v_b and q_a_from_b rotate a body vector the same way
    v_b = rng.normal(size=(300, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rotations.dcm_from_q(q), v_b),
                               Rotation.from_quat(q).apply(v_b), rtol=0, atol=1e-14)
    assert rotations.q_from_dcm(dcm[0]).shape == (4,)
    assert rotations.dcm_from_q(q[0]).shape == (3, 3)


def test_quaternion_scalar_last() -> None:
    # 90 degrees about +Z, scalar last: (0, 0, sin 45, cos 45)
    q = rotations.q_from_dcm(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(q, [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], rtol=0, atol=1e-15)


def test_dcm_from_q_is_scipy_bit_for_bit() -> None:
    """Same bits as scipy for unit, non-unit and single quaternions (trajectories and detections
    computed before the helpers moved here are reproduced exactly)."""
    rng = np.random.default_rng(6)
    q = rng.normal(size=(2000, 4))
    q[:1000] /= np.linalg.norm(q[:1000], axis=1, keepdims=True)
    expected = Rotation.from_quat(q).as_matrix()
    np.testing.assert_array_equal(rotations.dcm_from_q(q), expected)
    np.testing.assert_array_equal(rotations.dcm_from_q(q.reshape(40, 50, 4)),
                                  expected.reshape(40, 50, 3, 3))
    for k in range(0, 2000, 97):
        np.testing.assert_array_equal(rotations.dcm_from_q(q[k]), expected[k])


def test_quaternion_product_exponential_and_skew_match_scipy() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        p, q = Rotation.random(2, rng=rng).as_quat()
        np.testing.assert_allclose(rotations.dcm_from_q(rotations.q_multiply(p, q)),
                                   (Rotation.from_quat(p) * Rotation.from_quat(q)).as_matrix(),
                                   atol=1e-15)
        v, a = rng.normal(size=(2, 3))
        np.testing.assert_allclose(rotations.skew(v) @ a, np.cross(v, a), rtol=0, atol=1e-15)
    v = rng.normal(size=(7, 3))
    np.testing.assert_array_equal(rotations.skew(v)[3], rotations.skew(v[3]))
    for angle in (0.0, 1e-9, 1e-5, 1e-4, 2e-4, 0.3, 3.0):
        theta = angle * np.array([0.48, -0.6, 0.64])
        np.testing.assert_allclose(rotations.dcm_from_q(rotations.q_exp(theta)),
                                   Rotation.from_rotvec(theta).as_matrix(), atol=1e-16)
    q = Rotation.random(rng=rng).as_quat()
    q = q if q[3] < 0 else -q
    np.testing.assert_array_equal(rotations.positive_scalar(q), -q)
