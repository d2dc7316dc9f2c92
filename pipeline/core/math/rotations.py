"""Rotation helpers: scalar-last Hamilton quaternions `q_a_from_b` (x, y, z, w) as scipy and Rerun,
DCMs `dcm_a_from_b` with `v_a = dcm_a_from_b @ v_b`, and body-frame rotation vectors (rad).

`dcm_from_q`, `q_multiply`, `q_exp` and `skew` are written out in numpy: a scipy `Rotation`
costs ~20 us per call inside the estimators' Gauss-Newton loops. `dcm_from_q` does the same
arithmetic as scipy's `Rotation.from_quat(q).as_matrix()` (normalise, then the standard
formula), so it returns the same bits.
"""

from __future__ import annotations

import math

import numpy as np

# below this angle (rad) q_exp takes sin(a / 2) / a as its series 1/2 - a^2 / 48 (error < 1e-19)
Q_EXP_SERIES_ANGLE_RAD = 1e-4


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for broadcast (..., 3) arrays, written out: np.cross costs ~10x more on the small
    arrays of an integrator step or one frame's craters."""
    a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2]
    b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a2 * b3 - a3 * b2, a3 * b1 - a1 * b3, a1 * b2 - a2 * b1], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x (..., 3, 3) of vectors (..., 3): skew(v) @ a == cross(v, a)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def dcm_from_q(q_a_from_b: np.ndarray) -> np.ndarray:
    """DCM (..., 3, 3) dcm_a_from_b of scalar-last quaternions (..., 4) q_a_from_b (normalised
    first)."""
    q = np.asarray(q_a_from_b, dtype=float)
    if q.ndim == 1:  # one quaternion: Python floats, the same operations as the batched branch
        x, y, z, w = q.tolist()
        n = math.sqrt(x * x + y * y + z * z + w * w)
        x, y, z, w = x / n, y / n, z / n, w / n
        x2, y2, z2, w2 = x * x, y * y, z * z, w * w
        xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
        return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                         [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                         [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])
    x, y, z, w = np.moveaxis(q, -1, 0)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.stack([x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
                     2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
                     2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2], -1
                    ).reshape(*q.shape[:-1], 3, 3)


def q_from_dcm(dcm_a_from_b: np.ndarray) -> np.ndarray:
    """Scalar-last quaternion (..., 4) q_a_from_b of DCMs (..., 3, 3); sign chosen with w >= 0."""
    from scipy.spatial.transform import Rotation  # lazy: not paid by commands that never call this
    q = Rotation.from_matrix(dcm_a_from_b).as_quat()
    return np.where(q[..., 3:4] < 0, -q, q)


def q_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q of scalar-last quaternions, (4,) or broadcast (..., 4):
    dcm(p * q) = dcm(p) @ dcm(q)."""
    if p.ndim == 1 and q.ndim == 1:  # one pair: Python floats (the estimators' inner loop)
        x1, y1, z1, w1 = p.tolist()
        x2, y2, z2, w2 = q.tolist()
        return np.array([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                         w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                         w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
                         w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2])
    x1, y1, z1, w1 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    x2, y2, z2, w2 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2],
                    axis=-1)


def q_exp(theta_rad: np.ndarray) -> np.ndarray:
    """Unit scalar-last quaternion of the rotation vector theta (rad), (4,) of (3,) or (..., 4) of
    (..., 3): dcm = Exp([theta]x)."""
    if theta_rad.ndim > 1:
        angle = np.sqrt(np.einsum("...i,...i->...", theta_rad, theta_rad))
        half = 0.5 * angle
        small = angle <= Q_EXP_SERIES_ANGLE_RAD
        k = np.where(small, 0.5 - angle * angle / 48.0,
                     np.sin(half) / np.where(small, 1.0, angle))
        return np.concatenate([k[..., None] * theta_rad, np.cos(half)[..., None]], axis=-1)
    angle = math.sqrt(float(theta_rad @ theta_rad))
    half = 0.5 * angle
    k = math.sin(half) / angle if angle > Q_EXP_SERIES_ANGLE_RAD else 0.5 - angle * angle / 48.0
    return np.array([k * theta_rad[0], k * theta_rad[1], k * theta_rad[2], math.cos(half)])


def q_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector (..., 3) (rad, angle in [0, pi]) of scalar-last quaternions (..., 4): the
    inverse of `q_exp`, q_exp(q_log(q)) = +-q."""
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    vec_norm = np.sqrt(np.einsum("...i,...i->...", q[..., :3], q[..., :3]))
    angle = 2.0 * np.arctan2(vec_norm, q[..., 3])
    # angle / sin(angle / 2) -> 2 (1 + angle^2 / 24) for small angles
    small = vec_norm < 1e-8
    k = np.where(small, 2.0 / np.where(small, q[..., 3], 1.0),
                 angle / np.where(small, 1.0, vec_norm))
    return k[..., None] * q[..., :3]


def positive_scalar(q: np.ndarray) -> np.ndarray:
    """The sign of a quaternion (4,) with w >= 0 (the same rotation)."""
    return -q if q[3] < 0 else q
